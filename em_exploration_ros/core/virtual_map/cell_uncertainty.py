"""Virtual map uncertainty: per-cell covariances of virtual landmarks.

Every cell of the virtual map holds a virtual landmark ``v`` at its centre (map frame, the
cell layout of :class:`~em_exploration_ros.core.virtual_map.occupancy.GridGeometry`). A robot
pose ``x = (x [m], y [m], theta [rad])`` observes the cell when the centre lies within the
sonar range (the rule of :func:`~em_exploration_ros.core.virtual_map.occupancy.observation_pairs`),
through the bearing-range model ``g(x, v) = (bearing [rad], range [m])``.

Covariance of one observation (inverse sensor model)::

    Sigma_v = Hl^+ (Hx Sigma_x Hx^T + R) Hl^+^T,    R = diag(sigma_bearing^2, sigma_range^2)

with ``Hx`` (2x3) and ``Hl`` (2x2) the Jacobians of ``g`` w.r.t. the pose and the point,
rows ordered (bearing, range), and ``Hl^+`` the pseudo-inverse of ``Hl`` (its inverse:
``det Hl = -1/range``). The paper writes ``H Sigma_x H^T``; like the authors' reference
implementation we add the sonar noise ``R`` and map the result into the point's
coordinates through ``Hl^+``, so ``Sigma_v`` is a (2x2, [m^2]) map-frame position
covariance. In closed form, with ``d = (dx, dy) = v - (x, y)`` and ``r = |d|``::

    Hl^+ Hx        = -[[1, 0, -dy], [0, 1, dx]]      (additive map-frame pose errors)
    Hl^+ R Hl^+^T  = sigma_bearing^2 (-dy, dx)(-dy, dx)^T + sigma_range^2 d d^T / r^2

(for body-frame pose errors the first two columns are rotated by the heading). At a
distance below :data:`MIN_RANGE_M` the range direction is taken along the map x axis.

Several observations of one cell are fused by covariance intersection (Julier and
Uhlmann): ``I = sum_k w_k I_k`` with ``I_k = Sigma_k^-1`` and convex weights ``w_k``. Any
convex weights give a consistent result whatever the (unknown) correlation between the
observations, which all share the SLAM estimate. We use the fast information-proportional
weights ``w_k = det(I_k) / sum_j det(I_j)`` (a closed form for any number of inputs,
no per-cell optimisation): the more certain observations dominate. Cells never observed
keep the prior ``sigma0^2 I`` (``MapParams.virtual_landmark_prior_sigma_m``).

Everything is vectorized over (pose, cell) pairs with closed-form 2x2 algebra; pose
covariances may be given in the map frame (additive ``(x, y, theta)`` errors) or in the
GTSAM ``Pose2`` tangent (body) frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.virtual_map.occupancy import GridGeometry, observation_pairs
from em_exploration_ros.core.params import MapParams, SensorParams

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Frame of pose covariances: ``"map"`` (additive map-frame errors) or ``"body"`` (GTSAM
#: ``Pose2`` tangent space, x and y along the pose's own axes).
CovarianceFrame = Literal["map", "body"]

#: Below this pose-to-cell distance [m] the range direction is taken along map x.
MIN_RANGE_M = 1e-3


def inverse_2x2(matrices: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Closed-form inverses and determinants of 2x2 matrices ``(..., 2, 2)``.

    Returns ``(inverse (..., 2, 2), determinant (...))``; singular inputs give inf/nan.
    """
    m = np.asarray(matrices, dtype=float)
    a, b, c, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1]
    det = a * d - b * c
    inverse = np.stack([np.stack([d, -b], axis=-1), np.stack([-c, a], axis=-1)], axis=-2)
    return inverse / det[..., None, None], det


def position_gain(poses: ArrayLike, covariance_frame: CovarianceFrame = "map") -> FloatArray:
    """The first two columns ``(K, 2, 2)`` of ``G = Hl^+ Hx`` (see
    :func:`inverse_sensor_model`): they depend on the pose only, not on the point."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    gain = np.zeros((len(poses), 2, 2))
    if covariance_frame == "body":
        cos_t, sin_t = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        gain[:, 0, 0], gain[:, 0, 1] = -cos_t, sin_t
        gain[:, 1, 0], gain[:, 1, 1] = -sin_t, -cos_t
    else:
        gain[:, 0, 0] = gain[:, 1, 1] = -1.0
    return gain


def inverse_sensor_model(poses: ArrayLike, points: ArrayLike,
                         sensor_params: SensorParams,
                         covariance_frame: CovarianceFrame = "map"
                         ) -> tuple[FloatArray, FloatArray]:
    """``(G, N)`` of the observation of points ``(P, 2)`` from poses ``(P, 3)`` (map frame):
    ``Sigma_v = G Sigma_x G^T + N`` with ``G = Hl^+ Hx`` ``(P, 2, 3)`` for pose covariances
    in ``covariance_frame`` and ``N = Hl^+ R Hl^+^T`` ``(P, 2, 2)`` [m^2]."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    lever, noise = _lever_and_noise(poses, points, sensor_params)
    gain = np.empty((len(poses), 2, 3))
    gain[:, :, :2] = position_gain(poses, covariance_frame)
    gain[:, :, 2] = lever.T
    return gain, noise


def _lever_and_noise(poses: FloatArray, points: ArrayLike,
                     sensor_params: SensorParams) -> tuple[FloatArray, FloatArray]:
    """The point-dependent parts of :func:`inverse_sensor_model`: the last column of ``G``,
    ``(dy, -dx)`` ``(2, P)`` [m], and ``N`` ``(P, 2, 2)`` [m^2]."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    dx = points[:, 0] - poses[:, 0]
    dy = points[:, 1] - poses[:, 1]
    distance = np.hypot(dx, dy)
    near = distance < MIN_RANGE_M
    ux = np.where(near, 1.0, dx / np.where(near, 1.0, distance))
    uy = np.where(near, 0.0, dy / np.where(near, 1.0, distance))
    bearing_var = sensor_params.sonar_bearing_sigma_rad ** 2
    range_var = sensor_params.sonar_range_sigma_m ** 2
    noise = np.empty((len(poses), 2, 2))
    noise[:, 0, 0] = bearing_var * dy * dy + range_var * ux * ux
    noise[:, 0, 1] = noise[:, 1, 0] = -bearing_var * dx * dy + range_var * ux * uy
    noise[:, 1, 1] = bearing_var * dx * dx + range_var * uy * uy
    return np.stack([dy, -dx]), noise


def _cell_matrices(entries: FloatArray) -> FloatArray:
    """Symmetric 2x2 matrices ``(..., 2, 2)`` from their entries ``(..., 3)`` (xx, xy, yy)."""
    xx, xy, yy = entries[..., 0], entries[..., 1], entries[..., 2]
    return np.stack([np.stack([xx, xy], axis=-1), np.stack([xy, yy], axis=-1)], axis=-2)


@dataclass(frozen=True)
class CovarianceIntersectionSums:
    """Per-cell accumulators of covariance intersection: the total weight ``(..., C)`` and
    the weighted information entries ``(..., C, 3)`` (xx, xy, yy) [1/m^2]; leading
    dimensions hold several independent sets (e.g. one per EM candidate). Sums over
    disjoint sets of observations add up; the fused information is their ratio."""

    weight: FloatArray
    weighted_information: FloatArray

    def __add__(self, other: "CovarianceIntersectionSums") -> "CovarianceIntersectionSums":
        return CovarianceIntersectionSums(self.weight + other.weight,
                                          self.weighted_information + other.weighted_information)

    def __sub__(self, other: "CovarianceIntersectionSums") -> "CovarianceIntersectionSums":
        """The sums without the observations ``other`` holds (a subset of these)."""
        return CovarianceIntersectionSums(self.weight - other.weight,
                                          self.weighted_information - other.weighted_information)

    @property
    def observed(self) -> NDArray[np.bool_]:
        """Cells ``(..., C)`` with at least one observation."""
        return self.weight > 0.0

    def information_entries(self) -> FloatArray:
        """Fused information entries ``(..., C, 3)`` (xx, xy, yy), zero for unobserved
        cells."""
        scale = np.divide(1.0, self.weight, out=np.zeros_like(self.weight),
                          where=self.observed)
        return self.weighted_information * scale[..., None]

    def information(self) -> FloatArray:
        """Fused information ``(..., C, 2, 2)`` [1/m^2], zero for unobserved cells."""
        return _cell_matrices(self.information_entries())

    def covariance_traces(self) -> FloatArray:
        """``trace(Sigma)`` [m^2] of the fused covariance of each cell ``(..., C)``
        (A-optimality); 0 for unobserved cells."""
        info = self.information_entries()
        det = info[..., 0] * info[..., 2] - info[..., 1] ** 2
        return np.divide(info[..., 0] + info[..., 2], det, out=np.zeros_like(det),
                         where=self.observed)

    def __getitem__(self, index: int) -> "CovarianceIntersectionSums":
        """The sums of set ``index`` along the first leading dimension."""
        return CovarianceIntersectionSums(self.weight[index], self.weighted_information[index])

    @classmethod
    def stack(cls, sums: Sequence["CovarianceIntersectionSums"]
              ) -> "CovarianceIntersectionSums":
        """Sets of the same cells stacked along a new first dimension."""
        return cls(np.stack([s.weight for s in sums]),
                   np.stack([s.weighted_information for s in sums]))


def _intersection_sums(cell_index: IntArray, entries: FloatArray,
                       num_cells: int) -> CovarianceIntersectionSums:
    """Covariance-intersection sums of 2x2 covariances given by entries ``(3, P)`` (xx, xy,
    yy), with weights ``det(Sigma)^-1 = det(I)`` (information-proportional)."""
    xx, xy, yy = entries
    weight = 1.0 / (xx * yy - xy * xy)
    # weight * information = weight * adj(Sigma) / det(Sigma) = adj(Sigma) * weight^2
    factor = weight * weight

    def cell_sum(value: FloatArray) -> FloatArray:
        sums = np.bincount(cell_index, weights=value, minlength=num_cells)
        return sums.astype(float, copy=False)  # integer when there is no pair

    return CovarianceIntersectionSums(
        cell_sum(weight),
        np.stack([cell_sum(factor * yy), cell_sum(-factor * xy), cell_sum(factor * xx)],
                 axis=-1))


@dataclass(frozen=True)
class CellObservations:
    """Pose-independent part of the (pose, cell) observations of a set of poses.

    For pair ``p`` (pose ``pose_index[p]`` observing cell ``flat_cell[p]``: the cell's flat
    index ``row * cols + col``, or its slot when the observations were built for a subset of
    the cells, see :meth:`from_poses`) the virtual landmark covariance is
    ``G Sigma_x G^T + N`` (see :func:`inverse_sensor_model`). ``G = [B | l]`` splits into a
    block ``B`` that depends on the pose only (``position_gain`` ``(K, 2, 2)``) and the lever
    ``l = (dy, -dx)`` of the pair (``lever`` ``(2, P)`` [m]); with ``Sigma_x`` split into
    its position block ``S``, position-heading column ``s`` and heading variance ``t``::

        G Sigma_x G^T = B S B^T + (B s) l^T + l (B s)^T + t l l^T

    so a pose covariance hypothesis costs three small per-pose products and a few
    multiply-adds per pair. ``noise`` ``(3, P)`` holds the entries (xx, xy, yy) of ``N``
    [m^2]. Built once per set of poses, so that many pose covariance hypotheses (EM
    candidates) are evaluated with array algebra only.
    """

    pose_index: IntArray
    flat_cell: IntArray
    lever: FloatArray
    noise: FloatArray
    position_gain: FloatArray

    @property
    def num_poses(self) -> int:
        """Number of poses the covariances passed in are given for."""
        return len(self.position_gain)

    @classmethod
    def from_poses(cls, geometry: GridGeometry, poses: ArrayLike, sensor_params: SensorParams,
                   covariance_frame: CovarianceFrame = "map",
                   cell_slots: IntArray | None = None) -> "CellObservations":
        """Observations of every cell whose centre is within sonar range of a pose.

        Args:
            geometry: virtual map cell layout.
            poses: (K, 3) map-frame poses ``(x [m], y [m], theta [rad])``.
            sensor_params: sonar range and bearing/range noise.
            covariance_frame: frame of the pose covariances that will be supplied.
            cell_slots: optional ``(rows * cols,)`` accumulator slot of every cell, -1 for a
                cell left out. The pairs of left-out cells are dropped and ``flat_cell``
                holds slots, so that sums over a subset of the map (the cells a utility
                counts) cost nothing for the other cells. Default: every cell, slot = flat
                index.
        """
        poses = np.asarray(poses, dtype=float).reshape(-1, 3)
        pose_index, flat_cell = observation_pairs(geometry, poses, sensor_params.sonar_max_range_m)
        slot = flat_cell
        if cell_slots is not None:
            slot = np.asarray(cell_slots, dtype=np.int64)[flat_cell]
            kept = slot >= 0
            pose_index, flat_cell, slot = pose_index[kept], flat_cell[kept], slot[kept]
        centres = geometry.cell_center(np.stack(np.divmod(flat_cell, geometry.cols), axis=-1))
        lever, noise = _lever_and_noise(poses[pose_index], centres, sensor_params)
        return cls(pose_index, slot, lever, np.ascontiguousarray(noise[:, [0, 0, 1], [0, 1, 1]].T),
                   position_gain(poses, covariance_frame))

    def of_poses(self, selected: NDArray[np.bool_]) -> "CellObservations":
        """The observations of the poses where ``selected`` ``(num_poses,)`` is True, pose
        numbering kept (covariances are still given for all ``num_poses``)."""
        keep = np.asarray(selected, dtype=bool)[self.pose_index]
        return CellObservations(self.pose_index[keep], self.flat_cell[keep],
                                self.lever[:, keep], self.noise[:, keep], self.position_gain)

    def _pair_entries(self, pose_covariances: ArrayLike) -> FloatArray:
        """Cell covariance entries ``(3, P)`` (xx, xy, yy) [m^2] of every pair."""
        covariances = np.asarray(pose_covariances, dtype=float).reshape(-1, 3, 3)
        gain = self.position_gain
        position = gain @ covariances[:, :2, :2] @ np.swapaxes(gain, 1, 2)
        heading = gain @ covariances[:, :2, 2:]
        per_pose = np.stack([position[:, 0, 0], position[:, 0, 1], position[:, 1, 1],
                             heading[:, 0, 0], heading[:, 1, 0], covariances[:, 2, 2]])
        p_xx, p_xy, p_yy, h_x, h_y, t = np.take(per_pose, self.pose_index, axis=1)
        l_x, l_y = self.lever
        entries = np.empty_like(self.noise)
        xx, xy, yy = entries  # filled in place: this runs for every EM candidate
        np.multiply(t, l_x, out=xx)  # xx = p_xx + l_x (2 h_x + t l_x)
        xx += h_x
        xx += h_x
        xx *= l_x
        xx += p_xx
        np.multiply(t, l_y, out=yy)  # yy = p_yy + l_y (2 h_y + t l_y)
        yy += h_y
        yy += h_y
        yy *= l_y
        yy += p_yy
        np.multiply(t, l_y, out=xy)  # xy = p_xy + h_x l_y + l_x (h_y + t l_y)
        xy += h_y
        xy *= l_x
        h_x *= l_y
        xy += h_x
        xy += p_xy
        entries += self.noise
        return entries

    def intersection_sums(self, pose_covariances: ArrayLike,
                          num_cells: int) -> CovarianceIntersectionSums:
        """Covariance-intersection accumulators ``(num_cells,)`` of these observations."""
        return _intersection_sums(self.flat_cell, self._pair_entries(pose_covariances),
                                  num_cells)

    def grouped_intersection_sums(self, pose_covariances: ArrayLike, pose_group: IntArray,
                                  num_groups: int,
                                  num_cells: int) -> CovarianceIntersectionSums:
        """Covariance-intersection accumulators ``(num_groups, num_cells)``, one set per
        group of poses (``pose_group`` ``(num_poses,)``: the group of each pose), in one
        pass; each set equals, to the last bit, that of its poses alone."""
        sums = _intersection_sums(self._grouped_cells(pose_group, num_cells),
                                  self._pair_entries(pose_covariances), num_groups * num_cells)
        return CovarianceIntersectionSums(sums.weight.reshape(num_groups, num_cells),
                                          sums.weighted_information.reshape(
                                              num_groups, num_cells, 3))

    def grouped_counts(self, pose_group: IntArray, num_groups: int,
                       num_cells: int) -> IntArray:
        """Observations of each cell ``(num_groups, num_cells)`` by each group of poses
        (``pose_group`` as for :meth:`grouped_intersection_sums`)."""
        return np.bincount(self._grouped_cells(pose_group, num_cells),
                           minlength=num_groups * num_cells).reshape(num_groups, num_cells)

    def _grouped_cells(self, pose_group: IntArray, num_cells: int) -> IntArray:
        """Index ``group * num_cells + cell`` of every pair."""
        return np.asarray(pose_group, dtype=np.int64)[self.pose_index] * num_cells \
            + self.flat_cell

    def fused_information(self, pose_covariances: ArrayLike,
                          num_cells: int) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Covariance-intersection information ``(num_cells, 2, 2)`` [1/m^2] of every cell
        and the mask ``(num_cells,)`` of observed cells (unobserved rows are zero)."""
        sums = self.intersection_sums(pose_covariances, num_cells)
        return sums.information(), sums.observed


def information_to_covariance(information: ArrayLike, observed: ArrayLike,
                              prior_sigma_m: float) -> FloatArray:
    """Cell covariances ``(..., 2, 2)`` [m^2]: the inverse of ``information`` where
    ``observed``, the prior ``prior_sigma_m^2 I`` elsewhere."""
    information = np.asarray(information, dtype=float)
    observed = np.asarray(observed, dtype=bool)
    prior = prior_sigma_m ** 2 * np.eye(2)
    safe = np.where(observed[..., None, None], information, np.eye(2))
    covariance, _ = inverse_2x2(safe)
    return np.where(observed[..., None, None], covariance, prior)


def cell_covariances_from_poses(geometry: GridGeometry, poses: ArrayLike,
                                pose_covariances: ArrayLike, sensor_params: SensorParams,
                                map_params: MapParams,
                                covariance_frame: CovarianceFrame = "map"
                                ) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Virtual map of a set of poses.

    Args:
        geometry: virtual map cell layout.
        poses: (K, 3) map-frame poses; pose_covariances: (K, 3, 3) in ``covariance_frame``.
        sensor_params: sonar range and noise; map_params: prior sigma of unobserved cells.

    Returns:
        ``(covariances (rows, cols, 2, 2) [m^2], observed (rows, cols))``.
    """
    observations = CellObservations.from_poses(geometry, poses, sensor_params, covariance_frame)
    num_cells = geometry.rows * geometry.cols
    information, observed = observations.fused_information(pose_covariances, num_cells)
    covariance = information_to_covariance(information, observed,
                                           map_params.virtual_landmark_prior_sigma_m)
    return covariance.reshape(geometry.shape + (2, 2)), observed.reshape(geometry.shape)


def observation_confidence(counts: ArrayLike, map_params: MapParams) -> FloatArray:
    """Probability ``q`` that a cell counts as observed, from the number of poses (any
    shape) that saw it: the occupancy probability ``p`` of the log-odds free update
    ``counts * logit(prob_free)`` clamped to ``[prob_min, prob_max]``, as
    ``q = max(p, 1 - p)`` (0.5 for an unseen cell). With the symmetric defaults
    (free 0.3, occupied 0.7) a landmark cell gets the same ``q``."""
    counts = np.asarray(counts, dtype=float)
    logit = np.log(map_params.prob_free / (1.0 - map_params.prob_free))
    low = np.log(map_params.prob_min / (1.0 - map_params.prob_min))
    high = np.log(map_params.prob_max / (1.0 - map_params.prob_max))
    probability = 1.0 / (1.0 + np.exp(-np.clip(counts * logit, low, high)))
    return np.maximum(probability, 1.0 - probability)
