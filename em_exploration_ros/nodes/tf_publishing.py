"""The system's TF: tf2_msgs/TFMessage on /tf and /tf_static, frames as in core/frames.py.

Who publishes what (all stamped with the simulation time of the pose they carry):

| transform | topic | publisher | when |
|---|---|---|---|
| ``world`` -> ``map`` | /tf_static | em-world | once, at start (the mission anchor) |
| ``world`` -> ``robot_<i>/base_link_truth`` | /tf | em-world | every step, all robots |
| ``map`` -> ``robot_<i>/odom`` | /tf | em-robot i | every step it processes, once anchored |
| ``robot_<i>/odom`` -> ``robot_<i>/base_link`` | /tf | em-robot i | with the one above |

A robot publishes its two transforms in one message with one stamp, so a tf2 lookup of
``map`` -> ``robot_<i>/base_link`` at that time composes the SLAM correction with the dead
reckoning of the same step: the robot's own estimate of its current pose.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.publisher import Publisher
from tf2_msgs.msg import TFMessage

from em_exploration_ros.core.frames import map_in_world, odom_in_map
from em_exploration_ros.nodes.conversions import (MAP_FRAME, WORLD_FRAME, robot_namespace,
                                                  seconds_to_time, yaw_to_quaternion)
from em_exploration_ros.nodes.qos import TF_QOS, TF_STATIC_QOS

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

#: One transform: (parent frame, child frame, pose (x [m], y [m], theta [rad]) of the child in
#: the parent).
FrameTransform = tuple[str, str, np.ndarray]


def odom_frame(robot_id: int) -> str:
    """``robot_<i>/odom``: robot i's dead-reckoning frame."""
    return f"{robot_namespace(robot_id)}/odom"


def base_frame(robot_id: int) -> str:
    """``robot_<i>/base_link``: robot i's body, as the robot estimates it."""
    return f"{robot_namespace(robot_id)}/base_link"


def truth_frame(robot_id: int) -> str:
    """``robot_<i>/base_link_truth``: robot i's body where it truly is (under ``world``)."""
    return f"{robot_namespace(robot_id)}/base_link_truth"


def transform_stamped(stamp_s: float, transform: FrameTransform) -> TransformStamped:
    """One planar transform as geometry_msgs/TransformStamped at simulation time ``stamp_s``."""
    parent, child, pose = transform
    message = TransformStamped()
    message.header.stamp = seconds_to_time(stamp_s)
    message.header.frame_id = parent
    message.child_frame_id = child
    message.transform.translation.x = float(pose[0])
    message.transform.translation.y = float(pose[1])
    message.transform.rotation = yaw_to_quaternion(float(pose[2]))
    return message


def tf_message(stamp_s: float, transforms: Iterable[FrameTransform]) -> TFMessage:
    """Transforms of one instant [s] as one TFMessage."""
    return TFMessage(transforms=[transform_stamped(stamp_s, t) for t in transforms])


def robot_transforms(robot_id: int, base_in_map: np.ndarray,
                     base_in_odom: np.ndarray) -> list[FrameTransform]:
    """Robot i's ``map`` -> ``odom`` (its SLAM correction) and ``odom`` -> ``base_link`` (its
    dead reckoning), from its estimated pose in ``map`` and its odometry pose of one step."""
    return [(MAP_FRAME, odom_frame(robot_id), odom_in_map(base_in_map, base_in_odom)),
            (odom_frame(robot_id), base_frame(robot_id), np.asarray(base_in_odom, dtype=float))]


def truth_transforms(true_poses: Sequence[np.ndarray]) -> list[FrameTransform]:
    """``world`` -> ``robot_<i>/base_link_truth`` for every robot (true world-frame poses)."""
    return [(WORLD_FRAME, truth_frame(robot), np.asarray(pose, dtype=float))
            for robot, pose in enumerate(true_poses)]


def anchor_transform(anchor_in_world: np.ndarray, anchor_in_map: np.ndarray) -> FrameTransform:
    """The static ``world`` -> ``map`` from the mission anchor known in both frames."""
    return (WORLD_FRAME, MAP_FRAME, map_in_world(anchor_in_world, anchor_in_map))


def create_tf_publisher(node: Node) -> Publisher:
    """A /tf publisher with tf2's QoS."""
    return node.create_publisher(TFMessage, TF_TOPIC, TF_QOS)


def create_tf_static_publisher(node: Node) -> Publisher:
    """A /tf_static publisher with tf2's QoS (transient local)."""
    return node.create_publisher(TFMessage, TF_STATIC_TOPIC, TF_STATIC_QOS)
