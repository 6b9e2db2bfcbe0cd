"""What em-world publishes, from core data (``core/sessions/world_effects.py``): it only
converts and publishes (QoS from nodes/qos.py).

- ``/clock`` (rosgraph_msgs/Clock): the simulation time of the current step;
- ``/mission/anchor_pose`` (PoseStamped, latched, frame ``map``): robot 0's launch pose;
- ``/tf_static`` ``world`` -> ``map`` (from the anchor) and ``/tf`` ``world`` ->
  ``robot_i/base_link_truth`` every step (nodes/tf_publishing.py);
- per robot i: ``/robot_i/sonar`` (SonarScan), ``/robot_i/odom`` (Odometry, REP-105
  ``robot_i/odom`` -> ``robot_i/base_link``);
- ground truth, under ``/world`` only: ``/world/ground_truth/robot_i`` (Odometry, frame
  ``world``, every step), ``/world/landmarks`` (LandmarkArray, latched),
  ``/world/markers`` (MarkerArray, latched: landmarks and the map border),
  ``/world/status`` (WorldStatus, latched) and, when the sonar is not the paper's ideal
  one, ``/world/sonar_truth/robot_i`` (SonarTruth, every keyframe step: where each
  detection came from, for the evaluator's association counts; no robot reads it).
"""
from __future__ import annotations

import numpy as np
from em_exploration_msgs.msg import LandmarkArray, SonarScan, SonarTruth, WorldStatus
from geometry_msgs.msg import Point, PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import LandmarkEstimate
from em_exploration_ros.core.sessions.world_effects import (PublishClock, PublishSensors,
                                                            PublishSonarTruth, PublishStatus,
                                                            PublishTruth)
from em_exploration_ros.core.world.sensors import CLUTTER
from em_exploration_ros.core.world.world import World
from em_exploration_ros.nodes import tf_publishing
from em_exploration_ros.nodes.conversions import (MAP_FRAME, WORLD_FRAME, WORLD_STATUS_TOPIC,
                                                  landmark_array_to_msg, robot_namespace,
                                                  seconds_to_time, serialized_dead_reckoning,
                                                  serialized_odometry, sonar_scan_to_msg,
                                                  yaw_to_quaternion)
from em_exploration_ros.nodes.input_guard import listened
from em_exploration_ros.nodes.qos import CLOCK_QOS, GROUND_TRUTH_QOS, LATCHED_QOS, SENSOR_QOS

#: Height of the landmark cylinders drawn in /world/markers [m].
_MARKER_HEIGHT_M = 1.0


def world_markers(world: World, stamp_s: float) -> MarkerArray:
    """Landmarks as cylinders (true radius) and the mission border, frame ``world``."""
    def marker(marker_id: int, marker_type: int, rgba: tuple[float, ...]) -> Marker:
        m = Marker(ns="world", id=marker_id, type=marker_type, action=Marker.ADD)
        m.header.stamp = seconds_to_time(stamp_s)
        m.header.frame_id = WORLD_FRAME
        m.color = ColorRGBA(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
        m.pose.orientation.w = 1.0
        return m

    border = marker(0, Marker.LINE_STRIP, (0.2, 0.2, 0.2, 1.0))
    border.scale.x = 0.2
    corners = [(0.0, 0.0), (world.width_m, 0.0), (world.width_m, world.height_m),
               (0.0, world.height_m), (0.0, 0.0)]
    border.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in corners]
    markers = [border]
    diameter = 2.0 * max(world.landmark_radius_m, 0.05)
    for landmark_id, (x, y) in zip(world.landmark_ids, world.landmarks):
        cylinder = marker(1 + int(landmark_id), Marker.CYLINDER, (0.45, 0.3, 0.15, 1.0))
        cylinder.pose.position.x, cylinder.pose.position.y = float(x), float(y)
        cylinder.pose.position.z = _MARKER_HEIGHT_M / 2.0
        cylinder.scale.x = cylinder.scale.y = diameter
        cylinder.scale.z = _MARKER_HEIGHT_M
        markers.append(cylinder)
    return MarkerArray(markers=markers)


class WorldOutputs:
    """em-world's publishers (see module docstring) and the publishing of each effect."""

    def __init__(self, node: Node, params: ExplorationParams, run_id: int) -> None:
        self.max_range_m = params.sensors.sonar_max_range_m
        self.run_id = run_id  # carried by every project message it publishes
        self.clock_pub = node.create_publisher(Clock, "/clock", CLOCK_QOS)
        self.anchor_pub = node.create_publisher(PoseStamped, "/mission/anchor_pose",
                                                LATCHED_QOS)
        self.landmarks_pub = node.create_publisher(LandmarkArray, "/world/landmarks",
                                                   LATCHED_QOS)
        self.markers_pub = node.create_publisher(MarkerArray, "/world/markers", LATCHED_QOS)
        self.status_pub = node.create_publisher(WorldStatus, WORLD_STATUS_TOPIC, LATCHED_QOS)
        self.tf_pub = tf_publishing.create_tf_publisher(node)
        self.tf_static_pub = tf_publishing.create_tf_static_publisher(node)
        self.sonar_pubs, self.odom_pubs, self.truth_pubs = [], [], []
        self._truth_frames = []
        for robot in range(params.world.num_robots):
            ns = robot_namespace(robot)
            self.sonar_pubs.append(node.create_publisher(SonarScan, f"/{ns}/sonar", SENSOR_QOS))
            self.odom_pubs.append(node.create_publisher(Odometry, f"/{ns}/odom", SENSOR_QOS))
            self.truth_pubs.append(node.create_publisher(
                Odometry, f"/world/ground_truth/{ns}", GROUND_TRUTH_QOS))
            self._truth_frames.append(f"{ns}/base_link")
        self.sonar_truth_pubs = [] if params.sensors.ideal_sonar else [
            node.create_publisher(SonarTruth, f"/world/sonar_truth/{robot_namespace(robot)}",
                                  GROUND_TRUTH_QOS)
            for robot in range(params.world.num_robots)]

    def mission(self, world: World, stamp_s: float) -> None:
        """The latched mission set-up at the first step's time ``stamp_s`` [s]: robot 0's
        launch pose, the landmarks, the markers, and the static ``world`` -> ``map``
        transform it defines."""
        anchor = PoseStamped()
        anchor.header.stamp = seconds_to_time(stamp_s)
        anchor.header.frame_id = MAP_FRAME
        start = world.start_poses[0]
        anchor.pose.position.x, anchor.pose.position.y = float(start[0]), float(start[1])
        anchor.pose.orientation = yaw_to_quaternion(float(start[2]))
        self.anchor_pub.publish(anchor)
        self.tf_static_pub.publish(tf_publishing.tf_message(
            stamp_s, [tf_publishing.anchor_transform(start, start)]))
        landmarks = [LandmarkEstimate(int(i), p, np.zeros((2, 2)))
                     for i, p in zip(world.landmark_ids, world.landmarks)]
        self.landmarks_pub.publish(landmark_array_to_msg(stamp_s, WORLD_FRAME, landmarks,
                                                         world.landmark_radius_m))
        self.markers_pub.publish(world_markers(world, stamp_s))

    def clock(self, effect: PublishClock) -> None:
        """/clock at the step's time."""
        self.clock_pub.publish(Clock(clock=seconds_to_time(effect.stamp_s)))

    def sensors(self, effect: PublishSensors) -> None:
        """A robot's sonar scan (barrier and delivery counts in it) and dead reckoning."""
        scan = sonar_scan_to_msg(effect.frame, self.max_range_m, effect.team_sequences)
        scan.run_id = self.run_id
        if effect.delivered is not None:
            scan.delivered_updates, scan.delivered_requests = effect.delivered
        self.sonar_pubs[effect.robot].publish(scan)
        self.odom_pubs[effect.robot].publish(serialized_dead_reckoning(effect.frame))

    def truth(self, effect: PublishTruth) -> None:
        """Every robot's true pose on its ground-truth topic, and /tf if anyone listens."""
        for robot, pose in enumerate(effect.poses):
            self.truth_pubs[robot].publish(serialized_odometry(
                effect.stamp_s, pose, WORLD_FRAME, self._truth_frames[robot]))
        if listened(self.tf_pub):
            self.tf_pub.publish(tf_publishing.tf_message(
                effect.stamp_s, tf_publishing.truth_transforms(list(effect.poses))))

    def sonar_truth(self, effect: PublishSonarTruth) -> None:
        """Where each detection of a robot's keyframe scan came from (CLUTTER: none)."""
        message = SonarTruth(
            run_id=self.run_id, robot_id=effect.robot, step=effect.step,
            range=[float(r.range_m) for r in effect.readings],
            bearing=[float(r.bearing_rad) for r in effect.readings],
            source=[SonarTruth.CLUTTER if s == CLUTTER else int(s) for s in effect.sources])
        message.header.stamp = seconds_to_time(effect.stamp_s)
        message.header.frame_id = self._truth_frames[effect.robot]
        self.sonar_truth_pubs[effect.robot].publish(message)

    def status(self, effect: PublishStatus) -> None:
        """/world/status: the current step, whether stepping is over for good, and why."""
        header = Header(stamp=seconds_to_time(effect.stamp_s), frame_id=WORLD_FRAME)
        self.status_pub.publish(WorldStatus(header=header, run_id=self.run_id,
                                            step=effect.step,
                                            stepping_over=effect.stepping_over,
                                            reason=effect.reason))
