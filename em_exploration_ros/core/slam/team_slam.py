"""Per-robot team factor graph on iSAM2: measurement records, estimates and covariances.

Every robot runs one :class:`TeamSlam` that holds the whole team's pose graph as that
robot knows it: its own keyframes and whatever its teammates shared, in any order.

Graph layout (all in the ``map`` frame, poses ``(x [m], y [m], theta [rad])``):

* pose of robot ``r`` at keyframe ``k``: key ``gtsam.symbol(chr(ord('a') + r), k)``
  (robot 0 -> ``'a'``, robot 1 -> ``'b'``, ...), a ``gtsam.Pose2``;
* landmark ``j``: key ``gtsam.symbol('L', j)``, a ``gtsam.Point2``;
* a prior on robot 0's first keyframe at the mission's anchor pose (the gauge);
* a ``BetweenFactorPose2`` per odometry link between consecutive keyframes of a robot;
* a ``BearingRangeFactor2D`` per sonar landmark reading;
* a ``BetweenFactorPose2`` per teammate reading (observer keyframe -> observed keyframe
  with the same index); without landmark identities, once it agrees with other readings of
  the same two robots (``robot_detections``).

Noise convention: sensor covariances arrive as covariances of additive errors of the
pose coordinates ``(x, y, theta)`` (the convention of :mod:`geometry`); they are rotated
into the body frame of the measured relative pose, the frame of a GTSAM ``Pose2``
tangent vector, before they become factor noise models. Pose covariances returned by
the accessors are in the ``map`` frame by default (additive ``(x, y, theta)`` errors)
and in the GTSAM body (tangent) frame with ``frame="body"``.
"""
from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass
from typing import Iterable, Literal, Sequence

import gtsam
import numpy as np

from em_exploration_ros.core.geometry import (compose, compose_jacobians,
                                              coordinate_to_body_covariance, inverse,
                                              transform_points)
from em_exploration_ros.core.params import SlamParams
from em_exploration_ros.core.records.readings import (KeyframeId, KeyframeMeasurements,
                                                      LandmarkReading, OdometryReading,
                                                      TeammateReading)
from em_exploration_ros.core.slam.robot_detections import RobotDetection, RobotDetectionScreen

_LOG = logging.getLogger(__name__)

#: Covariance frame of pose accessors: ``"map"`` (additive x, y, theta errors in the map
#: frame) or ``"body"`` (GTSAM Pose2 tangent space, x and y in the pose's body frame).
CovarianceFrame = Literal["map", "body"]

#: Widest span of keyframe indices [keyframes] added to iSAM2 in one update: a larger backlog
#: goes in slices of this many indices (``TeamSlam.update``). A robot restarted 350
#: keyframes into a 200 m mission (seed 1) rebuilt its graph from the team's streams in one
#: update with its trajectory up to 81 m off (the incremental estimate it had before: within
#: 2 m); in slices of 1, 5 or 20 indices it got that estimate back to the centimetre.
BACKLOG_SLICE_INDICES = 10

def pose_key(robot_id: int, index: int) -> int:
    """GTSAM key of robot ``robot_id``'s pose at keyframe ``index`` (``'a' + robot_id``)."""
    return gtsam.symbol(chr(ord("a") + robot_id), index)


def pose_keys(robot_id: int | np.ndarray, indices: np.ndarray) -> np.ndarray:
    """:func:`pose_key` of many keyframe indices ``(K,)`` at once (of one robot, or of one
    robot each, ``robot_id`` ``(K,)``), ``(K,)`` int64 (a GTSAM symbol is its character in
    the top byte and the index below)."""
    robot = np.asarray(robot_id, dtype=np.int64)
    return ((np.int64(ord("a")) + robot) << np.int64(56)) | np.asarray(indices, dtype=np.int64)


def landmark_key(landmark_id: int) -> int:
    """GTSAM key of landmark ``landmark_id`` (``'L'``)."""
    return gtsam.symbol("L", landmark_id)


#: Without landmark identities, the team graph's id of robot r's own landmark n is
#: ``(r + 1) * OWNED_LANDMARK_STRIDE + n``: distinct per robot, never a world id (those are
#: below the stride), and within a LandmarkEstimate's uint32 and the id checks (< 2^31).
OWNED_LANDMARK_STRIDE = 1 << 24


def owned_landmark_id(robot_id: int, own_id: int) -> int:
    """The team graph's id of robot ``robot_id``'s landmark ``own_id`` (its own number)."""
    if not 0 <= own_id < OWNED_LANDMARK_STRIDE:
        raise ValueError(f"own landmark id {own_id} outside [0, {OWNED_LANDMARK_STRIDE})")
    return (robot_id + 1) * OWNED_LANDMARK_STRIDE + own_id


def graph_landmark_id(robot_id: int, landmark_id: int, shared_ids: bool) -> int:
    """The team graph's id of a landmark reading of robot ``robot_id``'s keyframe: the
    reading's own ``landmark_id`` when the sonar names landmarks (``shared_ids``), else
    the robot's own number as ``owned_landmark_id`` keeps it."""
    return landmark_id if shared_ids else owned_landmark_id(robot_id, landmark_id)


def landmark_owner(landmark_id: int) -> int | None:
    """The robot whose own landmark a team-graph id is, None for a world id (identities on)."""
    return landmark_id // OWNED_LANDMARK_STRIDE - 1 if landmark_id >= OWNED_LANDMARK_STRIDE \
        else None


def is_landmark_key(key: int) -> bool:
    """True for the key of a landmark, False for a pose's (by the key's symbol character)."""
    return gtsam.symbolChr(int(key)) == ord("L")


def landmark_key_mask(keys: np.ndarray) -> np.ndarray:
    """:func:`is_landmark_key` of many keys ``(K,)`` at once (the symbol character is the
    key's top byte), ``(K,)`` bool."""
    return np.asarray(keys, dtype=np.int64) >> np.int64(56) == ord("L")


def body_to_map_covariance(pose: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Pose covariances ``(..., 3, 3)`` from the body (GTSAM tangent) frame to additive
    map-frame ``(x, y, theta)`` errors: the position block rotated by ``+theta``."""
    mirrored = np.asarray(pose, dtype=float) * np.array([1.0, 1.0, -1.0])
    return coordinate_to_body_covariance(mirrored, covariance)


class OdometryAccumulator:
    """Integrates per-step odometry into the motion since the last keyframe.

    The accumulated delta is expressed in the body frame of the last keyframe; its
    covariance (additive ``(x, y, theta)`` errors) is propagated to first order with the
    compose Jacobians, step errors being independent.
    """

    def __init__(self) -> None:
        self._delta = np.zeros(3)
        self._covariance = np.zeros((3, 3))

    def add(self, reading: OdometryReading) -> None:
        """Append one step's motion (its delta is in the previous step's body frame)."""
        j_acc, j_step = compose_jacobians(self._delta, reading.delta)
        self._covariance = (j_acc @ self._covariance @ j_acc.T
                            + j_step @ np.asarray(reading.covariance, dtype=float) @ j_step.T)
        self._delta = compose(self._delta, reading.delta)

    def take(self) -> tuple[np.ndarray, np.ndarray]:
        """The accumulated ``(delta (3,), covariance (3, 3))``; starts a new interval."""
        accumulated = (self._delta, self._covariance)
        self._delta = np.zeros(3)
        self._covariance = np.zeros((3, 3))
        return accumulated


class KeyframeBuilder:
    """Turns one robot's per-step sensor stream into :class:`KeyframeMeasurements`.

    A keyframe is cut at every step that is a multiple of ``keyframe_interval_steps``;
    landmark and teammate readings are kept only at those steps, landmark readings only
    when they name their landmark (``LandmarkReading.identified``) unless
    ``keep_unidentified`` (without landmark identities: ``OwnLandmarks.associate`` names
    them next).
    """

    def __init__(self, robot_id: int, slam_params: SlamParams,
                 keep_unidentified: bool = False) -> None:
        self._robot_id = robot_id
        self._keep_unidentified = keep_unidentified
        self._interval = slam_params.keyframe_interval_steps
        self._accumulator = OdometryAccumulator()
        self._last_index: int | None = None

    def resume(self, last_index: int) -> None:
        """Continue a stream whose latest keyframe is ``last_index`` (after a restart): the
        next keyframe links to it, with the odometry fed since."""
        self._accumulator = OdometryAccumulator()
        self._last_index = last_index

    def add_step(self, step: int, stamp_s: float, odometry: OdometryReading | None,
                 sonar: Iterable[LandmarkReading],
                 teammates: Iterable[TeammateReading]) -> KeyframeMeasurements | None:
        """Feed step ``step`` (``odometry``: motion from step-1 to step, None at the
        start); returns the keyframe cut at this step, if any. ``stamp_s`` in seconds."""
        if odometry is not None:
            self._accumulator.add(odometry)
        if step % self._interval != 0:
            return None
        delta, covariance = self._accumulator.take()
        is_first = self._last_index is None
        keyframe = KeyframeMeasurements(
            robot_id=self._robot_id, index=step // self._interval, stamp_s=stamp_s,
            is_first=is_first, previous_index=-1 if is_first else self._last_index,
            odom_delta=np.zeros(3) if is_first else delta,
            odom_covariance=np.zeros((3, 3)) if is_first else covariance,
            landmarks=tuple(reading for reading in sonar
                            if reading.identified or self._keep_unidentified),
            teammates=tuple(teammates))
        self._last_index = keyframe.index
        return keyframe


class SlamNoise:
    """The noise models of the team graph: derived from sensor covariances (paper) or
    the reference implementation's fixed sigmas (``use_fixed_sigmas``)."""

    def __init__(self, slam_params: SlamParams) -> None:
        self._params = slam_params
        self._floor = slam_params.covariance_floor_sigma ** 2
        self.prior = gtsam.noiseModel.Diagonal.Sigmas(np.array(slam_params.prior_sigmas))
        self.virtual_robot_observation = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(slam_params.virtual_robot_obs_sigmas))
        self._fixed_odometry = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(slam_params.fixed_odometry_sigmas))
        self._fixed_bearing_range = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(slam_params.fixed_bearing_range_sigmas))
        self._fixed_robot_observation = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(slam_params.fixed_robot_obs_sigmas))

    def _relative_pose(self, relative_pose: np.ndarray,
                       covariance: np.ndarray) -> gtsam.noiseModel.Base:
        """Noise of a measured relative pose given additive coordinate covariance."""
        body = coordinate_to_body_covariance(relative_pose, covariance)
        return gtsam.noiseModel.Gaussian.Covariance(body + self._floor * np.eye(3))

    def odometry(self, delta: np.ndarray, covariance: np.ndarray) -> gtsam.noiseModel.Base:
        """Noise model of an odometry between factor (``covariance`` of ``delta``'s
        additive coordinates, [m^2], [rad^2])."""
        if self._params.use_fixed_sigmas:
            return self._fixed_odometry
        return self._relative_pose(delta, covariance)

    def odometry_roots(self, deltas: np.ndarray, covariances: np.ndarray) -> np.ndarray:
        """Square-root information matrices ``(F, 3, 3)`` of many odometry factors: what
        ``odometry(delta, covariance).R()`` gives for each, computed in one NumPy batch
        (the upper-triangular ``R`` with ``R^T R`` the inverse of the body-frame covariance,
        as GTSAM's ``Gaussian.Covariance``; equal to it up to round-off)."""
        if self._params.use_fixed_sigmas:
            return np.broadcast_to(self._fixed_odometry.R(), (len(deltas), 3, 3)).copy()
        body = coordinate_to_body_covariance(deltas, covariances) + self._floor * np.eye(3)
        return np.swapaxes(np.linalg.cholesky(np.linalg.inv(body)), -1, -2)

    def bearing_range(self, reading: LandmarkReading,
                      associated: bool = False) -> gtsam.noiseModel.Base:
        """Noise model of a bearing-range factor, ordered (bearing [rad], range [m]);
        ``associated``: the robot associated the reading itself (no landmark identities),
        so it may be wrong: under a Cauchy loss (``landmark_cauchy_k``, unless 0). Without
        it one wrong reading in a run of 20 seeds bent a robot's map by metres (robot RMSE
        9.7 times its ideal-sensing run's); with it the worst run was 3.0 times."""
        if self._params.use_fixed_sigmas:
            model = self._fixed_bearing_range
        else:
            variances = np.array([reading.bearing_variance, reading.range_variance]) + self._floor
            model = gtsam.noiseModel.Diagonal.Variances(variances)
        if not associated or self._params.landmark_cauchy_k == 0.0:
            return model
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(self._params.landmark_cauchy_k), model)

    def robot_observation(self, reading: TeammateReading) -> gtsam.noiseModel.Base:
        """Noise model of an inter-robot between factor."""
        if self._params.use_fixed_sigmas:
            return self._fixed_robot_observation
        return self._relative_pose(reading.relative_pose, reading.covariance)


def _pose2(pose: np.ndarray) -> gtsam.Pose2:
    """``(x, y, theta)`` as a ``gtsam.Pose2``."""
    return gtsam.Pose2(float(pose[0]), float(pose[1]), float(pose[2]))


def _pose_array(pose: gtsam.Pose2) -> np.ndarray:
    """A ``gtsam.Pose2`` as ``(x, y, theta)``."""
    return np.array([pose.x(), pose.y(), pose.theta()])


class _TeamGraph:
    """Bookkeeping of the team graph: received keyframes, what is already in the graph,
    what still waits, and the construction of the factors and initial values of
    everything that became connectable. ``detection_screen``, if given, holds back
    robot-to-robot detections until they agree with others (``robot_detections``)."""

    def __init__(self, num_robots: int, noise: SlamNoise, anchor_pose: np.ndarray,
                 shared_landmark_ids: bool = True,
                 detection_screen: RobotDetectionScreen | None = None) -> None:
        self.num_robots = num_robots
        self.noise = noise
        self.anchor_pose = np.asarray(anchor_pose, dtype=float)
        self.shared_landmark_ids = shared_landmark_ids
        self.detection_screen = detection_screen
        #: Keyframe in the graph -> (previous index, odometry delta (3,), covariance
        #: (3, 3)) from it; robots' first keyframes have none. Kept only with a screen.
        self._odometry: dict[KeyframeId, tuple[int, np.ndarray, np.ndarray]] = {}
        #: Every landmark reading in the graph: (robot, keyframe index, landmark id, bearing
        #: [rad], range [m]), in the order added.
        self.landmark_readings: list[tuple[int, int, int, float, float]] = []
        self.factors = gtsam.NonlinearFactorGraph()
        self.indices: list[list[int]] = [[] for _ in range(num_robots)]
        self.landmark_ids: list[int] = []
        self._landmark_set: set[int] = set()
        self._received: set[KeyframeId] = set()
        self._pending: dict[KeyframeId, KeyframeMeasurements] = {}
        self._in_graph: set[KeyframeId] = set()
        # observed keyframe -> [(observer keyframe, reading)] waiting for the observed one
        self._waiting_observations: dict[KeyframeId, list[tuple[KeyframeId, TeammateReading]]] = {}
        # unordered robot pair (low id, high id) -> inter-robot factors in the graph
        self.observation_counts: dict[tuple[int, int], int] = {}

    def receive(self, keyframe: KeyframeMeasurements) -> None:
        """Store a keyframe unless it is a duplicate. Raises ValueError on bad robot ids."""
        self._check_robot(keyframe.robot_id)
        for reading in keyframe.teammates:
            self._check_robot(reading.robot_id)
            if reading.robot_id == keyframe.robot_id:
                raise ValueError(f"robot {keyframe.robot_id} cannot observe itself")
        if keyframe.keyframe_id not in self._received:
            self._received.add(keyframe.keyframe_id)
            self._pending[keyframe.keyframe_id] = keyframe

    def _check_robot(self, robot_id: int) -> None:
        if not 0 <= robot_id < self.num_robots:
            raise ValueError(f"robot id {robot_id} outside [0, {self.num_robots})")

    @property
    def num_pending(self) -> int:
        """Received keyframes not yet connectable to the graph."""
        return len(self._pending)

    def backlog_slices(self, span: int) -> list[int | None]:
        """The keyframe-index limits of the :meth:`collect` calls one update makes: ``[None]``
        (everything at once) when the pending keyframes span at most ``span`` indices, else
        one limit every ``span`` indices from the lowest pending index, then None."""
        if not self._pending:
            return [None]
        indices = [index for _, index in self._pending]
        lowest, highest = min(indices), max(indices)
        if highest - lowest < span:
            return [None]
        return [*range(lowest + span - 1, highest, span), None]

    def collect(self, estimate: gtsam.Values, up_to_index: int | None = None
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int]:
        """New factors, initial values of new variables and the number of keyframes that
        became connectable (only those with an index up to ``up_to_index``, if given);
        ``estimate`` holds the current values of the graph."""
        batch = _Batch(estimate)
        progress = True
        while progress:
            progress = False
            for keyframe_id in sorted(self._pending, key=lambda kf: (kf[1], kf[0])):
                if up_to_index is not None and keyframe_id[1] > up_to_index:
                    break
                keyframe = self._pending[keyframe_id]
                initial = self._initial_pose(keyframe, batch)
                if initial is None:
                    continue
                self._add(keyframe, initial, batch)
                progress = True
        if self.detection_screen is not None:
            self._screen_detections(batch)
        self.factors.push_back(batch.factors)
        return batch.factors, batch.values, batch.added

    def _initial_pose(self, keyframe: KeyframeMeasurements, batch: _Batch) -> np.ndarray | None:
        """Initial map-frame pose of a keyframe, or None while it is not connectable."""
        if not keyframe.is_first:
            previous = (keyframe.robot_id, keyframe.previous_index)
            if previous not in self._in_graph:
                return None
            return compose(batch.pose(previous), keyframe.odom_delta)
        if keyframe.robot_id == 0:
            return self.anchor_pose
        # Anchor from an observation with an anchored teammate, lowest robot id first.
        candidates = []
        for reading in keyframe.teammates:
            other = (reading.robot_id, keyframe.index)
            if other in self._in_graph:
                # relative_pose = teammate in this robot's frame: self = other ⊕ rel^-1
                candidates.append((reading.robot_id, compose(batch.pose(other),
                                                             inverse(reading.relative_pose))))
        for observer, reading in self._waiting_observations.get(keyframe.keyframe_id, []):
            candidates.append((observer[0], compose(batch.pose(observer),
                                                    reading.relative_pose)))
        if not candidates:
            return None
        return min(candidates, key=lambda candidate: candidate[0])[1]

    def _add(self, keyframe: KeyframeMeasurements, initial: np.ndarray, batch: _Batch) -> None:
        """Insert a connectable keyframe with its factors into ``batch``."""
        keyframe_id = keyframe.keyframe_id
        key = pose_key(*keyframe_id)
        del self._pending[keyframe_id]
        self._in_graph.add(keyframe_id)
        bisect.insort(self.indices[keyframe.robot_id], keyframe.index)
        batch.insert_pose(keyframe_id, initial)
        if keyframe.is_first and keyframe.robot_id == 0:
            batch.factors.push_back(gtsam.PriorFactorPose2(key, _pose2(self.anchor_pose),
                                                           self.noise.prior))
        elif not keyframe.is_first:
            previous_key = pose_key(keyframe.robot_id, keyframe.previous_index)
            if self.detection_screen is not None:
                self._odometry[keyframe_id] = (keyframe.previous_index,
                                               np.asarray(keyframe.odom_delta, dtype=float),
                                               np.asarray(keyframe.odom_covariance,
                                                          dtype=float))
            odometry_noise = self.noise.odometry(keyframe.odom_delta, keyframe.odom_covariance)
            batch.factors.push_back(gtsam.BetweenFactorPose2(
                previous_key, key, _pose2(keyframe.odom_delta), odometry_noise))
        self._add_landmarks(keyframe, initial, batch)
        for reading in keyframe.teammates:
            observed = (reading.robot_id, keyframe.index)
            if observed in self._in_graph:
                self._add_observation(keyframe_id, reading, batch)
            else:
                self._waiting_observations.setdefault(observed, []).append((keyframe_id, reading))
        for observer, reading in self._waiting_observations.pop(keyframe_id, []):
            self._add_observation(observer, reading, batch)

    def _add_landmarks(self, keyframe: KeyframeMeasurements, pose: np.ndarray,
                       batch: _Batch) -> None:
        """Bearing-range factors of the keyframe's readings, then of its late readings
        (from the robot's earlier keyframes, each in the graph already; one that is not,
        which only a forged record carries, is left out with a warning); unseen landmarks
        start at the first reading's point."""
        for reading in keyframe.landmarks:
            self._add_reading(keyframe.keyframe_id, pose, reading, batch)
        absent = []
        for late in keyframe.late_landmarks:
            earlier = (keyframe.robot_id, late.keyframe_index)
            if earlier in self._in_graph:
                self._add_reading(earlier, batch.pose(earlier), late.reading, batch)
            else:
                absent.append(late.keyframe_index)
        if absent:  # one line per keyframe, however many a forged record carries
            _LOG.warning("robot %d's keyframe %d: %d late reading(s) of its keyframe(s) %s, "
                         "which are not in the graph, left out", keyframe.robot_id,
                         keyframe.index, len(absent), sorted(set(absent)))

    def _add_reading(self, observer: KeyframeId, pose: np.ndarray, reading: LandmarkReading,
                     batch: _Batch) -> None:
        """One bearing-range factor from keyframe ``observer`` (at ``pose``)."""
        robot, index = observer
        landmark_id = graph_landmark_id(robot, reading.landmark_id, self.shared_landmark_ids)
        point_key = landmark_key(landmark_id)
        if landmark_id not in self._landmark_set:
            in_body = reading.range_m * np.array([np.cos(reading.bearing_rad),
                                                  np.sin(reading.bearing_rad)])
            batch.values.insert(point_key, gtsam.Point2(transform_points(pose, in_body)))
            bisect.insort(self.landmark_ids, landmark_id)
            self._landmark_set.add(landmark_id)
        self.landmark_readings.append((robot, index, landmark_id, reading.bearing_rad,
                                       reading.range_m))
        batch.factors.push_back(gtsam.BearingRangeFactor2D(
            pose_key(robot, index), point_key, gtsam.Rot2.fromAngle(reading.bearing_rad),
            reading.range_m,
            self.noise.bearing_range(reading, associated=not self.shared_landmark_ids)))

    def _add_observation(self, observer: KeyframeId, reading: TeammateReading,
                         batch: _Batch) -> None:
        """A detection whose two keyframes are in the graph: its factor now, or, with a
        screen, once the screen accepts it (at once at either robot's first keyframe)."""
        detection = RobotDetection(observer, reading)
        if self.detection_screen is None:
            self._add_detection_factor(detection, batch)
        elif self._is_first(observer) or self._is_first((reading.robot_id, observer[1])):
            self.detection_screen.accept_unscreened(detection)
            self._add_detection_factor(detection, batch)
        else:
            self.detection_screen.offer(detection)

    def _is_first(self, keyframe_id: KeyframeId) -> bool:
        """Whether a keyframe in the graph is its robot's first (it has no odometry)."""
        return keyframe_id not in self._odometry

    def _screen_detections(self, batch: _Batch) -> None:
        """The screen's decisions: factors of the detections it accepted, a warning for
        each it left out."""
        accepted, left_out = self.detection_screen.screen(
            self._odometry_between,
            lambda robot: self.indices[robot][-1] if self.indices[robot] else -1)
        for detection in accepted:
            self._add_detection_factor(detection, batch)
        for item in left_out:
            detection = item.detection
            _LOG.warning("robot %d's detection of robot %d at keyframe %d left out: %s",
                         detection.observer[0], detection.reading.robot_id, detection.index,
                         item.reason)

    def _odometry_between(self, robot: int, since: int, until: int
                          ) -> tuple[np.ndarray, np.ndarray] | None:
        """Robot ``robot``'s odometry from keyframe index ``since`` to ``until`` (in the
        body frame of ``since``) with its covariance; None when the graph does not hold the
        chain of its keyframes between them."""
        chain = []
        index = until
        while index > since:
            link = self._odometry.get((robot, index))
            if link is None:
                return None
            index, delta, covariance = link
            chain.append(OdometryReading(delta, covariance))
        if index != since:
            return None
        accumulator = OdometryAccumulator()
        for step in reversed(chain):
            accumulator.add(step)
        return accumulator.take()

    def _add_detection_factor(self, detection: RobotDetection, batch: _Batch) -> None:
        """Between factor observer -> observed teammate keyframe (same index)."""
        observer, reading = detection.observer, detection.reading
        pair = detection.robots
        self.observation_counts[pair] = self.observation_counts.get(pair, 0) + 1
        observation_noise = self.noise.robot_observation(reading)
        batch.factors.push_back(gtsam.BetweenFactorPose2(
            pose_key(*observer), pose_key(reading.robot_id, observer[1]),
            _pose2(reading.relative_pose), observation_noise))


class _Batch:
    """Factors and initial values collected in one update, over the current estimate."""

    def __init__(self, estimate: gtsam.Values) -> None:
        self.estimate = estimate
        self.factors = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self.added = 0

    def insert_pose(self, keyframe_id: KeyframeId, pose: np.ndarray) -> None:
        """Initial value of a newly connected keyframe pose (map frame)."""
        self.values.insert(pose_key(*keyframe_id), _pose2(pose))
        self.added += 1

    def pose(self, keyframe_id: KeyframeId) -> np.ndarray:
        """Initial value (new this batch) or current estimate of a graph pose."""
        key = pose_key(*keyframe_id)
        source = self.values if self.values.exists(key) else self.estimate
        return _pose_array(source.atPose2(key))


@dataclass(frozen=True)
class SlamRecovery:
    """An update whose iSAM2 result failed or diverged and was replaced by a batch re-solve.

    Errors are the graph's total nonlinear error (half the sum of squared whitened
    residuals): ``error_before`` at the previous estimate with the new variables' initial
    values, ``error_after`` after the iSAM2 update (NaN when it raised), ``error_resolved``
    after the re-solve. ``estimate_size`` counts the variables (poses and landmarks).
    ``fallback`` says why Powell's dogleg failed when Levenberg-Marquardt re-solved instead
    (``TeamSlam._resolve``), None when the dogleg did.
    """

    estimate_size: int
    reason: str
    error_before: float
    error_after: float
    error_resolved: float
    fallback: str | None = None

    def describe(self) -> str:
        """One line for a log: why, and the graph's error before and after the re-solve."""
        solver = "" if self.fallback is None else \
            f"; {self.fallback}; Levenberg-Marquardt re-solved instead"
        return (f"iSAM2 update re-solved in batch ({self.reason}{solver}): graph error "
                f"{self.error_before:.4g} before the update, {self.error_resolved:.4g} after "
                f"the re-solve, {self.estimate_size} variables")


def largest_component(delta: gtsam.VectorValues) -> float:
    """Largest absolute component of a Gauss-Newton step (m or rad); infinite or NaN when
    the step is."""
    return float(np.max(np.abs(delta.vector()), initial=0.0))


def step_against(delta: gtsam.VectorValues, bound: float) -> float:
    """A Gauss-Newton step's size as a check against ``bound`` needs it: its 2-norm when
    that is within ``bound`` (no component is larger than the norm, so the largest one is
    within it too), else its largest absolute component (:func:`largest_component`). Both
    answer ``<= bound`` alike; the norm is computed in GTSAM without copying the step into
    an array, about 10 us against 160 us at 4500 dimensions."""
    norm = delta.norm()
    return norm if norm <= bound else largest_component(delta)


def _isam_params(slam_params: SlamParams) -> gtsam.ISAM2Params:
    """iSAM2 with QR factorization, relinearization checked at every update."""
    params = gtsam.ISAM2Params()
    params.setFactorization("QR")
    params.setRelinearizeThreshold(slam_params.relinearize_threshold)
    params.relinearizeSkip = 1
    return params


class TeamSlam:
    """One robot's estimate of the whole team's trajectories and the landmarks.

    Keyframes (own or teammates') may arrive in any order, with gaps and duplicates;
    those not yet connectable wait until they are. Robot 0's first keyframe is anchored
    by a prior at ``anchor_pose`` (map frame); every other robot's first keyframe is
    initialised from an observation linking it to an anchored teammate's keyframe with
    the same index (robot 0 preferred). Later keyframes start at the previous estimate
    composed with their odometry; landmarks at their first bearing-range reading.

    With ``landmark_ids`` (the sonar names each landmark) a reading's landmark id is the
    world's, the same in every robot's records. Without, it is the observing robot's own
    number of the landmark (``association.py`` pairs its detections), the graph holds robot
    r's landmark n as :func:`owned_landmark_id` ``(r, n)``, and
    :meth:`add_landmark_correspondences` ties a teammate's landmark to the robot's own.
    """

    def __init__(self, robot_id: int, num_robots: int, slam_params: SlamParams,
                 anchor_pose: np.ndarray, landmark_ids: bool = True) -> None:
        if not 0 <= robot_id < num_robots <= 26:
            raise ValueError(f"need 0 <= robot_id < num_robots <= 26, got {robot_id}, "
                             f"{num_robots}")
        self.robot_id = robot_id
        self.num_robots = num_robots
        self.slam_params = slam_params
        self.noise = SlamNoise(slam_params)
        screen = None if landmark_ids else RobotDetectionScreen(
            slam_params.track_window_keyframes, slam_params.robot_detection_gate_probability,
            slam_params.covariance_floor_sigma ** 2)
        self._graph = _TeamGraph(num_robots, self.noise, anchor_pose, landmark_ids, screen)
        #: Landmark pairs (own id, teammate's id) tied by a correspondence factor, in order.
        self.landmark_correspondences: list[tuple[int, int]] = []
        self._isam = gtsam.ISAM2(_isam_params(slam_params))
        self._estimate = gtsam.Values()
        #: Landmark positions (L, 2) and the poses of every robot (P, 3) extracted from
        #: ``_estimate``, None until asked for after the estimate changed (each extraction
        #: scans every variable of the graph).
        self._landmark_points: np.ndarray | None = None
        self._pose_rows: np.ndarray | None = None
        #: Updates whose iSAM2 result was replaced by a batch re-solve, in order.
        self.recoveries: list[SlamRecovery] = []

    def _set_estimate(self, estimate: gtsam.Values) -> None:
        self._estimate = estimate
        self._landmark_points = None
        self._pose_rows = None

    # -- input -------------------------------------------------------------------------

    def add_keyframe(self, keyframe: KeyframeMeasurements) -> None:
        """Queue a keyframe (own or a teammate's) for the next :meth:`update`; duplicates
        (same robot and index) are ignored."""
        self._graph.receive(keyframe)

    def landmark_readings(self) -> list[tuple[int, int, int, float, float]]:
        """Every landmark reading in the graph: ``(robot, keyframe index, landmark id,
        bearing [rad], range [m])`` in the order added (a copy)."""
        return list(self._graph.landmark_readings)

    def add_landmark_correspondences(self, pairs: Iterable[tuple[int, int]]) -> None:
        """Tie each pair of landmarks ``(a, b)`` of the graph as one point: a factor
        ``b - a = 0`` with sigma ``correspondence_sigma_m`` per axis under a Huber loss
        (``correspondence_huber_k``), added to iSAM2 at once."""
        pairs = list(pairs)
        if not pairs:
            return
        params = self.slam_params
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(params.correspondence_huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, params.correspondence_sigma_m))
        factors = gtsam.NonlinearFactorGraph()
        for a, b in pairs:
            factors.push_back(gtsam.BetweenFactorPoint2(landmark_key(a), landmark_key(b),
                                                        gtsam.Point2(0.0, 0.0), noise))
        self._graph.factors.push_back(factors)
        self.landmark_correspondences.extend(pairs)
        self._update_with(factors, gtsam.Values())

    def update(self, backlog_slice_indices: int = BACKLOG_SLICE_INDICES) -> int:
        """Add every newly connectable keyframe to iSAM2; returns how many were added.

        Keyframes waiting in a backlog that spans more than ``backlog_slice_indices``
        (:data:`BACKLOG_SLICE_INDICES`) keyframe indices (a restarted robot's recovered
        stream with its teammates', or a teammate's records after a long link outage) go in
        index order, one slice of that many indices per iSAM2 update, as they would have
        arrived during the mission: all at once, every pose starts from its dead reckoning
        and a few Gauss-Newton steps from there do not reach the optimum
        (:meth:`_update_with`).
        """
        added = 0
        for up_to_index in self._graph.backlog_slices(backlog_slice_indices):
            factors, values, count = self._graph.collect(self._estimate, up_to_index)
            added += count
            if factors.size() > 0:
                self._update_with(factors, values)
        return added

    def _update_with(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """One iSAM2 update with new factors and values, then up to
        ``slam_params.extra_update_iterations`` plain updates while iSAM2 still
        relinearizes variables. iSAM2 takes plain Gauss-Newton steps, and a sharp loop
        closure after a long drift can send them diverging, with nothing to bring the
        estimate back. So an update that raises, or that steps more than
        ``divergence_check_step`` and raises the graph's error (:meth:`_divergence`), is
        replaced by a batch solve (Powell's dogleg) of the whole graph from the previous
        estimate, iSAM2 restarts from its solution, and :attr:`recoveries` records it.
        Every other update keeps iSAM2's estimate as it is.
        """
        previous = self._estimate
        try:
            result = self._isam.update(factors, values)
            for _ in range(self.slam_params.extra_update_iterations):
                if result.getVariablesRelinearized() == 0:
                    break
                result = self._isam.update()
            estimate = self._isam.calculateEstimate()
        except RuntimeError as error:  # e.g. GTSAM's IndeterminateSystemException
            estimate, failure = None, " ".join(str(error).split())[:160]
        else:
            failure = None
        bound = self.slam_params.divergence_check_step
        step = math.nan if failure is not None else step_against(self._isam.getDelta(), bound)
        if not step <= bound:  # NaN is checked too
            initial = gtsam.Values(previous)
            initial.insert(values)
            before = self._graph.factors.error(initial)
            after = math.nan if estimate is None else self._graph.factors.error(estimate)
            reason = failure or self._divergence(step, before, after)
            if reason is not None:
                estimate, fallback = self._resolve(initial)
                self.recoveries.append(SlamRecovery(initial.size(), reason, before, after,
                                                    self._graph.factors.error(estimate),
                                                    fallback))
        self._set_estimate(estimate)

    def _largest_step(self) -> float:
        """Largest absolute component of iSAM2's last step (m or rad); infinite or NaN
        when the step is."""
        return largest_component(self._isam.getDelta())

    def _divergence(self, step: float, before: float, after: float) -> str | None:
        """Why an update that took a large ``step`` diverged, None if it did not: it did
        when it raised the graph's error from ``before`` (at the previous estimate with the
        new variables' initial values) to ``after`` more than ``divergence_error_ratio``
        times, rises of an error below 1 (a one-sigma residual) aside; a NaN error counts."""
        if after <= self.slam_params.divergence_error_ratio * max(before, 1.0):
            return None
        return f"a step of {step:.3g} raised the error to {after:.4g}"

    def _resolve(self, initial: gtsam.Values) -> tuple[gtsam.Values, str | None]:
        """Re-solve the whole graph in batch from ``initial`` and restart iSAM2 from the
        solution; returns iSAM2's new estimate and, when Powell's dogleg raised, why
        (Levenberg-Marquardt re-solved instead), else None.

        Powell's dogleg: on the 1492-variable graph of a diverged 200 m mission (CE, seed
        19) it converged in 35 iterations (0.6-0.8 s), where GTSAM's default
        Levenberg-Marquardt stopped at its 100-iteration limit short of the optimum (2.2-3.0
        s), and iSAM2's first step from that point raised the error from 272 to 1305.

        The dogleg's Gauss-Newton systems are undamped, and one raises GTSAM's indeterminate
        system when a landmark's estimate lies on a pose that reads it: there the bearing is
        undefined, GTSAM gives its Jacobian as zero, and the landmark keeps one equation (the
        range) for two unknowns. Victoria Park with the odometry's heading sigma 5 to 10
        times the file's (2000 poses, one robot) drove a wrongly associated landmark to
        1.3e-5 m of its keyframe in the dogleg's 21st iteration. Levenberg-Marquardt damps
        every system and takes a failed solve as a rejected step, so it passes there."""
        fallback = None
        try:
            solution = gtsam.DoglegOptimizer(self._graph.factors, initial,
                                             gtsam.DoglegParams()).optimize()
        except RuntimeError as error:  # GTSAM's IndeterminantLinearSystemException
            fallback = "the dogleg re-solve raised " + " ".join(str(error).split())[:120]
            solution = gtsam.LevenbergMarquardtOptimizer(
                self._graph.factors, initial, gtsam.LevenbergMarquardtParams()).optimize()
        self._isam = gtsam.ISAM2(_isam_params(self.slam_params))
        self._isam.update(self._graph.factors, solution)
        return self._isam.calculateEstimate(), fallback

    def converge(self, tolerance: float = 1e-9, max_iterations: int = 50) -> int:
        """Iterate iSAM2 until no variable is relinearized, the largest remaining
        Gauss-Newton step is below ``tolerance`` (m or rad) or stops shrinking (the
        floating-point floor of the problem's conditioning, about 1e-7 with the default
        prior sigmas); returns the number of iterations run.

        With a ``relinearize_threshold`` far below the expected accuracy (e.g. 0) this
        reaches the batch optimum; with a larger threshold the estimate keeps the
        threshold's linearization error.
        """
        iterations = 0
        previous_step = np.inf
        while iterations < max_iterations and self._isam.size() > 0:
            result = self._isam.update()
            iterations += 1
            largest_step = self._largest_step()
            if (result.getVariablesRelinearized() == 0 or largest_step < tolerance
                    or largest_step >= previous_step):
                break
            previous_step = largest_step
        self._set_estimate(self._isam.calculateEstimate())
        return iterations

    # -- graph access (EM planner) ----------------------------------------------------

    def graph(self) -> gtsam.NonlinearFactorGraph:
        """A copy of every factor given to iSAM2 (prior, odometry, landmarks, robots)."""
        return self._graph.factors.clone()

    def values(self) -> gtsam.Values:
        """The current estimate of every variable in the graph (map frame)."""
        return gtsam.Values(self._estimate)

    # -- estimates ---------------------------------------------------------------------

    def latest_index(self, robot_id: int) -> int | None:
        """Latest keyframe index of ``robot_id`` in the graph, None if it has none."""
        indices = self._graph.indices[robot_id]
        return indices[-1] if indices else None

    def num_variables(self) -> int:
        """Number of variables (poses and landmarks) in the graph."""
        return self._estimate.size()

    def inter_robot_factors(self, robot_a: int, robot_b: int) -> int:
        """How many inter-robot observation factors between the two robots (either way)
        the graph holds: counted when added, i.e. at the :meth:`update` that adds them."""
        return self._graph.observation_counts.get((min(robot_a, robot_b),
                                                   max(robot_a, robot_b)), 0)

    def num_pending(self) -> int:
        """Number of received keyframes still waiting to be connectable."""
        return self._graph.num_pending

    def pose(self, robot_id: int, index: int) -> np.ndarray:
        """Estimated map-frame pose ``(3,)`` of a keyframe in the graph."""
        return _pose_array(self._estimate.atPose2(pose_key(robot_id, index)))

    def trajectory(self, robot_id: int) -> tuple[np.ndarray, np.ndarray]:
        """``(indices (K,), poses (K, 3))`` of ``robot_id``'s keyframes, map frame."""
        indices = self._graph.indices[robot_id]
        # Values iterate in key order: robot r's poses follow those of robots < r.
        start = sum(len(self._graph.indices[r]) for r in range(robot_id))
        if self._pose_rows is None:
            self._pose_rows = gtsam.utilities.extractPose2(self._estimate).reshape(-1, 3)
            self._pose_rows.setflags(write=False)
        poses = self._pose_rows[start:start + len(indices)].copy()
        return np.array(indices, dtype=int), poses

    def landmark_estimates(self) -> dict[int, np.ndarray]:
        """Map-frame position ``(2,)`` [m] of every landmark in the graph, by id."""
        if self._landmark_points is None:
            self._landmark_points = gtsam.utilities.extractPoint2(self._estimate)
            self._landmark_points.setflags(write=False)
        points = self._landmark_points
        return {landmark_id: points[row] for row, landmark_id in
                enumerate(self._graph.landmark_ids)}

    def trajectory_covariances(self, robot_id: int,
                               frame: CovarianceFrame = "map") -> np.ndarray:
        """Marginal covariances ``(K, 3, 3)`` of ``robot_id``'s keyframes (trajectory order)."""
        indices, poses = self.trajectory(robot_id)
        covariances = np.array([self._isam.marginalCovariance(pose_key(robot_id, int(index)))
                                for index in indices]).reshape(-1, 3, 3)
        if frame == "body":
            return covariances
        return body_to_map_covariance(poses, covariances)

    def pose_covariance(self, robot_id: int, index: int) -> np.ndarray:
        """Marginal covariance ``(3, 3)`` of one keyframe pose, body frame (x, y [m], theta
        [rad]); its trace equals the map-frame one."""
        return self._isam.marginalCovariance(pose_key(robot_id, index))

    def landmark_covariance(self, landmark_id: int) -> np.ndarray:
        """Marginal covariance ``(2, 2)`` [m^2] of a landmark, map frame."""
        return self._isam.marginalCovariance(landmark_key(landmark_id))

    def landmarks_joint_covariance(self, landmark_ids: Sequence[int]) -> np.ndarray:
        """Joint marginal covariance ``(2L, 2L)`` [m^2] of landmarks ``(L,)``, map frame, in
        their order (x, y of the first, then of the second, ...)."""
        keys = gtsam.KeyVector([landmark_key(int(i)) for i in landmark_ids])
        joint = self._isam.jointMarginalCovariance(keys)
        return np.block([[joint.at(row, column) for column in keys] for row in keys])
