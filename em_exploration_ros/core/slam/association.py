"""Data association of one robot's sonar detections when they carry no landmark identity
(``sensors.landmark_ids`` false): the individual Mahalanobis gate, joint compatibility
branch and bound (JCBB) over one scan, and tentative tracks that become landmarks only once
seen consistently.

Frames and units: the ``map`` frame. A pose is ``(x [m], y [m], theta [rad])`` with the
``(3, 3)`` covariance of its additive coordinate errors; a landmark is a point ``(x, y)
[m]`` with its ``(2, 2)`` marginal covariance [m^2]; a detection is ``(bearing [rad, body
frame], range [m])``, GTSAM's BearingRange order, with its ``(2, 2)`` noise covariance
[rad^2, m^2]. Tentative tracks are in whatever frame the caller's poses are (a robot's
dead-reckoned odometry frame). Everything here is plain NumPy on arrays: the robot's SLAM
supplies the prediction (``ScanPrediction``) and turns the answers into graph landmarks.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from em_exploration_ros.core.geometry import wrap_angle

FloatArray = NDArray[np.float64]

#: One detection's answer: the row of the landmark it is paired with, or None.
Pairing = int | None


@functools.lru_cache(maxsize=256)
def chi2_quantile(dof: int, probability: float) -> float:
    """The ``probability`` quantile of the chi-square distribution with ``dof`` degrees of
    freedom (two per detection; three for a relative pose), by bisection on its closed-form
    CDF: ``1 - exp(-x/2) sum_{i<dof/2} (x/2)^i / i!`` for an even ``dof``, ``erf(sqrt(x/2))
    - sqrt(2x/pi) exp(-x/2) sum_{i<(dof-1)/2} x^i / (3 5 ... (2i+1))`` for an odd one."""
    if dof <= 0:
        raise ValueError(f"dof must be positive, got {dof}")
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")

    def cdf(x: float) -> float:
        if dof % 2 == 0:
            half, term, total = x / 2.0, 1.0, 1.0
            for i in range(1, dof // 2):
                term *= half / i
                total += term
            return 1.0 - math.exp(-half) * total
        term, total = 1.0, 0.0
        for i in range((dof - 1) // 2):
            total += term
            term *= x / (2 * i + 3)
        return math.erf(math.sqrt(x / 2.0)) \
            - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0) * total

    low, high = 0.0, 1.0
    while cdf(high) < probability:
        high *= 2.0
    for _ in range(100):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if cdf(middle) < probability else (low, middle)
    return high


def predict_measurements(pose: FloatArray, points: FloatArray
                         ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted ``(bearing, range)`` ``(L, 2)`` of points ``(L, 2)`` seen from ``pose``
    ``(3,)``, with their Jacobians with respect to the pose ``(L, 2, 3)`` and to the point
    ``(L, 2, 2)``."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    dx, dy = points[:, 0] - pose[0], points[:, 1] - pose[1]
    squared = np.maximum(dx * dx + dy * dy, 1e-12)
    ranges = np.sqrt(squared)
    predicted = np.stack([wrap_angle(np.arctan2(dy, dx) - pose[2]), ranges], axis=1)
    point_jacobian = np.stack([np.stack([-dy / squared, dx / squared], axis=1),
                               np.stack([dx / ranges, dy / ranges], axis=1)], axis=1)
    pose_jacobian = np.concatenate(
        [-point_jacobian, np.stack([-np.ones_like(ranges), np.zeros_like(ranges)],
                                   axis=1)[:, :, None]], axis=2)
    return predicted, pose_jacobian, point_jacobian


def detection_points(pose: FloatArray, pose_covariance: FloatArray, measurements: FloatArray,
                     noise: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Map-frame points ``(D, 2)`` of detections ``(D, 2)`` (bearing, range) seen from
    ``pose`` and their covariances ``(D, 2, 2)`` to first order, from the pose's and the
    detections' own (``noise`` ``(D, 2, 2)``)."""
    measurements = np.asarray(measurements, dtype=float).reshape(-1, 2)
    angle = pose[2] + measurements[:, 0]
    distance = measurements[:, 1]
    cos, sin = np.cos(angle), np.sin(angle)
    points = np.stack([pose[0] + distance * cos, pose[1] + distance * sin], axis=1)
    ones, zeros = np.ones_like(distance), np.zeros_like(distance)
    pose_jacobian = np.stack([np.stack([ones, zeros, -distance * sin], axis=1),
                              np.stack([zeros, ones, distance * cos], axis=1)], axis=1)
    measurement_jacobian = np.stack([np.stack([-distance * sin, cos], axis=1),
                                     np.stack([distance * cos, sin], axis=1)], axis=1)
    covariances = (pose_jacobian @ pose_covariance @ np.swapaxes(pose_jacobian, 1, 2)
                   + measurement_jacobian @ noise @ np.swapaxes(measurement_jacobian, 1, 2))
    return points, covariances


def point_pose_jacobian(pose: FloatArray, point: FloatArray) -> FloatArray:
    """Jacobian ``(2, 3)`` of a map point fixed in the body of ``pose`` ``(3,)`` with
    respect to that pose's additive map-frame errors: a pose error moves the point by its
    translation and turns it about the pose by its heading error."""
    lever = np.asarray(point, dtype=float) - np.asarray(pose, dtype=float)[:2]
    return np.array([[1.0, 0.0, -lever[1]], [0.0, 1.0, lever[0]]])


@dataclass(frozen=True)
class ScanPrediction:
    """What a robot expects before it associates one scan: its pose at the scan ``(3,)``
    with covariance ``(3, 3)``, and the landmarks it may see, points ``(L, 2)`` with their
    marginal covariances ``(L, 2, 2)`` (map frame)."""

    pose: FloatArray
    pose_covariance: FloatArray
    points: FloatArray
    point_covariances: FloatArray


class ScanCompatibility:
    """The innovations of every detection of one scan against every predicted landmark,
    their individual normalized squared innovations (NIS), and the joint NIS of a set of
    pairings.

    The joint innovation covariance keeps the correlation that the shared robot pose gives
    the detections of one scan (``A_i P_x A_j^T`` between pairings ``i`` and ``j``) and
    takes the landmarks as independent (their marginals: no landmark cross-covariance).
    """

    def __init__(self, prediction: ScanPrediction, measurements: FloatArray,
                 noise: FloatArray) -> None:
        """``measurements`` ``(D, 2)`` (bearing, range), ``noise`` ``(D, 2, 2)``."""
        self.measurements = np.asarray(measurements, dtype=float).reshape(-1, 2)
        self.noise = np.asarray(noise, dtype=float).reshape(-1, 2, 2)
        predicted, self._pose_jacobians, point_jacobians = predict_measurements(
            prediction.pose, prediction.points)
        self._pose_covariance = np.asarray(prediction.pose_covariance, dtype=float)
        #: Landmark part of each pairing's innovation covariance, (L, 2, 2).
        self._point_parts = (point_jacobians @ prediction.point_covariances
                             @ np.swapaxes(point_jacobians, 1, 2))
        self._pose_parts = (self._pose_jacobians @ self._pose_covariance
                            @ np.swapaxes(self._pose_jacobians, 1, 2))
        innovations = self.measurements[:, None, :] - predicted[None, :, :]
        innovations[..., 0] = wrap_angle(innovations[..., 0])
        #: Innovation of detection d against landmark l, (D, L, 2).
        self.innovations = innovations
        covariances = (self._pose_parts + self._point_parts)[None] + self.noise[:, None]
        #: Individual NIS of detection d against landmark l, (D, L).
        self.nis = np.einsum("dli,dlij,dlj->dl", innovations, np.linalg.inv(covariances),
                             innovations) if innovations.size else np.zeros(
                                 (len(self.measurements), len(predicted)))

    @property
    def num_detections(self) -> int:
        """D, the detections of the scan."""
        return self.nis.shape[0]

    @property
    def num_landmarks(self) -> int:
        """L, the predicted landmarks."""
        return self.nis.shape[1]

    def joint_nis(self, pairs: Sequence[tuple[int, int]]) -> float:
        """NIS of the stacked innovations of ``pairs`` ``[(detection, landmark row), ...]``
        under their joint covariance; 0 for no pair."""
        if not pairs:
            return 0.0
        detections = np.array([d for d, _ in pairs])
        landmarks = np.array([row for _, row in pairs])
        jacobians = self._pose_jacobians[landmarks].reshape(-1, 3)
        joint = jacobians @ self._pose_covariance @ jacobians.T
        for k, (d, row) in enumerate(pairs):
            joint[2 * k:2 * k + 2, 2 * k:2 * k + 2] += self._point_parts[row] + self.noise[d]
        innovation = self.innovations[detections, landmarks].reshape(-1)
        return float(innovation @ np.linalg.solve(joint, innovation))


def jcbb(compatibility: ScanCompatibility, gate_probability: float) -> tuple[Pairing, ...]:
    """Joint compatibility branch and bound (Neira and Tardos, IEEE T-RA 2001) over one
    scan: for each detection, the row of its landmark or None (new landmark or clutter).

    This variant: the recursive search in detection order; a detection may pair with a
    landmark of its individual gate (NIS below the ``gate_probability`` quantile of
    chi-square with 2 degrees of freedom) that no earlier detection of the hypothesis took,
    and only while the hypothesis stays jointly compatible (joint NIS, recomputed in full at
    every node, below the quantile with 2k degrees of freedom for k pairings); the answer
    has the most pairings, the lowest joint NIS among those. The bound prunes a branch that
    can no longer reach the best number of pairings.
    """
    detections, landmarks = compatibility.num_detections, compatibility.num_landmarks
    gate = chi2_quantile(2, gate_probability)
    candidates = [sorted(range(landmarks), key=lambda row, d=d: compatibility.nis[d, row])
                  for d in range(detections)]
    candidates = [[row for row in rows if compatibility.nis[d, row] <= gate]
                  for d, rows in enumerate(candidates)]
    thresholds = [0.0] + [chi2_quantile(2 * k, gate_probability)
                          for k in range(1, detections + 1)]
    best: list = [(None,) * detections, 0, 0.0]  # hypothesis, pairings, joint NIS

    def search(index: int, hypothesis: list[Pairing], pairs: list[tuple[int, int]],
               nis: float) -> None:
        if index == detections:
            if len(pairs) > best[1] or (len(pairs) == best[1] and nis < best[2]):
                best[:] = [tuple(hypothesis), len(pairs), nis]
            return
        remaining = detections - index - 1
        taken = {row for _, row in pairs}
        if len(pairs) + 1 + remaining >= best[1]:
            for landmark in candidates[index]:
                if landmark in taken:
                    continue
                trial = pairs + [(index, landmark)]
                joint = compatibility.joint_nis(trial)
                if joint <= thresholds[len(trial)]:
                    search(index + 1, hypothesis + [landmark], trial, joint)
        if len(pairs) + remaining >= best[1]:
            search(index + 1, hypothesis + [None], pairs, nis)

    search(0, [], [], 0.0)
    return best[0]


@dataclass
class _Track:
    """A tentative landmark: its point ``(2,)`` fused from its sightings (in the frame of
    the robot's poses), its covariance ``(2, 2)`` given the robot's pose at its latest
    sighting, and the keyframe indices it was seen at."""

    point: FloatArray
    covariance: FloatArray
    #: sightings in the window that confirm it (the fewest any of its sightings asked for)
    confirm_hits: int
    seen_at: list[int] = field(default_factory=list)
    #: what the caller gave with each sighting, in the order of ``seen_at``
    sightings: list[Any] = field(default_factory=list)


@dataclass(frozen=True)
class RobotMotion:
    """Where a robot is at a keyframe, ``pose`` ``(3,)``, and how well it knows its motion
    since an earlier keyframe of its own: ``covariance_since(index)`` ``(3, 3)``, additive
    errors of ``pose`` given that keyframe's pose (both in one frame, such as its
    dead-reckoned odometry frame)."""

    pose: FloatArray
    covariance_since: Callable[[int], FloatArray]


class TentativeTracks:
    """Detections that match no landmark, kept until they are seen consistently.

    A track is a point ``(2,)`` with its covariance relative to the robot's pose at the
    keyframe that last saw it. At a later keyframe, the robot's motion since then
    (``RobotMotion``) widens it, moved to the point; a detection within the gate
    (Mahalanobis distance of its point to the track's, under the sum of their covariances,
    below the ``gate_probability`` quantile of chi-square with 2 degrees of freedom) is
    another sighting of it (each track takes at most one detection per keyframe, the
    nearest first); any other detection starts a track. A track seen at ``confirm_hits``
    of the last ``window_keyframes`` keyframes is confirmed: the caller makes it a
    landmark. A track not seen in the last ``window_keyframes`` keyframes is dropped.
    Clutter, uniform over the sonar's field of view, seldom falls twice within a gate of
    centimetres, so it does not become a landmark. A gate holding the motion of the whole
    window for every track, however lately seen, was about twice as wide: three clutter
    points 0.3 m apart made a landmark in the sparse scenario.
    """

    def __init__(self, confirm_hits: int, window_keyframes: int,
                 gate_probability: float) -> None:
        if not 1 <= confirm_hits <= window_keyframes:
            raise ValueError(f"need 1 <= confirm_hits <= window_keyframes, got {confirm_hits}, "
                             f"{window_keyframes}")
        self.confirm_hits = confirm_hits
        self.window_keyframes = window_keyframes
        self._gate = chi2_quantile(2, gate_probability)
        self._tracks: list[_Track] = []

    def __len__(self) -> int:
        """Tentative tracks held."""
        return len(self._tracks)

    def observe(self, index: int, points: FloatArray, covariances: FloatArray,
                sightings: Sequence[Any] | None = None,
                confirm_hits: Sequence[int] | None = None,
                motion: RobotMotion | None = None) -> list[tuple | None]:
        """Sightings at keyframe ``index`` (increasing between calls): points ``(U, 2)`` of
        detections that matched no landmark, seen from ``motion.pose``, and their
        covariances ``(U, 2, 2)`` given that pose (the sonar's noise), with what the caller
        gives with each (``sightings``, one per point; e.g. the keyframe and the reading)
        and how many sightings in the window confirm its track (``confirm_hits``, one per
        point; default ``self.confirm_hits``: a track needs the fewest any of its
        sightings asked for). ``motion`` None: the robot has not moved since any track was
        seen. Returns, per detection, None if it did not confirm its track at this
        keyframe, else what was given with the track's earlier sightings, oldest first (the
        track is then removed here: the caller adds the landmark at that detection and
        names those sightings' landmark too)."""
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        sightings = list(sightings) if sightings is not None else [None] * len(points)
        needs = (list(confirm_hits) if confirm_hits is not None
                 else [self.confirm_hits] * len(points))
        covariances = np.asarray(covariances, dtype=float).reshape(-1, 2, 2)
        self._tracks = [track for track in self._tracks
                        if track.seen_at[-1] > index - self.window_keyframes]
        predicted = [self._moved(track, motion) for track in self._tracks]
        distances = np.full((len(points), len(self._tracks)), np.inf)
        for t, (track, covariance) in enumerate(zip(self._tracks, predicted)):
            difference = points - track.point
            combined = np.linalg.inv(covariances + covariance)
            distances[:, t] = np.einsum("ui,uij,uj->u", difference, combined, difference)
        matched: dict[int, int] = {}
        for flat in np.argsort(distances, axis=None, kind="stable"):
            detection, track = np.unravel_index(flat, distances.shape)
            if distances[detection, track] > self._gate:
                break
            if detection not in matched and track not in matched.values():
                matched[int(detection)] = int(track)
        confirmed: list[tuple | None] = [None] * len(points)
        finished: set[int] = set()
        for detection in range(len(points)):
            if detection not in matched:
                self._tracks.append(_Track(points[detection], covariances[detection],
                                           needs[detection], [index], [sightings[detection]]))
                continue
            track = self._tracks[matched[detection]]
            track_information = np.linalg.inv(predicted[matched[detection]])
            detection_information = np.linalg.inv(covariances[detection])
            fused = np.linalg.inv(track_information + detection_information)
            track.point = fused @ (track_information @ track.point
                                   + detection_information @ points[detection])
            track.covariance = fused
            track.confirm_hits = min(track.confirm_hits, needs[detection])
            track.seen_at.append(index)
            track.sightings.append(sightings[detection])
            recent = [seen for seen in track.seen_at if seen > index - self.window_keyframes]
            if len(recent) >= track.confirm_hits:
                confirmed[detection] = tuple(track.sightings[:-1])
                finished.add(matched[detection])
        self._tracks = [track for t, track in enumerate(self._tracks) if t not in finished]
        return confirmed

    @staticmethod
    def _moved(track: _Track, motion: RobotMotion | None) -> FloatArray:
        """The track's covariance ``(2, 2)`` given the robot's pose now: its own plus the
        robot's motion since the track was last seen, moved to the track's point."""
        if motion is None:
            return track.covariance
        moved = point_pose_jacobian(motion.pose, track.point)
        return track.covariance + moved @ motion.covariance_since(track.seen_at[-1]) @ moved.T


def pairwise_consistency(offsets: FloatArray, offset_covariance: FloatArray,
                         gate_probability: float) -> np.ndarray:
    """Which pairs of correspondences ``a_i = b_i`` agree (``(N, N)`` bool, diagonal true):
    ``i`` and ``j`` do when the difference of their offsets ``e_i = a_i - b_i``, ``e_i -
    e_j``, is within the ``gate_probability`` chi-square gate (2 degrees of freedom) under
    its covariance, from the offsets' joint covariance. ``offsets`` ``(N, 2)`` [m], map
    frame; ``offset_covariance`` ``(2N, 2N)`` [m^2] (x, y of ``e_0``, then of ``e_1``, ...):
    drawn from one graph's joint marginals, a drift common to both points of a
    correspondence, or to two correspondences, cancels in it."""
    offsets = np.asarray(offsets, dtype=float).reshape(-1, 2)
    count = len(offsets)
    blocks = np.asarray(offset_covariance, dtype=float).reshape(count, 2, count, 2)
    blocks = blocks.transpose(0, 2, 1, 3)  # (N, N, 2, 2): cov(e_i, e_j)
    own = blocks[np.arange(count), np.arange(count)]
    combined = own[:, None] + own[None, :] - blocks - blocks.transpose(1, 0, 2, 3)
    combined[np.arange(count), np.arange(count)] = np.eye(2)  # e_i - e_i: not tested
    difference = offsets[:, None, :] - offsets[None, :, :]
    distances = np.einsum("ijk,ijkl,ijl->ij", difference, np.linalg.inv(combined), difference)
    consistent = distances <= chi2_quantile(2, gate_probability)
    np.fill_diagonal(consistent, True)
    return consistent


def offsets_within_gate(offsets: FloatArray, offset_covariance: FloatArray,
                        gate_probability: float) -> np.ndarray:
    """Which correspondences ``a_i = b_i`` are each within the ``gate_probability``
    chi-square gate (2 degrees of freedom): the offset ``e_i = a_i - b_i`` ``(N, 2)`` [m]
    under its own block of the joint covariance ``(2N, 2N)`` [m^2]; ``(N,)`` bool."""
    offsets = np.asarray(offsets, dtype=float).reshape(-1, 2)
    count = len(offsets)
    blocks = np.asarray(offset_covariance, dtype=float).reshape(count, 2, count, 2)
    own = blocks[np.arange(count), :, np.arange(count), :]
    distances = np.einsum("ik,ikl,il->i", offsets, np.linalg.inv(own), offsets)
    return distances <= chi2_quantile(2, gate_probability)


def maximum_consistent_set(consistent: np.ndarray, required: Sequence[int] = ()) -> list[int]:
    """The largest set of indices that are pairwise consistent (a maximum clique of the
    ``(N, N)`` bool graph ``consistent``) containing every index of ``required`` (which
    must be consistent with each other), sorted; the lowest indices first among equally
    large sets. Exact branch and bound, for the tens of candidates of one teammate (pairwise
    consistency maximization, Mangelson et al., ICRA 2018)."""
    consistent = np.asarray(consistent, dtype=bool)
    chosen = sorted(set(required))
    pool = [i for i in range(len(consistent))
            if i not in chosen and all(consistent[i, j] for j in chosen)]
    best: list[list[int]] = [chosen]

    def grow(members: list[int], candidates: list[int]) -> None:
        if len(members) > len(best[0]):
            best[0] = members
        for position, candidate in enumerate(candidates):
            if len(members) + len(candidates) - position <= len(best[0]):
                return
            grow(members + [candidate], [other for other in candidates[position + 1:]
                                         if consistent[candidate, other]])

    grow(chosen, pool)
    return sorted(best[0])
