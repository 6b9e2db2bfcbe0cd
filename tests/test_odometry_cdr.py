"""The world's Odometry in its serialized form (nodes/odometry_cdr.py) against rclpy's own
serialization: what it writes reads back as the message conversions would have built, and
what it reads is what rclpy wrote; anything not in the exact form is left to the caller."""
from __future__ import annotations

import math

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message

from em_exploration_ros.nodes.conversions import (odometry_pose, odometry_twist_covariance,
                                                  serialized_odometry, seconds_to_time)
from em_exploration_ros.nodes.odometry_cdr import OdometryCodec

FRAMES = [("world", "robot_0/base_link"), ("robot_12/odom", "robot_12/base_link"),
          ("ab", "c"), ("", "")]


def built_message(stamp_s: float, pose: np.ndarray, frames: tuple[str, str],
                  pose_covariance: np.ndarray, twist_covariance: np.ndarray) -> Odometry:
    """The Odometry built field by field through rclpy's classes."""
    message = Odometry()
    message.header.stamp = seconds_to_time(stamp_s)
    message.header.frame_id, message.child_frame_id = frames
    message.pose.pose.position.x, message.pose.pose.position.y = float(pose[0]), float(pose[1])
    message.pose.pose.orientation.z = math.sin(pose[2] / 2.0)
    message.pose.pose.orientation.w = math.cos(pose[2] / 2.0)
    message.pose.covariance = pose_covariance.ravel().tolist()
    message.twist.covariance = twist_covariance.ravel().tolist()
    return message


@pytest.mark.parametrize("frames", FRAMES)
def test_written_bytes_read_back_as_the_message_and_rclpy_bytes_read_as_written(
        frames: tuple[str, str]) -> None:
    rng = np.random.default_rng(len(frames[0]))
    pose = np.array([rng.normal(scale=50.0), rng.normal(scale=50.0), rng.uniform(-3.1, 3.1)])
    pose_covariance, twist_covariance = rng.normal(size=(2, 6, 6))
    stamp_s = float(rng.uniform(0.0, 5000.0))
    expected = built_message(stamp_s, pose, frames, pose_covariance, twist_covariance)
    data = serialized_odometry(stamp_s, pose, *frames, twist_covariance, pose_covariance)
    assert len(data) == len(serialize_message(expected)) == OdometryCodec(*frames).size
    assert deserialize_message(data, Odometry) == expected
    decoded = OdometryCodec(*frames).decode(serialize_message(expected))
    assert decoded is not None
    assert decoded.stamp == (expected.header.stamp.sec, expected.header.stamp.nanosec)
    np.testing.assert_array_equal(decoded.pose, odometry_pose(expected))
    np.testing.assert_array_equal(decoded.pose_covariance, pose_covariance)
    np.testing.assert_array_equal(decoded.twist_covariance, odometry_twist_covariance(expected))


def test_anything_not_in_the_exact_form_is_left_to_the_message_checks() -> None:
    codec = OdometryCodec("world", "robot_0/base_link")
    good = built_message(3.0, np.array([1.0, 2.0, 0.5]), ("world", "robot_0/base_link"),
                         np.eye(6), np.eye(6))
    assert codec.decode(serialize_message(good)) is not None
    other_frame = built_message(3.0, np.zeros(3), ("wOrld", "robot_0/base_link"),
                                np.eye(6), np.eye(6))
    other_child = built_message(3.0, np.zeros(3), ("world", "robot_1/base_link"),
                                np.eye(6), np.eye(6))
    longer_frame = built_message(3.0, np.zeros(3), ("world2", "robot_0/base_link"),
                                 np.eye(6), np.eye(6))
    for message in (other_frame, other_child, longer_frame):
        assert codec.decode(serialize_message(message)) is None
    for field, value in (("x", math.nan), ("y", math.inf), ("x", 1e300)):
        bad = built_message(3.0, np.zeros(3), ("world", "robot_0/base_link"), np.eye(6),
                            np.eye(6))
        setattr(bad.pose.pose.position, field, value)
        assert codec.decode(serialize_message(bad)) is None
    covariance = np.eye(6)
    covariance[2, 3] = math.nan
    assert codec.decode(serialize_message(built_message(
        3.0, np.zeros(3), ("world", "robot_0/base_link"), np.eye(6), covariance))) is None
    negative = built_message(3.0, np.zeros(3), ("world", "robot_0/base_link"), np.eye(6),
                             np.eye(6))
    negative.header.stamp.sec = -1
    assert codec.decode(serialize_message(negative)) is None
    data = serialize_message(good)
    assert codec.decode(data[:-1]) is None
    assert codec.decode(data + b"\x00") is None
    assert codec.decode(b"\x01\x01" + data[2:]) is None  # big-endian CDR
