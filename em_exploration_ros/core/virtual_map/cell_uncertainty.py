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

#: Upper-triangle entries ``(j, k)`` of a 3x3 pose covariance, and of a 2x2 cell covariance.
_POSE_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_CELL_ENTRIES = ((0, 0), (0, 1), (1, 1))


def inverse_2x2(matrices: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Closed-form inverses and determinants of 2x2 matrices ``(..., 2, 2)``.

    Returns ``(inverse (..., 2, 2), determinant (...))``; singular inputs give inf/nan.
    """
    m = np.asarray(matrices, dtype=float)
    a, b, c, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1]
    det = a * d - b * c
    inverse = np.stack([np.stack([d, -b], axis=-1), np.stack([-c, a], axis=-1)], axis=-2)
    return inverse / det[..., None, None], det


def inverse_sensor_model(poses: ArrayLike, points: ArrayLike,
                         sensor_params: SensorParams,
                         covariance_frame: CovarianceFrame = "map"
                         ) -> tuple[FloatArray, FloatArray]:
    """``(G, N)`` of the observation of points ``(P, 2)`` from poses ``(P, 3)`` (map frame):
    ``Sigma_v = G Sigma_x G^T + N`` with ``G = Hl^+ Hx`` ``(P, 2, 3)`` for pose covariances
    in ``covariance_frame`` and ``N = Hl^+ R Hl^+^T`` ``(P, 2, 2)`` [m^2]."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    dx = points[:, 0] - poses[:, 0]
    dy = points[:, 1] - poses[:, 1]
    gain = np.zeros((len(poses), 2, 3))
    if covariance_frame == "body":
        cos_t, sin_t = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        gain[:, 0, 0], gain[:, 0, 1] = -cos_t, sin_t
        gain[:, 1, 0], gain[:, 1, 1] = -sin_t, -cos_t
    else:
        gain[:, 0, 0] = gain[:, 1, 1] = -1.0
    gain[:, 0, 2] = dy
    gain[:, 1, 2] = -dx
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
    return gain, noise


def _pose_entries(covariances: FloatArray) -> FloatArray:
    """Upper-triangle entries ``(K, 6)`` of symmetric 3x3 matrices ``(K, 3, 3)``."""
    rows, cols = zip(*_POSE_ENTRIES)
    return covariances[:, rows, cols]


def _cell_matrices(entries: FloatArray) -> FloatArray:
    """Symmetric 2x2 matrices ``(..., 2, 2)`` from their entries ``(..., 3)`` (xx, xy, yy)."""
    xx, xy, yy = entries[..., 0], entries[..., 1], entries[..., 2]
    return np.stack([np.stack([xx, xy], axis=-1), np.stack([xy, yy], axis=-1)], axis=-2)


def _quadratic_form_coefficients(gain: FloatArray) -> FloatArray:
    """``(P, 3, 6)`` linear map from the pose covariance entries (``_POSE_ENTRIES``) to the
    entries (xx, xy, yy) of ``G Sigma_x G^T`` for gains ``G`` ``(P, 2, 3)``: an
    off-diagonal pose entry ``(j, k)`` stands for both ``(j, k)`` and ``(k, j)``."""
    rows = [[np.ascontiguousarray(gain[:, a, j]) for j in range(3)] for a in range(2)]
    columns = []
    for a, b in _CELL_ENTRIES:
        for j, k in _POSE_ENTRIES:
            term = rows[a][j] * rows[b][k]
            columns.append(term + rows[a][k] * rows[b][j] if j != k else term)
    return np.stack(columns, axis=-1).reshape(-1, 3, 6)


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
    """Covariance-intersection sums of 2x2 covariances given by entries ``(P, 3)``, with
    weights ``det(Sigma)^-1 = det(I)`` (information-proportional)."""
    xx, xy, yy = entries[:, 0], entries[:, 1], entries[:, 2]
    weight = 1.0 / (xx * yy - xy * xy)
    # weight * information = weight * adj(Sigma) / det(Sigma) = adj(Sigma) * weight^2
    factor = weight * weight

    def cell_sum(value: FloatArray) -> FloatArray:
        return np.bincount(cell_index, weights=value, minlength=num_cells).astype(float)

    return CovarianceIntersectionSums(
        cell_sum(weight),
        np.stack([cell_sum(factor * yy), cell_sum(-factor * xy), cell_sum(factor * xx)],
                 axis=-1))


@dataclass(frozen=True)
class CellObservations:
    """Pose-independent part of the (pose, cell) observations of a set of poses.

    For pair ``p`` (pose ``pose_index[p]`` observing cell ``flat_cell[p]``: the cell's flat
    index ``row * cols + col``, or its slot when the observations were built for a subset of
    the cells, see :meth:`from_poses`) the virtual landmark covariance ``G Sigma_x G^T + N`` (see
    :func:`inverse_sensor_model`) is stored linearly in the pose covariance entries:
    ``coefficients`` ``(P, 3, 6)`` maps the 6 upper-triangle entries of ``Sigma_x`` to the 3
    entries (xx, xy, yy) of the cell covariance, ``noise`` ``(P, 3)`` holds those of ``N``
    [m^2]. Built once per set of poses, so that many pose covariance hypotheses (EM
    candidates) are evaluated with array algebra only.
    """

    pose_index: IntArray
    flat_cell: IntArray
    coefficients: FloatArray
    noise: FloatArray
    num_poses: int

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
        gain, noise = inverse_sensor_model(poses[pose_index], centres, sensor_params,
                                           covariance_frame)
        return cls(pose_index, slot, _quadratic_form_coefficients(gain),
                   noise[:, [0, 0, 1], [0, 1, 1]], len(poses))

    def of_poses(self, selected: NDArray[np.bool_]) -> "CellObservations":
        """The observations of the poses where ``selected`` ``(num_poses,)`` is True, pose
        numbering kept (covariances are still given for all ``num_poses``)."""
        keep = np.asarray(selected, dtype=bool)[self.pose_index]
        return CellObservations(self.pose_index[keep], self.flat_cell[keep],
                                self.coefficients[keep], self.noise[keep], self.num_poses)

    def _pair_entries(self, pose_covariances: ArrayLike) -> FloatArray:
        """Cell covariance entries ``(P, 3)`` (xx, xy, yy) [m^2] of every pair."""
        entries = _pose_entries(np.asarray(pose_covariances, dtype=float).reshape(-1, 3, 3))
        return np.einsum("pqu,pu->pq", self.coefficients, entries[self.pose_index]) + self.noise

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
