"""Algorithm 1 of the paper, lines 1-7: the virtual paths and measurements of a candidate.

For one candidate target of robot alpha, every robot drives a straight virtual path from
its latest graph pose: alpha towards the candidate (``X_next``), each teammate towards its
current target (``X_predict``; a teammate without target stays where it is). Waypoints
lie every ``virtual_waypoint_spacing_m`` along the path and carry the robot's own key
sequence (``pose_key(robot, latest + k)``), heading along the path. Virtual measurements:

* odometry between successive waypoints, with the covariance the robot's dead reckoning
  accumulates over that distance (straight motion in steps of ``speed * time_step``,
  the per-step model of :func:`~em_exploration_ros.core.world.sensors.odometry_covariance_per_step`
  accumulated like the SLAM keyframes), turned into a noise model by the SLAM's own
  :class:`~em_exploration_ros.core.slam.team_slam.SlamNoise` (so fixed reference sigmas apply too);
* bearing-range readings of every known landmark within sonar range of a waypoint;
* inter-robot readings when two robots are within sonar range at the same step ``k``
  (waypoint ``k`` of each path; a robot that reached its target waits at its last
  waypoint, an idle robot at its latest pose), one reading per pair of variables, with
  ``SlamParams.virtual_robot_obs_sigmas``.

Virtual measurements equal their predicted values (zero residual), so the means do not
move; only the covariances change. All pose covariances are in the GTSAM ``Pose2``
tangent (body) frame. The propagation of covariances through these measurements is
``em_step``; its direct re-solve reference is ``em_oracle``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping, Sequence, TypeVar

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.geometry import between, range_bearing
from em_exploration_ros.core.params import MotionParams, SensorParams
from em_exploration_ros.core.records.readings import LandmarkReading
from em_exploration_ros.core.slam.team_slam import (SlamNoise, TeamSlam, landmark_key, pose_key,
                                                    pose_keys)
from em_exploration_ros.core.world.sensors import odometry_covariance_per_step

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def virtual_waypoints(start_pose: ArrayLike, target_xy: ArrayLike | None,
                      spacing_m: float) -> FloatArray:
    """Waypoints ``(n, 3)`` (map frame) along the straight path from ``start_pose`` (3,) to
    ``target_xy`` (2,): ``n = ceil(length / spacing_m)`` equally spaced points ending at the
    target, heading along the path; none for a missing or reached target."""
    target = np.full(2, np.nan) if target_xy is None else target_xy
    _, waypoints = _batch_waypoints(np.asarray(start_pose, dtype=float).reshape(1, 3),
                                    np.asarray(target, dtype=float).reshape(1, 2), spacing_m)
    return waypoints


def _ragged(counts: IntArray) -> tuple[IntArray, IntArray]:
    """For runs of ``counts`` (P,) entries laid end to end: the run of every entry and its
    position in its run (0 first)."""
    run = np.repeat(np.arange(len(counts)), counts)
    return run, np.arange(len(run)) - (np.cumsum(counts) - counts)[run]


def _batch_waypoints(starts: FloatArray, targets: FloatArray,
                     spacing_m: float) -> tuple[IntArray, FloatArray]:
    """:func:`virtual_waypoints` of many paths at once: starts (P, 3), targets (P, 2) (NaN:
    none). Returns the waypoint count of each path (P,) and every path's waypoints in
    path order (sum of counts, 3)."""
    direction = targets - starts[:, :2]
    length = np.hypot(direction[:, 0], direction[:, 1])
    moving = np.isfinite(length) & (length >= 1e-9)
    counts = np.zeros(len(starts), dtype=np.int64)
    counts[moving] = np.ceil(length[moving] / spacing_m - 1e-9)
    path, index = _ragged(counts)
    xy = starts[path, :2] + ((index + 1) / counts[path])[:, None] * direction[path]
    heading = np.arctan2(direction[:, 1], direction[:, 0])[path]
    return counts, np.column_stack([xy, heading]).reshape(-1, 3)


def _straight_odometry_covariance(steps: int, step_length_m: float,
                                  sensor_params: SensorParams) -> FloatArray:
    """Covariance ``(3, 3)`` of the odometry of ``steps`` straight steps of equal length.

    The :class:`~em_exploration_ros.core.slam.team_slam.OdometryAccumulator` recursion
    ``Sigma_k+1 = A Sigma_k A^T + Q`` in closed form: along a straight line the compose
    Jacobian is ``A = [[1, 0, 0], [0, 1, s], [0, 0, 1]]`` (``s`` the step length) and the
    per-step noise ``Q = diag(q_xy, q_xy, q_theta)``, so ``Sigma_n = sum_k A^k Q A^kT``.
    """
    step_noise = odometry_covariance_per_step(step_length_m, False, sensor_params)
    translation, heading = step_noise[0, 0], step_noise[2, 2]
    k = np.arange(steps)
    lever = step_length_m * k
    covariance = np.diag([steps * translation,
                          steps * translation + heading * np.sum(lever ** 2),
                          steps * heading])
    covariance[1, 2] = covariance[2, 1] = heading * np.sum(lever)
    return covariance


class VirtualNoise:
    """Square-root information matrices of the virtual measurements (GTSAM conventions)."""

    def __init__(self, slam_noise: SlamNoise, sensor_params: SensorParams,
                 motion_params: MotionParams) -> None:
        self._slam_noise = slam_noise
        self._sensor_params = sensor_params
        self._step_m = motion_params.speed_mps * motion_params.time_step_s
        reading = LandmarkReading(0, 1.0, 0.0, sensor_params.sonar_range_sigma_m ** 2,
                                  sensor_params.sonar_bearing_sigma_rad ** 2)
        #: (2, 2) for (bearing [rad], range [m]) residuals.
        self.bearing_range = np.asarray(slam_noise.bearing_range(reading).R(), dtype=float)
        #: (3, 3) for inter-robot relative-pose residuals (tangent space).
        self.robot_observation = np.asarray(slam_noise.virtual_robot_observation.R(),
                                            dtype=float)

    def odometry(self, deltas: ArrayLike) -> FloatArray:
        """``(F, 3, 3)`` for virtual odometry ``deltas`` (F, 3) [m, m, rad], each in the
        previous body frame: straight motion over its length at the robot's per-step
        distance."""
        deltas = np.asarray(deltas, dtype=float).reshape(-1, 3)
        if not len(deltas):
            return np.zeros((0, 3, 3))
        covariances = np.empty((len(deltas), 3, 3))
        for covariance, length in zip(covariances, np.hypot(deltas[:, 0], deltas[:, 1])):
            steps = max(1, int(round(length / self._step_m)))
            covariance[:] = _straight_odometry_covariance(steps, length / steps,
                                                          self._sensor_params)
        return self._slam_noise.odometry_roots(deltas, covariances)


@dataclass(frozen=True)
class TeamSnapshot:
    """What Algorithm 1 needs from one robot's SLAM at decision time (map frame).

    ``start_keys`` / ``start_poses``: latest graph pose of every robot in the graph;
    ``next_index``: first free keyframe index per robot (keys of virtual waypoints);
    ``history_keys`` / ``history_poses`` (K, 3): the deciding robot's graph poses in
    trajectory order.
    """

    robot_id: int
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    start_keys: Mapping[int, int]
    start_poses: Mapping[int, FloatArray]
    next_index: Mapping[int, int]
    landmark_keys: IntArray
    landmark_positions: FloatArray
    history_keys: tuple[int, ...]
    history_poses: FloatArray

    @classmethod
    def from_slam(cls, slam: TeamSlam, robot_id: int) -> "TeamSnapshot":
        """Snapshot of ``slam`` (graph copy and current estimate) for robot ``robot_id``."""
        start_keys, start_poses, next_index = {}, {}, {}
        for robot in range(slam.num_robots):
            latest = slam.latest_index(robot)
            if latest is None:
                continue
            start_keys[robot] = pose_key(robot, latest)
            start_poses[robot] = slam.pose(robot, latest)
            next_index[robot] = latest + 1
        landmarks = slam.landmark_estimates()
        ids = sorted(landmarks)
        indices, poses = slam.trajectory(robot_id)
        return cls(robot_id, slam.graph(), slam.values(), start_keys, start_poses, next_index,
                   np.array([landmark_key(i) for i in ids], dtype=np.int64),
                   np.array([landmarks[i] for i in ids], dtype=float).reshape(-1, 2),
                   tuple(pose_keys(robot_id, indices).tolist()), poses)


@dataclass(frozen=True)
class _PoseFactors:
    """Relative-pose factors ``key1 -> key2`` (F,) with measurement (F, 3) and (F, 3, 3)
    square-root information."""

    key1: IntArray
    key2: IntArray
    measured: FloatArray
    sqrt_information: FloatArray


@dataclass(frozen=True)
class _LandmarkFactors:
    """Bearing-range factors pose ``pose_key`` -> ``landmark_key`` (F,): measured bearing and
    range (F,), linearization pose (F, 3) and point (F, 2), (F, 2, 2) square-root
    information."""

    pose_key: IntArray
    landmark_key: IntArray
    bearing: FloatArray
    range: FloatArray
    pose: FloatArray
    point: FloatArray
    sqrt_information: FloatArray


def _pose_factors(key1: Sequence[int], key2: Sequence[int], poses1: FloatArray,
                  poses2: FloatArray, roots: FloatArray) -> _PoseFactors:
    return _PoseFactors(np.asarray(key1, dtype=np.int64), np.asarray(key2, dtype=np.int64),
                        between(poses1, poses2).reshape(-1, 3), roots.reshape(-1, 3, 3))


@dataclass(frozen=True)
class VirtualFactors:
    """New waypoint variables and virtual measurements.

    ``waypoint_keys`` (n,), ``waypoint_robots`` (n,) and ``waypoints`` (n, 3, map frame)
    list the new variables robot by robot (ascending id).
    """

    waypoint_keys: IntArray
    waypoint_robots: IntArray
    waypoints: FloatArray
    odometry: _PoseFactors
    robot_observations: _PoseFactors
    landmark_observations: _LandmarkFactors

    def touched_keys(self) -> set[int]:
        """Every variable key a factor touches."""
        return set(np.concatenate([self.odometry.key1, self.odometry.key2,
                                   self.robot_observations.key1, self.robot_observations.key2,
                                   self.landmark_observations.pose_key,
                                   self.landmark_observations.landmark_key]).tolist())

    def factors_and_values(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The virtual factors and the initial values of the waypoints, as GTSAM objects."""
        graph = gtsam.NonlinearFactorGraph()
        for factors in (self.odometry, self.robot_observations):
            for key1, key2, measured, root in zip(factors.key1, factors.key2, factors.measured,
                                                  factors.sqrt_information):
                graph.add(gtsam.BetweenFactorPose2(
                    int(key1), int(key2), gtsam.Pose2(*measured),
                    gtsam.noiseModel.Gaussian.SqrtInformation(root)))
        obs = self.landmark_observations
        for key1, key2, bearing, distance, root in zip(obs.pose_key, obs.landmark_key,
                                                       obs.bearing, obs.range,
                                                       obs.sqrt_information):
            graph.add(gtsam.BearingRangeFactor2D(
                int(key1), int(key2), gtsam.Rot2.fromAngle(float(bearing)), float(distance),
                gtsam.noiseModel.Gaussian.SqrtInformation(root)))
        values = gtsam.Values()
        for key, pose in zip(self.waypoint_keys, self.waypoints):
            values.insert(int(key), gtsam.Pose2(*pose))
        return graph, values


@dataclass(frozen=True)
class VirtualScenario:
    """Virtual paths and measurements of one candidate (Algorithm 1, lines 1-7).

    ``predicted`` (``X_predict``): the teammates' paths to their current targets and their
    readings among themselves, shared by every candidate of a decision; ``next``
    (``X_next``): the deciding robot's path to the candidate, its landmark readings and
    its readings of (and by) teammates. ``boundary_keys``: variables outside ``next``'s
    waypoints that ``next``'s factors touch (graph variables or predicted waypoints).
    """

    robot_id: int
    predicted: VirtualFactors
    next: VirtualFactors
    boundary_keys: tuple[int, ...]


@dataclass(frozen=True)
class _PathBatch:
    """Virtual timelines of several robots' paths, each its robot's latest graph pose then
    ``counts[p]`` waypoints. Waypoint arrays list every path's waypoints in path order
    (path ``p``'s from ``first[p]``); ``odometry`` has one factor per waypoint (from the
    previous timeline entry) and ``landmarks`` are in waypoint order (path ``p``'s from
    ``landmark_first[p]``)."""

    robot_ids: IntArray
    start_keys: IntArray
    starts: FloatArray
    counts: IntArray
    first: IntArray
    waypoint_path: IntArray
    keys: IntArray
    waypoints: FloatArray
    odometry: _PoseFactors
    landmarks: _LandmarkFactors
    landmark_first: IntArray

    def timeline(self, path: int) -> tuple[IntArray, FloatArray]:
        """Keys (n + 1,) and poses (n + 1, 3) of path ``path``, latest graph pose first."""
        span = slice(self.first[path], self.first[path] + self.counts[path])
        return (np.concatenate([self.start_keys[path:path + 1], self.keys[span]]),
                np.vstack([self.starts[path:path + 1], self.waypoints[span]]))

    def readings_with(self, keys: IntArray, poses: FloatArray, sonar_range_m: float
                      ) -> tuple[IntArray, IntArray, IntArray, FloatArray, FloatArray]:
        """Inter-robot readings between each path and one other timeline (``keys`` (m + 1,),
        ``poses`` (m + 1, 3)): within sonar range at the same step ``k >= 1`` (a robot past
        its last waypoint waits there). Returns the path of each reading and its keys and
        poses on both sides, path by path in step order. Steps run to the longer
        timeline's end, whose index is ``k``: so no pair of variables comes twice, and two
        robots both still at their latest graph poses (already in the graph) are never
        read."""
        other_count = len(keys) - 1
        path, index = _ragged(np.maximum(self.counts, other_count))
        step = index + 1
        own_index = np.minimum(step, self.counts[path])
        other_index = np.minimum(step, other_count)
        # Rows of [starts; waypoints]: path p's latest graph pose, or its waypoint i - 1.
        entry = np.where(own_index == 0, path,
                         len(self.counts) + self.first[path] + own_index - 1)
        own_poses = np.vstack([self.starts, self.waypoints])[entry]
        offsets = poses[other_index, :2] - own_poses[:, :2]
        near = np.hypot(offsets[:, 0], offsets[:, 1]) <= sonar_range_m
        own_keys = np.concatenate([self.start_keys, self.keys])[entry]
        return (path[near], own_keys[near], keys[other_index[near]], own_poses[near],
                poses[other_index[near]])


def _empty_pose_factors() -> _PoseFactors:
    return _pose_factors([], [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)))


FactorsT = TypeVar("FactorsT", _PoseFactors, _LandmarkFactors)


def _sliced(factors: FactorsT, span: slice) -> FactorsT:
    """The factors ``span`` of a set of factors (every array field sliced alike)."""
    return type(factors)(*(getattr(factors, field.name)[span] for field in fields(factors)))


class ScenarioBuilder:
    """Builds the :class:`VirtualScenario` of each candidate of one decision.

    Args:
        snapshot: the deciding robot's view of the team (``snapshot.robot_id`` is alpha).
        teammate_targets: current target (2,) [m] of each teammate; None or missing: idle.
        noise: virtual measurement noise; spacing_m: waypoint spacing [m];
        sonar_range_m: range of landmark and inter-robot readings [m].

    The teammates' part (``predicted``) does not depend on the candidate and is built once.
    """

    def __init__(self, snapshot: TeamSnapshot, teammate_targets: Mapping[int, ArrayLike | None],
                 noise: VirtualNoise, spacing_m: float, sonar_range_m: float) -> None:
        self.snapshot = snapshot
        self.noise = noise
        self.spacing_m = spacing_m
        self.sonar_range_m = sonar_range_m
        mates = [robot for robot in sorted(snapshot.start_keys) if robot != snapshot.robot_id]
        targets = [teammate_targets.get(robot) for robot in mates]
        self._mates = self._paths(np.array(mates, dtype=np.int64), np.array(
            [np.full(2, np.nan) if t is None else np.asarray(t, dtype=float)[:2]
             for t in targets]).reshape(-1, 2))
        self._mate_timelines = [self._mates.timeline(p) for p in range(len(mates))]
        # Readings between teammates, pair by pair (i < j), each in step order.
        parts = []
        for j, (keys, poses) in enumerate(self._mate_timelines):
            path, *columns = self._mates.readings_with(keys, poses, sonar_range_m)
            earlier = path < j
            parts.append((path[earlier] * len(mates) + j, *(c[earlier] for c in columns)))
        observations, _ = self._observations(parts)
        batch = self._mates
        self.predicted = VirtualFactors(batch.keys, batch.robot_ids[batch.waypoint_path],
                                        batch.waypoints, batch.odometry, observations,
                                        batch.landmarks)

    def _observations(self, parts: list[tuple]) -> tuple[_PoseFactors, IntArray]:
        """Readings from ``(rank, key1, key2, poses1, poses2)`` parts, stably sorted by
        rank, and their ranks in that order."""
        if not parts:
            return _empty_pose_factors(), np.zeros(0, dtype=np.int64)
        rank, key1, key2, poses1, poses2 = (np.concatenate(c) for c in zip(*parts))
        order = np.argsort(rank, kind="stable")
        return _pose_factors(key1[order], key2[order], poses1[order], poses2[order],
                             np.broadcast_to(self.noise.robot_observation,
                                             (len(order), 3, 3))), rank[order]

    def _paths(self, robots: IntArray, targets: FloatArray) -> _PathBatch:
        """The virtual paths of ``robots`` (P,) from their latest graph poses to ``targets``
        (P, 2) (NaN: idle), with their odometry and landmark readings."""
        snapshot = self.snapshot
        starts = np.array([snapshot.start_poses[r] for r in robots], dtype=float).reshape(-1, 3)
        start_keys = np.array([snapshot.start_keys[r] for r in robots], dtype=np.int64)
        counts, waypoints = _batch_waypoints(starts, targets, self.spacing_m)
        first = np.cumsum(counts) - counts
        path, step = _ragged(counts)  # step 0: a path's first waypoint
        next_index = np.array([snapshot.next_index[r] for r in robots], dtype=np.int64)
        keys = pose_keys(robots[path], next_index[path] + step)
        is_first = step == 0
        previous = np.empty_like(waypoints)
        previous[is_first] = starts[path[is_first]]
        previous[~is_first] = waypoints[np.flatnonzero(~is_first) - 1]
        previous_keys = np.where(is_first, start_keys[path], np.roll(keys, 1))
        deltas = between(previous, waypoints).reshape(-1, 3)
        # A path's first segment turns from the start heading; every later one is the same
        # straight step along the path: two noise models per path.
        first_segments, second_segments = first[counts > 0], first[counts > 1] + 1
        distinct = self.noise.odometry(deltas[np.concatenate([first_segments,
                                                              second_segments])])
        roots = np.empty((len(path), 3, 3))
        roots[first_segments] = distinct[:len(first_segments)]
        later_root = np.empty((len(robots), 3, 3))
        later_root[counts > 1] = distinct[len(first_segments):]
        roots[~is_first] = later_root[path[~is_first]]
        landmarks, seen_waypoint = self._landmark_observations(keys, waypoints)
        return _PathBatch(robots, start_keys, starts, counts, first, path, keys, waypoints,
                          _PoseFactors(previous_keys, keys, deltas, roots), landmarks,
                          np.searchsorted(seen_waypoint, first))

    def _landmark_observations(self, keys: IntArray, waypoints: FloatArray
                               ) -> tuple[_LandmarkFactors, IntArray]:
        """Bearing-range readings of known landmarks within sonar range of each waypoint,
        in waypoint order, and the waypoint of each."""
        landmarks = self.snapshot.landmark_positions
        offsets = landmarks[None, :, :] - waypoints[:, None, :2]
        seen_waypoint, seen_landmark = np.nonzero(
            np.hypot(offsets[..., 0], offsets[..., 1]) <= self.sonar_range_m)
        distance, bearing = range_bearing(waypoints[seen_waypoint], landmarks[seen_landmark])
        return _LandmarkFactors(keys[seen_waypoint], self.snapshot.landmark_keys[seen_landmark],
                                bearing, distance, waypoints[seen_waypoint],
                                landmarks[seen_landmark],
                                np.broadcast_to(self.noise.bearing_range,
                                                (len(seen_waypoint), 2, 2))), seen_waypoint

    def build(self, target_xy: ArrayLike) -> VirtualScenario:
        """Virtual paths and measurements of the candidate ``target_xy`` (2,) [m]."""
        return self.build_all(np.asarray(target_xy, dtype=float).reshape(1, 2))[0]

    def build_all(self, targets_xy: ArrayLike) -> list[VirtualScenario]:
        """The scenarios of the candidates ``targets_xy`` (C, 2) [m], built together (each
        as :meth:`build` would)."""
        targets = np.asarray(targets_xy, dtype=float).reshape(-1, 2)
        alpha = self.snapshot.robot_id
        own = self._paths(np.full(len(targets), alpha, dtype=np.int64), targets)
        parts = []
        for mate, (keys, poses) in enumerate(self._mate_timelines):
            path, *columns = own.readings_with(keys, poses, self.sonar_range_m)
            parts.append((path * len(self._mate_timelines) + mate, *columns))
        observations, ranks = self._observations(parts)
        per_candidate = np.searchsorted(ranks // max(len(parts), 1),
                                        np.arange(len(targets) + 1))
        landmark_bounds = np.append(own.landmark_first, len(own.landmarks.pose_key))
        scenarios = []
        for candidate in range(len(targets)):
            span = slice(own.first[candidate], own.first[candidate] + own.counts[candidate])
            seen = slice(landmark_bounds[candidate], landmark_bounds[candidate + 1])
            readings = slice(per_candidate[candidate], per_candidate[candidate + 1])
            next_factors = VirtualFactors(
                own.keys[span], own.robot_ids[own.waypoint_path[span]], own.waypoints[span],
                _sliced(own.odometry, span), _sliced(observations, readings),
                _sliced(own.landmarks, seen))
            boundary = next_factors.touched_keys() - set(own.keys[span].tolist())
            scenarios.append(VirtualScenario(alpha, self.predicted, next_factors,
                                             tuple(sorted(boundary))))
        return scenarios


def graph_with_virtual(snapshot: TeamSnapshot, *parts: VirtualFactors
                       ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Copies of the snapshot's graph and values extended with virtual factors."""
    graph = snapshot.graph.clone()
    values = gtsam.Values(snapshot.values)
    for part in parts:
        factors, waypoint_values = part.factors_and_values()
        graph.push_back(factors)
        values.insert(waypoint_values)
    return graph, values
