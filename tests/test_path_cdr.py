"""The NumPy codec of nav_msgs/Path against rclpy's own serialization, and attacked."""
import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message, serialize_message

from em_exploration_ros.nodes.conversions import (path_from_msg, path_to_msg, planar_path,
                                                  serialized_path)
from em_exploration_ros.nodes.input_guard import path_problem
from em_exploration_ros.nodes.path_cdr import PathDecodeError, decode_path, encode_path


def robot_path(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [s], poses (K, 3)) as a robot's keyframes give them."""
    rng = np.random.default_rng(seed)
    poses = np.column_stack([rng.uniform(-60, 60, (count, 2)), rng.uniform(-3.2, 3.2, count)])
    return 2.0 * np.arange(count) + 0.2, poses


def framed_path(frame_id: str, count: int) -> Path:
    message = Path()
    message.header.frame_id = frame_id
    message.header.stamp.sec, message.header.stamp.nanosec = 7, 5
    for index in range(count):
        pose = PoseStamped()
        pose.header.frame_id = frame_id
        pose.header.stamp.sec, pose.header.stamp.nanosec = index, 10 * index
        pose.pose.position.x, pose.pose.position.z = 1.5 + index, -2.0
        pose.pose.orientation.w = 1.0
        message.poses.append(pose)
    return message


@pytest.mark.parametrize("count", [0, 1, 2, 3, 165])
def test_serialized_path_is_the_message_rclpy_builds(count):
    stamps, poses = robot_path(count)
    built = path_to_msg(33.2, stamps, poses)
    data = serialized_path(33.2, stamps, poses)
    assert len(data) == len(serialize_message(built))
    assert deserialize_message(data, Path) == built


@pytest.mark.parametrize("count", [0, 1, 165])
def test_read_path_equals_rclpys_bit_for_bit(count):
    stamps, poses = robot_path(count, seed=3)
    message = path_to_msg(9.0, stamps, poses)
    expected_stamps, expected_poses = path_from_msg(message)
    decoded = decode_path(serialize_message(message))
    got_stamps, got_poses = planar_path(decoded)
    assert decoded.frame_id == "map" and decoded.stamp == (9, 0)
    assert np.array_equal(got_stamps, expected_stamps)
    assert np.array_equal(got_poses, expected_poses)


@pytest.mark.parametrize("frame_id", ["", "a", "ab", "abc", "abcde", "robot_0/odom_frame"])
def test_every_frame_length_reads_and_writes(frame_id):
    message = framed_path(frame_id, 4)
    decoded = decode_path(serialize_message(message))
    assert decoded.frame_id == frame_id and decoded.stamp == (7, 5)
    assert decoded.pose_stamps.tolist() == [[i, 10 * i] for i in range(4)]
    assert decoded.poses[:, 0].tolist() == [1.5, 2.5, 3.5, 4.5]
    assert np.all(decoded.poses[:, 2] == -2.0) and np.all(decoded.poses[:, 6] == 1.0)
    again = encode_path(decoded.stamp, frame_id, decoded.pose_stamps, decoded.poses)
    assert deserialize_message(again, Path) == message


def test_a_pose_in_another_frame_is_not_read():
    message = framed_path("map", 3)
    message.poses[1].header.frame_id = "mop"
    assert decode_path(serialize_message(message)) is None


def test_truncated_and_garbled_bytes_raise_only_decode_errors():
    data = serialize_message(framed_path("map", 20))
    for cut in (0, 3, 10, 20, 23, 24, 60, len(data) - 1):
        with pytest.raises(PathDecodeError):
            decode_path(data[:cut])
    with pytest.raises(PathDecodeError, match="little-endian"):
        decode_path(b"\x00\x00" + data[2:])  # big-endian CDR
    huge_count = bytearray(data)
    huge_count[20:24] = (2 ** 32 - 1).to_bytes(4, "little")
    with pytest.raises(PathDecodeError, match="do not fit"):
        decode_path(bytes(huge_count))
    rng = np.random.default_rng(0)
    for _ in range(2000):
        garbled = np.frombuffer(data, dtype=np.uint8).copy()
        index = rng.integers(0, len(garbled), rng.integers(1, 6))
        garbled[index] = rng.integers(0, 256, len(index))
        try:
            decoded = decode_path(garbled[:rng.integers(20, len(garbled) + 1)].tobytes())
        except PathDecodeError:
            continue
        assert decoded is None or len(decoded.poses) == len(decoded.pose_stamps) <= 20


def test_path_problem_names_what_is_wrong():
    message = framed_path("map", 3)
    assert path_problem(decode_path(serialize_message(message)), "map") is None
    assert "frame" in path_problem(decode_path(serialize_message(framed_path("odom", 2))),
                                   "map")
    message.poses[2].header.stamp.sec = -4
    assert path_problem(decode_path(serialize_message(message)), "map") == \
        "stamp is negative (-4 s)"
    message.poses[2].header.stamp.sec = 4
    message.poses[1].pose.orientation.z = float("nan")
    assert "not finite" in path_problem(decode_path(serialize_message(message)), "map")
    message.poses[1].pose.orientation.z = 0.0
    message.header.stamp.sec = -1
    assert "negative" in path_problem(decode_path(serialize_message(message)), "map")
