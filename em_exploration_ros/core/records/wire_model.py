"""The numeric path data takes between the world simulator and a robot.

On the wire, a robot's motion command is a velocity (geometry_msgs/Twist) and its
dead-reckoning is an integrated odometry pose with a twist covariance
(nav_msgs/Odometry). The world and the robot convert between those and per-step
increments with the functions here. em-sim calls the same functions, so a robot in
em-sim sees bit-identical numbers to a robot process fed over DDS, and seeded runs
choose the same targets in both.
"""
from __future__ import annotations

import math

import numpy as np

from em_exploration_ros.core.geometry import between, compose, compose_jacobians

NANOSECONDS_PER_SECOND = 1_000_000_000


def nanoseconds_to_seconds(nanoseconds: int) -> float:
    """Seconds of an integer nanosecond time, computed as builtin_interfaces/Time is read
    (``sec + nanosec * 1e-9``), so a time survives the wire bit for bit."""
    sec, nanosec = divmod(int(nanoseconds), NANOSECONDS_PER_SECOND)
    return sec + nanosec * 1e-9


def seconds_to_nanoseconds(seconds: float) -> int:
    """Integer nanoseconds of a time in seconds (rounded)."""
    return int(round(seconds * NANOSECONDS_PER_SECOND))


def sim_time_s(step: int, time_step_s: float) -> float:
    """Simulation time of a step [s], in its wire-exact form (see nanoseconds_to_seconds)."""
    return nanoseconds_to_seconds(seconds_to_nanoseconds(step * time_step_s))


def planar_quaternion(yaw: float) -> tuple[float, float]:
    """(z, w) of the unit quaternion of a rotation by ``yaw`` [rad] about +z."""
    return math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def planar_yaw(z: float, w: float) -> float:
    """Yaw [rad] of a rotation about +z given as quaternion (0, 0, z, w)."""
    return math.atan2(2.0 * w * z, 1.0 - 2.0 * z * z)


def pose_through_wire(pose: np.ndarray) -> np.ndarray:
    """A planar pose as it reads after travelling in a geometry_msgs/Pose (yaw as quaternion)."""
    z, w = planar_quaternion(float(pose[2]))
    return np.array([float(pose[0]), float(pose[1]), planar_yaw(z, w)])


def command_to_twist(turn_rad: float, forward_m: float, time_step_s: float) -> tuple[float, float]:
    """A per-step motion (turn [rad], forward distance [m]) as (linear.x [m/s],
    angular.z [rad/s])."""
    return forward_m / time_step_s, turn_rad / time_step_s


def twist_to_command(linear_x: float, angular_z: float, time_step_s: float) -> tuple[float, float]:
    """Inverse of ``command_to_twist``: (turn [rad], forward distance [m]) for one step."""
    return angular_z * time_step_s, linear_x * time_step_s


#: Rows/columns of (x, y, theta) in the 6x6 covariances of ROS messages, which are over
#: (x, y, z, rotation about x, about y, about z).
_PLANAR_INDEX = [0, 1, 5]


def planar_covariance_to_6x6(covariance: np.ndarray) -> np.ndarray:
    """A 3x3 covariance over (x, y, theta) as the 6x6 covariance of a ROS pose or twist; z, roll
    and pitch are exactly zero for a planar robot, so their rows and columns are zero."""
    full = np.zeros((6, 6))
    full[np.ix_(_PLANAR_INDEX, _PLANAR_INDEX)] = np.asarray(covariance)
    return full


def planar_covariance_from_6x6(covariance: np.ndarray) -> np.ndarray:
    """The 3x3 covariance over (x, y, theta) of a ROS pose's 6x6 (x, y, z, roll, pitch,
    yaw): the inverse of ``planar_covariance_to_6x6``."""
    full = np.asarray(covariance, dtype=float).reshape(6, 6)
    return full[np.ix_(_PLANAR_INDEX, _PLANAR_INDEX)].copy()


def increment_covariance_to_twist(covariance: np.ndarray, time_step_s: float) -> np.ndarray:
    """Covariance of a per-step increment (3x3, x/y/theta) as a 6x6 twist covariance.

    nav_msgs/Odometry.twist.covariance is over (vx, vy, vz, wx, wy, wz) in the child frame;
    the increment over one step is velocity times the step, so variances scale by 1/dt^2.
    """
    return planar_covariance_to_6x6(np.asarray(covariance) / time_step_s**2)


def twist_to_increment_covariance(twist_covariance: np.ndarray, time_step_s: float) -> np.ndarray:
    """Inverse of ``increment_covariance_to_twist``: the 3x3 per-step increment covariance."""
    return (np.asarray(twist_covariance).reshape(6, 6)[np.ix_(_PLANAR_INDEX, _PLANAR_INDEX)]
            * time_step_s**2)


class DeadReckoningIntegrator:
    """World side: integrates noisy per-step increments into the published odometry pose,
    and the covariance of that pose's accumulated noise (first order)."""

    def __init__(self) -> None:
        self._pose = np.zeros(3)
        self._covariance = np.zeros((3, 3))

    @property
    def pose(self) -> np.ndarray:
        """Current dead-reckoning pose in the robot's odom frame (x [m], y [m], theta [rad])."""
        return self._pose.copy()

    @property
    def covariance(self) -> np.ndarray:
        """Covariance (3x3, x/y/theta in the odom frame) of the noise accumulated in ``pose``
        since the start (where the odom frame is exact)."""
        return self._covariance.copy()

    def add(self, increment: np.ndarray, covariance: np.ndarray | None = None) -> np.ndarray:
        """Apply one measured increment (body frame of the previous pose) whose noise has
        ``covariance`` (3x3, that body frame; None: exact); returns the pose."""
        increment = np.asarray(increment, dtype=float)
        if covariance is not None:
            j_pose, j_increment = compose_jacobians(self._pose, increment)
            self._covariance = (j_pose @ self._covariance @ j_pose.T
                                + j_increment @ np.asarray(covariance) @ j_increment.T)
        self._pose = compose(self._pose, increment)
        return self.pose


class DeadReckoningDifferencer:
    """Robot side: recovers each per-step increment from consecutive odometry poses."""

    def __init__(self) -> None:
        self._previous: np.ndarray | None = None

    def resume(self, odom_pose: np.ndarray) -> None:
        """Take ``odom_pose`` as the previous pose (after a restart: the pose at the last
        keyframe), so the next increment bridges the gap."""
        self._previous = np.asarray(odom_pose, dtype=float).copy()

    def increment(self, odom_pose: np.ndarray) -> np.ndarray | None:
        """The motion since the previous odometry pose (body frame), None for the first."""
        pose = np.asarray(odom_pose, dtype=float)
        previous, self._previous = self._previous, pose
        if previous is None:
            return None
        return between(previous, pose)
