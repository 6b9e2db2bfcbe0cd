"""Simulated sonar, teammate detector and dead-reckoning odometry with seeded noise.

All noise is zero-mean Gaussian with ``sigma = 95% bound / BOUND_95_TO_SIGMA`` and is
not clipped. Every robot has one independent ``numpy.random.Generator`` per sensor,
derived from the simulator's seed sequence by ``(robot_id, sensor index)``; each call
of a sensor draws a fixed number of normals (independent of what is visible), so the
noise of the k-th call of a robot's sensor depends only on the seed, the robot id, the
sensor and k: never on other robots or on the order of calls across robots.

The sonar's misses (``detection_probability``) and false detections (``clutter_rate``) draw
from a fourth stream of their own, ``DETECTION_STREAM``, and only when the sonar is not the
paper's ideal one: the ideal sonar draws the same noise as before they existed. Its k-th
scan draws one uniform per landmark of the world (detected when below the probability),
then a Poisson count of false detections and their ranges and bearings.

With ``SensorParams.noise_enabled = False`` the outputs are exact, while the reported
variances and covariances stay those of the noise model, so an estimator is configured
the same way in both cases.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.geometry import between, range_bearing, wrap_angle
from em_exploration_ros.core.params import BOUND_95_TO_SIGMA, MotionParams, SensorParams
from em_exploration_ros.core.records.readings import (UNIDENTIFIED, LandmarkReading,
                                                      OdometryReading, TeammateReading,
                                                      sonar_variances, teammate_covariance)
from em_exploration_ros.core.world.world import World, derive_seed_sequence

FloatArray = NDArray[np.float64]

#: Index of each sensor's stream under a robot's branch of the seed sequence.
SONAR_STREAM, TEAMMATE_STREAM, ODOMETRY_STREAM, DETECTION_STREAM = 0, 1, 2, 3
#: Truth of a sonar detection that came from no landmark (clutter), in ``sonar_scan``'s sources.
CLUTTER = -1

#: A step shorter than this [m] counts as no translation; a smaller turn [rad] as no turn.
_STILL_TOLERANCE = 1e-12


def odometry_covariance_per_step(step_length_m: float, turned: bool,
                                 sensor_params: SensorParams) -> FloatArray:
    """Covariance ``(3, 3)`` of one step's odometry noise, in the previous body frame.

    With ``K = odometry_interval_steps`` and ``d = step_length_m * K`` the distance of one
    interval at this step length, the per-step noise is independent in each coordinate:

    - heading: variance ``(gyro_bound_rad / 1.96)^2 / K``, if the robot moved or turned;
    - translation: variance ``(min(accel_bound_m, accel_bound_fraction * d) / 1.96)^2 / K``
      along the direction of travel and the same across it (isotropic, so the same in any
      frame), if the robot moved.

    Summed over one interval of K steps, the 95% bounds are the paper's gyro (0.5 deg)
    and accelerometer (0.05 m) errors. A robot that neither moved nor turned has zero
    covariance (its reading is exact).
    """
    steps = sensor_params.odometry_interval_steps
    moved = step_length_m > _STILL_TOLERANCE
    covariance = np.zeros((3, 3))
    if moved or turned:
        covariance[2, 2] = (sensor_params.gyro_bound_rad / BOUND_95_TO_SIGMA) ** 2 / steps
    if moved:
        bound = min(sensor_params.accel_bound_m,
                    sensor_params.accel_bound_fraction * step_length_m * steps)
        covariance[0, 0] = covariance[1, 1] = (bound / BOUND_95_TO_SIGMA) ** 2 / steps
    return covariance


class SensorSimulator:
    """The sensors of every robot of a team in one simulated world (world frame, truth in)."""

    def __init__(self, world: World, sensor_params: SensorParams, motion_params: MotionParams,
                 seed_sequence: np.random.SeedSequence) -> None:
        """Create one noise stream per robot and sensor from ``seed_sequence``.

        Robot ``i``'s sensor ``s`` draws from ``derive_seed_sequence(seed_sequence, i, s)``
        (``s`` is ``SONAR_STREAM``, ``TEAMMATE_STREAM`` or ``ODOMETRY_STREAM``);
        ``seed_sequence`` itself is not modified.
        """
        self._world = world
        self._params = sensor_params
        self._motion = motion_params
        self._streams = [
            [np.random.default_rng(derive_seed_sequence(seed_sequence, robot, sensor))
             for sensor in (SONAR_STREAM, TEAMMATE_STREAM, ODOMETRY_STREAM, DETECTION_STREAM)]
            for robot in range(world.num_robots)]
        self._range_variance, self._bearing_variance = sonar_variances(sensor_params)
        self._teammate_covariance = teammate_covariance(sensor_params)

    @property
    def motion_params(self) -> MotionParams:
        """Kinematic parameters of the simulated robots."""
        return self._motion

    def _normals(self, robot_id: int, sensor: int, shape: tuple[int, ...]) -> FloatArray:
        """Standard normals from the robot's stream of ``sensor`` (zeros if noise is off)."""
        if not 0 <= robot_id < self._world.num_robots:
            raise ValueError(f"robot_id {robot_id} outside [0, {self._world.num_robots})")
        if not self._params.noise_enabled:
            return np.zeros(shape)
        return self._streams[robot_id][sensor].standard_normal(shape)

    def sonar(self, robot_id: int, true_pose: ArrayLike) -> list[LandmarkReading]:
        """One scan of robot ``robot_id`` at the true pose ``(3,)`` (world frame): the
        readings of :meth:`sonar_scan`, without their truth."""
        return self.sonar_scan(robot_id, true_pose)[0]

    def sonar_scan(self, robot_id: int, true_pose: ArrayLike
                   ) -> tuple[list[LandmarkReading], tuple[int, ...]]:
        """One scan of robot ``robot_id`` at the true pose ``(3,)`` (world frame) and, for
        the truth side only, where each reading came from (a landmark id or
        :data:`CLUTTER`).

        Each landmark within ``sonar_max_range_m`` is detected with probability
        ``detection_probability``, its range and bearing with independent noise; about
        ``clutter_rate`` false detections (Poisson) are uniform in range
        ``[0, sonar_max_range_m]`` and bearing. With ``landmark_ids`` a detection names its
        landmark (a false one :data:`UNIDENTIFIED`), detections in landmark-id order, then
        the false ones; without, every detection is unidentified and the scan is in
        bearing order (nothing in it tells one landmark from another).
        """
        pose = np.asarray(true_pose, dtype=float)
        noise = self._normals(robot_id, SONAR_STREAM, (self._world.num_landmarks, 2))
        ranges, bearings = range_bearing(pose, self._world.landmarks)
        ranges = ranges + np.sqrt(self._range_variance) * noise[:, 0]
        bearings = wrap_angle(bearings + np.sqrt(self._bearing_variance) * noise[:, 1])
        in_range = (np.linalg.norm(self._world.landmarks - pose[:2], axis=1)
                    <= self._params.sonar_max_range_m)
        clutter_ranges = clutter_bearings = np.zeros(0)
        if self._params.detection_probability < 1.0 or self._params.clutter_rate > 0.0:
            in_range, clutter_ranges, clutter_bearings = self._misses_and_clutter(robot_id,
                                                                                  in_range)
        visible = np.flatnonzero(in_range)
        visible = visible[np.argsort(self._world.landmark_ids[visible], kind="stable")]
        sources = [int(self._world.landmark_ids[k]) for k in visible]
        sources += [CLUTTER] * len(clutter_ranges)
        all_ranges = np.concatenate([ranges[visible], clutter_ranges])
        all_bearings = np.concatenate([bearings[visible], clutter_bearings])
        named = self._params.landmark_ids
        order = np.arange(len(sources)) if named else np.argsort(all_bearings, kind="stable")
        readings = [LandmarkReading(landmark_id=sources[k] if named and sources[k] != CLUTTER
                                    else UNIDENTIFIED,
                                    range_m=float(all_ranges[k]),
                                    bearing_rad=float(all_bearings[k]),
                                    range_variance=self._range_variance,
                                    bearing_variance=self._bearing_variance)
                    for k in order]
        return readings, tuple(sources[k] for k in order)

    def _misses_and_clutter(self, robot_id: int, in_range: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """From the robot's ``DETECTION_STREAM``: which of the landmarks ``in_range`` (M,)
        bool are detected, and the ranges [m] and bearings [rad] of the false detections."""
        if not 0 <= robot_id < self._world.num_robots:
            raise ValueError(f"robot_id {robot_id} outside [0, {self._world.num_robots})")
        stream = self._streams[robot_id][DETECTION_STREAM]
        detected = in_range & (stream.random(self._world.num_landmarks)
                               < self._params.detection_probability)
        count = int(stream.poisson(self._params.clutter_rate))
        clutter_ranges = stream.uniform(0.0, self._params.sonar_max_range_m, count)
        clutter_bearings = wrap_angle(stream.uniform(-np.pi, np.pi, count))
        return detected, clutter_ranges, np.asarray(clutter_bearings, dtype=float)

    def teammates(self, robot_id: int, true_poses: ArrayLike,
                  active: Sequence[bool] | None = None) -> list[TeammateReading]:
        """Readings of the other active robots within ``sonar_max_range_m`` of robot
        ``robot_id``, sorted by id; ``true_poses`` ``(N, 3)`` are all robots' world poses.

        Each relative pose carries additive noise with covariance
        ``diag(sxy^2, sxy^2, stheta^2)`` in the observer's body frame.
        """
        poses = np.asarray(true_poses, dtype=float)
        count = poses.shape[0]
        noise = self._normals(robot_id, TEAMMATE_STREAM, (count, 3))
        relative = between(poses[robot_id], poses)
        relative = relative + noise * np.sqrt(np.diag(self._teammate_covariance))
        relative[:, 2] = wrap_angle(relative[:, 2])
        seen = np.linalg.norm(poses[:, :2] - poses[robot_id, :2], axis=1) \
            <= self._params.sonar_max_range_m
        seen[robot_id] = False
        if active is not None:
            seen &= np.asarray(active, dtype=bool)
        return [TeammateReading(robot_id=int(j), relative_pose=relative[j].copy(),
                                covariance=self._teammate_covariance.copy())
                for j in np.flatnonzero(seen)]

    def odometry(self, robot_id: int, true_previous: ArrayLike,
                 true_current: ArrayLike) -> OdometryReading:
        """Dead-reckoning reading of one step between two true world poses ``(3,)``: the true
        motion in the previous body frame plus noise with the covariance of
        :func:`odometry_covariance_per_step` (exact reading if the robot stayed still)."""
        true_delta = between(true_previous, true_current)
        noise = self._normals(robot_id, ODOMETRY_STREAM, (3,))
        covariance = odometry_covariance_per_step(
            float(np.hypot(true_delta[0], true_delta[1])),
            bool(abs(true_delta[2]) > _STILL_TOLERANCE), self._params)
        delta = true_delta + noise * np.sqrt(np.diag(covariance))
        delta[2] = wrap_angle(delta[2])
        return OdometryReading(delta=delta, covariance=covariance)
