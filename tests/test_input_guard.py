"""The message checks every node applies before it touches state (nodes/input_guard.py)."""
from __future__ import annotations

import math
import types

import numpy as np
import rclpy.logging
from nav_msgs.msg import Odometry, Path
from rclpy.serialization import serialize_message

from em_exploration_ros.nodes.conversions import path_to_msg
from em_exploration_ros.nodes.input_guard import (InputGuard, content_problem,
                                                  serialized_size, size_limited)


def long_path(poses: int) -> Path:
    stamps = np.arange(poses) * 2.0
    return path_to_msg(2.0 * poses, stamps, np.zeros((poses, 3)))


def guard() -> InputGuard:
    return InputGuard(types.SimpleNamespace(get_logger=lambda: rclpy.logging.get_logger("t")))


def test_content_problem_finds_a_bad_value_deep_in_thousands_of_nested_messages():
    path = long_path(3000)
    assert content_problem(path) is None
    path.poses[2999].pose.orientation.w = math.nan
    assert "not finite" in content_problem(path)
    path.poses[2999].pose.orientation.w = 1.0
    path.poses[1500].header.stamp.sec = -5
    assert content_problem(path) == "stamp is negative (-5 s)"
    path.poses[1500].header.stamp.sec = 5
    path.poses[7].pose.position.y = -2e9
    assert "implausibly large" in content_problem(path)


def test_content_problem_checks_fixed_float_arrays():
    odometry = Odometry()
    assert content_problem(odometry) is None
    odometry.twist.covariance[35] = math.inf
    assert "not finite" in content_problem(odometry)


def test_size_limited_drops_a_longer_message_before_deserializing_it():
    received: list[Path] = []
    inputs = guard()
    limit = serialized_size(long_path(10))
    on_bytes = size_limited(inputs, "/robot_0/estimated_path", Path, limit, received.append)
    on_bytes(serialize_message(long_path(11)))
    assert received == [] and inputs.dropped == 1
    on_bytes(serialize_message(long_path(10)))
    assert inputs.dropped == 1 and len(received) == 1 and len(received[0].poses) == 10
    assert received[0].poses[9].header.stamp.sec == 18


def test_size_limited_drops_bytes_that_are_not_the_type():
    received: list[Path] = []
    inputs = guard()
    on_bytes = size_limited(inputs, "/robot_0/landmarks", Path, 10_000, received.append)
    on_bytes(b"\x00\x01\x00\x00" + b"\xff" * 40)  # a count of 2^32 - 1 poses
    on_bytes(b"\x00\x01")
    assert received == [] and inputs.dropped == 2
