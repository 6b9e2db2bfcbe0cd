"""em-record and the bag writer when the OS refuses a write (a full disk).

The bag writer is tested with a file that refuses writes as a full disk does (ENOSPC) until
the bag directory's reserve file is freed; em-record as a process that records onto a small
tmpfs until it is full (root only: mounting one needs it): one line, exit code 3, no
traceback, and a bag that every reader opens whole (summary, footer, metadata.yaml)
describing what reached the file.
"""
from __future__ import annotations

import errno
import io
import os
import sys
from pathlib import Path

import pytest
from ros_process import REPO_ROOT, NodeProcess
from rosbags.rosbag2 import Reader as RosbagsReader
from small_disk import small_disk

from em_exploration_ros.bag_format.bag_directory import (METADATA_FILE, RESERVE_FILE,
                                                         BagDirectoryWriter,
                                                         read_metadata_yaml)
from em_exploration_ros.bag_format.bag_reader import scan_bag
from em_exploration_ros.bag_format.bag_writer import BagWriteError
from em_exploration_ros.bag_format.mcap_ros2_schema import MessageDefinition
from em_exploration_ros.tools.bag_ros import other_types_of_taken_topics
from em_exploration_ros.tools.record import EXIT_WRITE_FAILED

DISK_BYTES = 64 * 1024
MESSAGE = b"\x00\x01\x00\x00" + bytes(20_000)
DEFINITION = MessageDefinition("std_msgs/msg/UInt8MultiArray", "ros2msg", "uint8[] data\n")
PUBLISHER = """
import time, rclpy
from std_msgs.msg import UInt8MultiArray
rclpy.init()
node = rclpy.create_node("em_test_big_publisher")
publisher = node.create_publisher(UInt8MultiArray, "/em_test/big", 10)
message = UInt8MultiArray(data=bytes(20000))
end = time.monotonic() + 60.0
while time.monotonic() < end and rclpy.ok():
    publisher.publish(message)
    time.sleep(0.02)
"""


def full_disk_file(reserve: Path):
    """A file maker for BagWriter: files on a disk with DISK_BYTES free, which refuse writes
    past them with ENOSPC while the bag directory's ``reserve`` file holds its space."""

    class FullDisk(io.FileIO):
        def write(self, data: bytes) -> int:
            if reserve.exists() and self.tell() + len(data) > DISK_BYTES:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return super().write(data)

    return lambda path: FullDisk(path, "xb")


def read_by_rosbags(bag: Path) -> dict[str, int]:
    """Messages per topic of a bag directory as rosbags reads them, every one of them."""
    counts: dict[str, int] = {}
    with RosbagsReader(bag) as reader:
        for connection, _, _ in reader.messages():
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    return counts


def test_a_full_disk_ends_the_bag_whole_with_what_reached_it(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    writer = BagDirectoryWriter(bag, compression="none", chunk_size=10**6,
                                create=full_disk_file(bag / RESERVE_FILE))
    channel = writer.add_topic("/big", DEFINITION)
    stamp = 0
    with pytest.raises(BagWriteError, match="bag_0.mcap: No space left on device") as refused:
        for stamp in range(1, 100):
            writer.write(channel, stamp, MESSAGE)
            if stamp % 2 == 0:
                writer.flush()
    assert writer.failure is refused.value
    with pytest.raises(BagWriteError):  # the recording has ended
        writer.flush()
    writer.close()  # no second error: the reserve's space ends the file and metadata.yaml
    assert not (bag / RESERVE_FILE).exists()
    info = scan_bag(writer.path)  # not tolerant: the file is whole (summary and footer)
    assert info.complete and info.topic_counts() == {"/big": 2} and stamp > 2
    assert info.rosbag2_metadata().message_count == 2
    assert writer.message_count == 2
    metadata = read_metadata_yaml(writer.directory)
    assert metadata.message_count == 2 and metadata.duration_ns == 1
    assert read_by_rosbags(bag) == {"/big": 2}


def test_a_bag_directory_that_cannot_keep_its_reserve_is_not_left_behind(
        tmp_path: Path) -> None:
    with pytest.raises(OSError):
        BagDirectoryWriter(tmp_path / "bag", reserve_bytes=-1)
    assert not (tmp_path / "bag").exists()


def test_record_on_a_full_disk_ends_the_bag_whole_with_one_line_and_exit_code_3(
        tmp_path: Path) -> None:
    with small_disk(tmp_path / "disk", 12 * 1024) as disk:  # the 8 MiB reserve and 4 MiB
        _record_until_the_disk_is_full(tmp_path, disk / "rec")


def _record_until_the_disk_is_full(tmp_path: Path, bag: Path) -> None:
    publisher = NodeProcess([sys.executable, "-c", PUBLISHER], tmp_path / "publisher.log")
    recorder = NodeProcess([sys.executable, "-m", "em_exploration_ros.tools.record", "-o",
                            str(bag), "--topics", "/em_test/big", "--compression", "none",
                            "--chunk-interval", "0.1", "--poll-interval", "0.1"],
                           tmp_path / "record.log", {"PYTHONPATH": str(REPO_ROOT)})
    with publisher, recorder:
        assert recorder.wait(60.0) == EXIT_WRITE_FAILED, recorder.output()
    output = recorder.output()
    assert "Traceback" not in output, output
    errors = [line for line in output.splitlines() if line.startswith("em-record:")]
    assert len(errors) == 1, output
    assert f"cannot write to {bag}/rec_0.mcap: No space left on device; stopped recording " \
        "after" in errors[0]
    info = scan_bag(bag)  # the file is whole
    stored = sum(info.topic_counts().values())
    assert info.complete and stored > 100, output
    assert "the bag is closed whole with them" in errors[0]
    assert (bag / METADATA_FILE).is_file() and not (bag / RESERVE_FILE).exists()
    assert read_metadata_yaml(bag).message_count == stored
    assert sum(read_by_rosbags(bag).values()) == stored


def test_a_taken_topic_that_carries_another_type_is_reported_once() -> None:
    """em-record and em-foxglove keep a topic's first type; a publisher of another type on
    it (beside the first, or after it left) is named once, not left out without a word."""
    taken = {"/robot_0/target": "std_msgs/msg/String", "/clock": "rosgraph_msgs/msg/Clock"}
    graph = [("/robot_0/target", ["std_msgs/msg/String", "nav_msgs/msg/OccupancyGrid"]),
             ("/clock", ["rosgraph_msgs/msg/Clock"]),
             ("/not_taken", ["std_msgs/msg/String", "std_msgs/msg/Empty"])]
    reported: set[tuple[str, str]] = set()
    assert other_types_of_taken_topics(graph, taken, reported) == [
        "/robot_0/target now carries nav_msgs/msg/OccupancyGrid too; only std_msgs/msg/String "
        "is taken (messages of nav_msgs/msg/OccupancyGrid are left out)"]
    assert other_types_of_taken_topics(graph, taken, reported) == []
    graph = [("/robot_0/target", ["std_msgs/msg/Empty"])]  # the first type gone
    assert len(other_types_of_taken_topics(graph, taken, reported)) == 1
