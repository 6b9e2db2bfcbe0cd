"""The world simulator's state and physics: ground truth, sensing and motion.

``WorldSimulation`` owns the world (seeded, or from a world file) and every robot's true
pose. Each step it produces what each robot's sensors report (``SensorFrame``, in the form
it takes on the wire) and applies each robot's velocity command. The ``em-world`` ROS node
and em-sim both drive this class, so they produce the same numbers.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.readings import LandmarkReading, TeammateReading
from em_exploration_ros.core.records.wire_model import (DeadReckoningIntegrator,
                                                        increment_covariance_to_twist, sim_time_s,
                                                        twist_to_command)
from em_exploration_ros.core.world.sensors import SensorSimulator
from em_exploration_ros.core.world.world import World, advance_robot, run_seed_sequences
from em_exploration_ros.core.world.world_file import world_for_params


@dataclass(frozen=True)
class SensorFrame:
    """One robot's sensor output at one step, as published.

    ``odom_pose``: dead-reckoning pose in ``robot_<i>/odom`` (x [m], y [m], theta [rad]);
    ``odom_pose_covariance``: 3x3 covariance of its accumulated noise (odom frame);
    ``twist_covariance``: 6x6 covariance of the last step's velocity (nav_msgs/Odometry
    convention), from which the robot recovers the per-step increment covariance.
    """

    robot_id: int
    step: int
    stamp_s: float
    odom_pose: np.ndarray
    odom_pose_covariance: np.ndarray
    twist_covariance: np.ndarray
    landmarks: tuple[LandmarkReading, ...]
    teammates: tuple[TeammateReading, ...]


class WorldSimulation:
    """Ground truth and physics of one seeded run (world frame).

    The world is ``world`` if given, else the run's (``world_for_params``: read from
    ``params.world.file``, or generated from ``params.run.seed``; ``ValueError`` if it
    cannot be); the seed draws the sensor noise either way."""

    def __init__(self, params: ExplorationParams, world: World | None = None) -> None:
        self.params = params
        _, sensor_sequence = run_seed_sequences(params.run.seed)
        self.world: World = world_for_params(params) if world is None else world
        self._sensors = SensorSimulator(self.world, params.sensors, params.motion, sensor_sequence)
        n = params.world.num_robots
        self._true_poses = np.array(self.world.start_poses, dtype=float)
        self._dead_reckoning = [DeadReckoningIntegrator() for _ in range(n)]
        self._twist_covariance = [np.zeros((6, 6)) for _ in range(n)]
        self.active = np.ones(n, dtype=bool)
        self.step = 0
        self._detection_sources: list[tuple[int, ...]] = [() for _ in range(n)]

    @property
    def stamp_s(self) -> float:
        """Simulation time of the current step [s]."""
        return sim_time_s(self.step, self.params.motion.time_step_s)

    def true_pose(self, robot_id: int) -> np.ndarray:
        """True world-frame pose (3,) of a robot at the current step."""
        return self._true_poses[robot_id].copy()

    def true_positions(self) -> np.ndarray:
        """True world-frame positions (N, 2) [m] of every robot at the current step."""
        return self._true_poses[:, :2].copy()

    def sense(self, robot_id: int) -> SensorFrame:
        """What robot ``robot_id``'s sensors report at the current step."""
        pose = self._true_poses[robot_id]
        readings, self._detection_sources[robot_id] = self._sensors.sonar_scan(robot_id, pose)
        return SensorFrame(
            robot_id=robot_id, step=self.step, stamp_s=self.stamp_s,
            odom_pose=self._dead_reckoning[robot_id].pose,
            odom_pose_covariance=self._dead_reckoning[robot_id].covariance,
            twist_covariance=self._twist_covariance[robot_id].copy(),
            landmarks=tuple(readings),
            teammates=tuple(self._sensors.teammates(robot_id, self._true_poses, self.active)))

    def detection_sources(self, robot_id: int) -> tuple[int, ...]:
        """Truth side only: where each sonar reading of robot ``robot_id``'s latest
        :meth:`sense` came from, in the readings' order: a landmark id, or
        ``sensors.CLUTTER`` for a false detection."""
        return self._detection_sources[robot_id]

    def apply_command(self, robot_id: int, linear_x: float, angular_z: float) -> None:
        """Move a robot for one step by its velocity command (Twist: m/s, rad/s)."""
        time_step = self.params.motion.time_step_s
        turn, forward = twist_to_command(linear_x, angular_z, time_step)
        previous = self._true_poses[robot_id].copy()
        current, _ = advance_robot(self.world, previous, turn, forward, self.params.motion)
        self._true_poses[robot_id] = current
        reading = self._sensors.odometry(robot_id, previous, current)
        self._dead_reckoning[robot_id].add(reading.delta, reading.covariance)
        self._twist_covariance[robot_id] = increment_covariance_to_twist(reading.covariance,
                                                                         time_step)

    def advance(self) -> None:
        """Move on to the next step (after every robot's command was applied)."""
        self.step += 1
