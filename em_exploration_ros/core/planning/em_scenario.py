"""Algorithm 1 of the paper, lines 1-7: the virtual paths and measurements of a candidate.

For one candidate target of robot alpha, every robot drives a straight virtual path from
its latest graph pose: alpha towards the candidate (``X_next``), each teammate towards its
current target (``X_predict``; a teammate without target stays where it is). Waypoints
lie every ``virtual_waypoint_spacing_m`` along the path and carry the robot's own key
sequence (``pose_key(robot, latest + k)``), heading along the path. Virtual measurements:

* odometry between successive waypoints, with the covariance the robot's dead reckoning
  accumulates over that distance (straight motion in steps of ``speed * time_step``,
  the per-step model of :func:`~em_exploration_ros.core.sim.sensors.odometry_covariance_per_step`
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

from dataclasses import dataclass
from typing import Mapping, Sequence

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.geometry import between, range_bearing
from em_exploration_ros.core.params import MotionParams, SensorParams
from em_exploration_ros.core.sim.sensors import LandmarkReading, odometry_covariance_per_step
from em_exploration_ros.core.slam.team_slam import (SlamNoise, TeamSlam, landmark_key, pose_key,
                                                    pose_keys)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def virtual_waypoints(start_pose: ArrayLike, target_xy: ArrayLike | None,
                      spacing_m: float) -> FloatArray:
    """Waypoints ``(n, 3)`` (map frame) along the straight path from ``start_pose`` (3,) to
    ``target_xy`` (2,): ``n = ceil(length / spacing_m)`` equally spaced points ending at the
    target, heading along the path; none for a missing or reached target."""
    start = np.asarray(start_pose, dtype=float)
    if target_xy is None:
        return np.zeros((0, 3))
    direction = np.asarray(target_xy, dtype=float)[:2] - start[:2]
    length = float(np.hypot(direction[0], direction[1]))
    if length < 1e-9:
        return np.zeros((0, 3))
    count = int(np.ceil(length / spacing_m - 1e-9))
    fractions = np.arange(1, count + 1) / count
    xy = start[:2] + fractions[:, None] * direction
    heading = np.full(count, np.arctan2(direction[1], direction[0]))
    return np.column_stack([xy, heading])


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


def _join_pose_factors(parts: Sequence[_PoseFactors]) -> _PoseFactors:
    return _PoseFactors(*(np.concatenate([getattr(p, name) for p in parts])
                          for name in ("key1", "key2", "measured", "sqrt_information")))


def _join_landmark_factors(parts: Sequence[_LandmarkFactors]) -> _LandmarkFactors:
    return _LandmarkFactors(*(np.concatenate([getattr(p, name) for p in parts])
                              for name in ("pose_key", "landmark_key", "bearing", "range",
                                           "pose", "point", "sqrt_information")))


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
class _RobotPath:
    """One robot's virtual timeline (latest graph pose first, then its waypoints), the
    odometry along it and its landmark readings."""

    robot_id: int
    keys: IntArray
    poses: FloatArray
    odometry: _PoseFactors
    landmarks: _LandmarkFactors


def _empty_pose_factors() -> _PoseFactors:
    return _pose_factors([], [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)))


def _virtual_factors(paths: Sequence[_RobotPath],
                     robot_observations: _PoseFactors) -> VirtualFactors:
    """The waypoints of ``paths`` with their odometry and landmark readings."""
    if not paths:
        empty = np.zeros(0, dtype=np.int64)
        no_landmarks = _LandmarkFactors(empty, empty, np.zeros(0), np.zeros(0),
                                        np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2, 2)))
        return VirtualFactors(empty, empty, np.zeros((0, 3)), _empty_pose_factors(),
                              robot_observations, no_landmarks)
    return VirtualFactors(
        np.concatenate([p.keys[1:] for p in paths]),
        np.concatenate([np.full(len(p.keys) - 1, p.robot_id, dtype=np.int64) for p in paths]),
        np.vstack([p.poses[1:] for p in paths]),
        _join_pose_factors([p.odometry for p in paths]), robot_observations,
        _join_landmark_factors([p.landmarks for p in paths]))


def _robot_observations(pairs_of_paths: Sequence[tuple[_RobotPath, _RobotPath]],
                        root: FloatArray, sonar_range_m: float) -> _PoseFactors:
    """Inter-robot readings between two robots within sonar range at the same step
    ``k >= 1`` (a robot past its last waypoint waits there; two robots both still at their
    latest graph poses are skipped), once per pair of variables: the longer path's index
    grows with ``k``, so no pair of variables comes twice."""
    parts = []
    for path_a, path_b in pairs_of_paths:
        step = np.arange(1, max(len(path_a.keys), len(path_b.keys)))
        index_a = np.minimum(step, len(path_a.keys) - 1)
        index_b = np.minimum(step, len(path_b.keys) - 1)
        offsets = path_b.poses[index_b, :2] - path_a.poses[index_a, :2]
        near = (np.hypot(offsets[:, 0], offsets[:, 1]) <= sonar_range_m) & (
            (index_a > 0) | (index_b > 0))
        index_a, index_b = index_a[near], index_b[near]
        parts.append((path_a.keys[index_a], path_b.keys[index_b], path_a.poses[index_a],
                      path_b.poses[index_b]))
    if not parts:
        return _empty_pose_factors()
    key1, key2, poses1, poses2 = (np.concatenate(column) for column in zip(*parts))
    return _pose_factors(key1, key2, poses1, poses2, np.broadcast_to(root, (len(key1), 3, 3)))


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
        self._teammates = [self._path(robot, teammate_targets.get(robot))
                           for robot in sorted(snapshot.start_keys)
                           if robot != snapshot.robot_id]
        mates = self._teammates
        observations = _robot_observations(
            [(a, b) for i, a in enumerate(mates) for b in mates[i + 1:]],
            noise.robot_observation, sonar_range_m)
        self.predicted = _virtual_factors(mates, observations)

    def _path(self, robot: int, target_xy: ArrayLike | None) -> _RobotPath:
        snapshot = self.snapshot
        start = np.asarray(snapshot.start_poses[robot], dtype=float)
        waypoints = virtual_waypoints(start, target_xy, self.spacing_m)
        keys = np.concatenate([[snapshot.start_keys[robot]], pose_keys(
            robot, snapshot.next_index[robot] + np.arange(len(waypoints)))]).astype(np.int64)
        poses = np.vstack([start[None], waypoints])
        deltas = between(poses[:-1], poses[1:]).reshape(-1, 3)
        roots = np.empty((len(waypoints), 3, 3))
        if len(waypoints):
            # Every segment after the first is the same straight step along the path.
            distinct = self.noise.odometry(deltas[:2])
            roots[0] = distinct[0]
            roots[1:] = distinct[-1]
        odometry = _PoseFactors(keys[:-1], keys[1:], deltas, roots)
        return _RobotPath(robot, keys, poses, odometry,
                          self._landmark_observations(keys[1:], waypoints))

    def _landmark_observations(self, keys: IntArray, waypoints: FloatArray) -> _LandmarkFactors:
        """Bearing-range readings of known landmarks within sonar range of each waypoint."""
        landmarks = self.snapshot.landmark_positions
        offsets = landmarks[None, :, :] - waypoints[:, None, :2]
        seen_waypoint, seen_landmark = np.nonzero(
            np.hypot(offsets[..., 0], offsets[..., 1]) <= self.sonar_range_m)
        distance, bearing = range_bearing(waypoints[seen_waypoint], landmarks[seen_landmark])
        return _LandmarkFactors(keys[seen_waypoint], self.snapshot.landmark_keys[seen_landmark],
                                bearing, distance, waypoints[seen_waypoint],
                                landmarks[seen_landmark],
                                np.broadcast_to(self.noise.bearing_range,
                                                (len(seen_waypoint), 2, 2)))

    def build(self, target_xy: ArrayLike) -> VirtualScenario:
        """Virtual paths and measurements of the candidate ``target_xy`` (2,) [m]."""
        own = self._path(self.snapshot.robot_id, target_xy)
        observations = _robot_observations([(own, mate) for mate in self._teammates],
                                           self.noise.robot_observation, self.sonar_range_m)
        next_factors = _virtual_factors([own], observations)
        boundary = next_factors.touched_keys() - set(next_factors.waypoint_keys.tolist())
        return VirtualScenario(self.snapshot.robot_id, self.predicted, next_factors,
                               tuple(sorted(boundary)))


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
