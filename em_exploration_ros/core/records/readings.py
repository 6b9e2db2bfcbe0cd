"""What a robot measures, as plain data: one sonar return, one teammate detection, one step's
odometry, and everything one robot measured at one keyframe (the unit the team shares).

The world's simulated sensors produce these (``core/world/sensors.py``), a robot's SLAM
consumes them (``core/slam/team_slam.py``), and the team stream carries keyframes between
robots (``core/records/team_data.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from em_exploration_ros.core.params import BOUND_95_TO_SIGMA, SensorParams
from em_exploration_ros.core.records.limits import MAX_ID

FloatArray = NDArray[np.float64]

#: (robot id, keyframe index) of one graph pose.
KeyframeId = tuple[int, int]

#: ``LandmarkReading.landmark_id`` of a sonar detection that names no landmark: every
#: detection when ``sensors.landmark_ids`` is false, a false detection (clutter) when it is
#: true. The largest id (``limits.MAX_ID``), so it fits the uint32 id of a LandmarkDetection
#: message and passes a receiver's id checks unchanged.
UNIDENTIFIED = MAX_ID


@dataclass(frozen=True)
class LandmarkReading:
    """One sonar return: range [m] and bearing [rad, observer body frame, wrapped] of a
    landmark centre, with the variances of their noise [m^2], [rad^2].

    ``landmark_id`` names the landmark: in a sonar scan, the world's landmark (the sonar's
    own association) or :data:`UNIDENTIFIED`; in a keyframe, the landmark of the team graph
    the observer associated it with (see ``TeamSlam``)."""

    landmark_id: int
    range_m: float
    bearing_rad: float
    range_variance: float
    bearing_variance: float

    @property
    def identified(self) -> bool:
        """True unless ``landmark_id`` is :data:`UNIDENTIFIED`."""
        return self.landmark_id != UNIDENTIFIED


@dataclass(frozen=True)
class TeammateReading:
    """Pose ``(x [m], y [m], theta [rad])`` of teammate ``robot_id`` in the observer's body
    frame, with the ``(3, 3)`` covariance of its additive noise in those coordinates."""

    robot_id: int
    relative_pose: FloatArray
    covariance: FloatArray


@dataclass(frozen=True)
class OdometryReading:
    """Motion ``(dx [m], dy [m], dtheta [rad])`` over one step, in the previous body frame,
    with the ``(3, 3)`` covariance of its additive noise in those coordinates."""

    delta: FloatArray
    covariance: FloatArray



@dataclass(frozen=True)
class LateReading:
    """A sonar return of the same robot's earlier keyframe ``keyframe_index`` that names its
    landmark only at a later keyframe: a sighting of a tentative track, carried by the
    keyframe at which the track was confirmed as a landmark (without landmark identities,
    ``core.slam.own_landmarks``)."""

    keyframe_index: int
    reading: LandmarkReading


@dataclass(frozen=True)
class KeyframeMeasurements:
    """Everything one robot measured at one keyframe, as shared with its teammates.

    ``index = step // keyframe_interval_steps``; keyframes of different robots with the
    same index are simultaneous. ``odom_delta`` is the motion from keyframe
    ``previous_index`` to this one, expressed in the previous keyframe's body frame
    (``x [m], y [m], theta [rad]``), and ``odom_covariance`` the covariance of its
    additive coordinate errors. A robot's first keyframe has ``is_first=True``,
    ``previous_index=-1`` and its odometry fields are ignored. Every teammate reading
    refers to the observed teammate's keyframe with the same ``index``. ``late_landmarks``
    are readings of earlier keyframes of the robot that named their landmark only at this
    one (a tentative track's sightings before it was confirmed).
    """

    robot_id: int
    index: int
    stamp_s: float
    is_first: bool
    previous_index: int
    odom_delta: np.ndarray
    odom_covariance: np.ndarray
    landmarks: tuple[LandmarkReading, ...]
    teammates: tuple[TeammateReading, ...]
    late_landmarks: tuple[LateReading, ...] = ()

    @property
    def keyframe_id(self) -> KeyframeId:
        """``(robot_id, index)``."""
        return self.robot_id, self.index


def sonar_variances(sensor_params: SensorParams) -> tuple[float, float]:
    """Variances of a sonar reading's noise: range [m^2] and bearing [rad^2]."""
    return sensor_params.sonar_range_sigma_m ** 2, sensor_params.sonar_bearing_sigma_rad ** 2


def teammate_covariance(sensor_params: SensorParams) -> FloatArray:
    """Covariance ``(3, 3)`` of a teammate reading's additive noise, ``diag(sxy^2, sxy^2,
    stheta^2)`` in the observer's body frame [m^2, m^2, rad^2]."""
    xy_variance = (sensor_params.robot_obs_xy_bound_m / BOUND_95_TO_SIGMA) ** 2
    theta_variance = (sensor_params.robot_obs_theta_bound_rad / BOUND_95_TO_SIGMA) ** 2
    return np.diag([xy_variance, xy_variance, theta_variance])
