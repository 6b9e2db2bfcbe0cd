"""Team graphs from scripted trajectories with exact measurements, for tests and benchmarks.

``exact_team_slam`` feeds one robot's ``TeamSlam`` with what every robot of a scripted
team would measure at its keyframes if the sensors were exact: odometry between
successive keyframes (with a chosen covariance, so uncertainty grows along paths),
bearing-range readings of the landmarks in sonar range, and readings of teammates in
range. Estimates then equal the scripted poses while the covariances are those of the
noise models: a controlled setting for the planners' behaviour tests and for timing.
"""
from __future__ import annotations

from typing import Collection, Mapping, Sequence

import numpy as np

from em_exploration_ros.core.geometry import between, range_bearing
from em_exploration_ros.core.params import BOUND_95_TO_SIGMA, ExplorationParams
from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      TeammateReading)
from em_exploration_ros.core.slam.team_slam import TeamSlam


def exact_team_slam(trajectories: Sequence[np.ndarray], landmarks: Mapping[int, np.ndarray],
                    odometry_covariance: np.ndarray, params: ExplorationParams,
                    meetings: Collection[int] | None = None, robot_id: int = 0) -> TeamSlam:
    """Robot ``robot_id``'s TeamSlam after every robot's keyframes of ``trajectories``.

    Args:
        trajectories: per robot, keyframe poses (K_r, 3) in the map frame; keyframe k of
            every robot is simultaneous. Robot 0's first pose anchors the map.
        landmarks: ``{landmark_id: position (2,)}`` [m], map frame.
        odometry_covariance: (3, 3) covariance of every keyframe-to-keyframe odometry.
        params: sensor range and noise, SLAM parameters.
        meetings: keyframe indices at which robots in range read each other, besides the
            first keyframe (which they need to be anchored); None: at every keyframe.
        robot_id: whose TeamSlam is built.
    """
    sensors = params.sensors
    slam = TeamSlam(robot_id, len(trajectories), params.slam, trajectories[0][0])
    teammate_covariance = np.diag(
        [(sensors.robot_obs_xy_bound_m / BOUND_95_TO_SIGMA) ** 2] * 2
        + [(sensors.robot_obs_theta_bound_rad / BOUND_95_TO_SIGMA) ** 2])
    ids = sorted(landmarks)
    points = np.array([landmarks[i] for i in ids], dtype=float).reshape(-1, 2)
    for robot, poses in enumerate(trajectories):
        for index, pose in enumerate(poses):
            distance, bearing = range_bearing(pose, points)
            readings = tuple(
                LandmarkReading(ids[j], float(distance[j]), float(bearing[j]),
                                sensors.sonar_range_sigma_m ** 2,
                                sensors.sonar_bearing_sigma_rad ** 2)
                for j in np.flatnonzero(distance <= sensors.sonar_max_range_m))
            reads_teammates = index == 0 or meetings is None or index in meetings
            mates = tuple(
                TeammateReading(other, between(pose, others[index]), teammate_covariance)
                for other, others in enumerate(trajectories)
                if other != robot and index < len(others) and reads_teammates
                and np.hypot(*(others[index][:2] - pose[:2])) <= sensors.sonar_max_range_m)
            slam.add_keyframe(KeyframeMeasurements(
                robot, index, float(index), index == 0, index - 1,
                np.zeros(3) if index == 0 else between(poses[index - 1], pose),
                np.zeros((3, 3)) if index == 0 else np.asarray(odometry_covariance), readings,
                mates))
    slam.update()
    return slam
