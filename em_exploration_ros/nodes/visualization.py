"""What a robot shows its users, as standard messages RViz and Foxglove display.

- nav_msgs/OccupancyGrid: the virtual map's occupancy (0..100, -1 unknown);
- visualization_msgs/MarkerArray: virtual-map covariance ellipses (3-sigma, flat
  cylinders), frontier candidates by type, the chosen target and the landmark estimates.
All in the ``map`` frame.
"""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point
from nav_msgs.msg import OccupancyGrid
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.virtual_map.ellipses import covariance_ellipses
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid as CoreGrid
from em_exploration_ros.nodes.conversions import MAP_FRAME, seconds_to_time, yaw_to_quaternion

#: Colours of the frontier types, as in the paper's figures.
FRONTIER_COLOURS = {FrontierType.EXPLORATION: (0.1, 0.7, 0.1),
                    FrontierType.REVISITING: (0.1, 0.3, 0.9),
                    FrontierType.RENDEZVOUS: (0.6, 0.1, 0.7)}


def occupancy_grid_to_msg(grid: CoreGrid, stamp_s: float) -> OccupancyGrid:
    """The occupancy grid: probability in percent, -1 for never observed cells."""
    message = OccupancyGrid()
    message.header.stamp = seconds_to_time(stamp_s)
    message.header.frame_id = MAP_FRAME
    geometry = grid.geometry
    message.info.resolution = float(geometry.cell_size_m)
    message.info.width = geometry.cols
    message.info.height = geometry.rows
    message.info.origin.orientation.w = 1.0
    percent = np.rint(grid.probability() * 100.0).astype(np.int8)
    percent[grid.observation_count() == 0] = -1
    message.data = percent.ravel().tolist()
    return message


def _marker(namespace: str, marker_id: int, marker_type: int, stamp_s: float,
            rgb: tuple[float, float, float], alpha: float = 1.0) -> Marker:
    marker = Marker(ns=namespace, id=marker_id, type=marker_type, action=Marker.ADD)
    marker.header.stamp = seconds_to_time(stamp_s)
    marker.header.frame_id = MAP_FRAME
    marker.color = ColorRGBA(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)
    marker.pose.orientation.w = 1.0
    return marker


def ellipse_markers(centres: np.ndarray, covariances: np.ndarray, stamp_s: float) -> list[Marker]:
    """Flat cylinders, one per cell: ``centres`` (K, 2) [m], ``covariances`` (K, 2, 2) [m^2],
    at ``ellipses.ELLIPSE_SIGMAS`` (``covariance_ellipses``, as the team map picture)."""
    markers = []
    ellipses = covariance_ellipses(centres, covariances)
    for index, (centre, (major, minor), angle) in enumerate(zip(ellipses.centres, ellipses.axes,
                                                                  ellipses.angles)):
        marker = _marker("virtual_map_covariance", index, Marker.CYLINDER, stamp_s,
                         (0.5, 0.5, 0.5), 0.5)
        marker.pose.position.x, marker.pose.position.y = float(centre[0]), float(centre[1])
        marker.pose.orientation = yaw_to_quaternion(float(angle))
        marker.scale.x, marker.scale.y, marker.scale.z = float(major), float(minor), 0.05
        markers.append(marker)
    return markers


def frontier_markers(candidates: list[Frontier], target: Frontier | None,
                     stamp_s: float) -> list[Marker]:
    """One sphere list per frontier type, and the chosen target as a red cube."""
    markers = []
    for kind, rgb in FRONTIER_COLOURS.items():
        marker = _marker(f"frontiers_{kind.name.lower()}", 0, Marker.SPHERE_LIST, stamp_s, rgb)
        marker.scale.x = marker.scale.y = marker.scale.z = 1.0
        marker.points = [Point(x=float(f.position[0]), y=float(f.position[1]), z=0.0)
                         for f in candidates if f.kind == kind]
        markers.append(marker)
    target_marker = _marker("target", 0, Marker.CUBE, stamp_s, (0.9, 0.1, 0.1))
    target_marker.scale.x = target_marker.scale.y = target_marker.scale.z = 1.5
    if target is None:
        target_marker.action = Marker.DELETE
    else:
        target_marker.pose.position.x = float(target.position[0])
        target_marker.pose.position.y = float(target.position[1])
    markers.append(target_marker)
    return markers


def landmark_markers(landmarks: dict[int, np.ndarray], radius_m: float,
                     stamp_s: float) -> list[Marker]:
    """Estimated landmarks as black cylinders of the landmark radius."""
    markers = []
    for landmark_id, position in sorted(landmarks.items()):
        marker = _marker("landmarks", landmark_id, Marker.CYLINDER, stamp_s, (0.1, 0.1, 0.1))
        marker.pose.position.x, marker.pose.position.y = float(position[0]), float(position[1])
        marker.scale.x = marker.scale.y = 2.0 * max(radius_m, 0.1)
        marker.scale.z = 0.5
        markers.append(marker)
    return markers


def marker_array(stamp_s: float, *groups: list[Marker]) -> MarkerArray:
    """A MarkerArray that first clears the previous one (the clearing marker stamped with the
    simulation time ``stamp_s`` [s] of the markers that replace it)."""
    clear = Marker(action=Marker.DELETEALL)
    clear.header.stamp = seconds_to_time(stamp_s)
    clear.header.frame_id = MAP_FRAME
    return MarkerArray(markers=[clear] + [m for group in groups for m in group])
