"""em-record and the bag writer when the OS refuses a write (a full disk).

The bag writer is tested with a file that refuses writes past a size, as a full disk does
(ENOSPC); em-record as a process whose file size limit (RLIMIT_FSIZE, set by ``prlimit``)
makes the OS refuse its writes (EFBIG): one line, exit code 3, no traceback, and a
metadata.yaml describing what reached the file.
"""
from __future__ import annotations

import errno
import io
import os
import sys
from pathlib import Path

import pytest
from ros_process import REPO_ROOT, NodeProcess

from em_exploration_ros.bag_format import bag_writer
from em_exploration_ros.bag_format.bag_directory import (METADATA_FILE, BagDirectoryWriter,
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
end = time.monotonic() + 30.0
while time.monotonic() < end and rclpy.ok():
    publisher.publish(message)
    time.sleep(0.05)
"""


class _FullDisk(io.FileIO):
    """A file on a disk with DISK_BYTES free: writes past them fail with ENOSPC."""

    def write(self, data: bytes) -> int:
        if self.tell() + len(data) > DISK_BYTES:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data)


def test_a_full_disk_ends_the_bag_and_close_describes_what_reached_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bag_writer.io, "FileIO", _FullDisk)
    writer = BagDirectoryWriter(tmp_path / "bag", compression="none", chunk_size=10**6)
    channel = writer.add_topic("/big", DEFINITION)
    stamp = 0
    with pytest.raises(BagWriteError, match="bag_0.mcap: No space left on device") as refused:
        for stamp in range(1, 100):
            writer.write(channel, stamp, MESSAGE)
            if stamp % 2 == 0:
                writer.flush()
    assert writer.failure is refused.value
    with pytest.raises(BagWriteError):  # the file has ended
        writer.flush()
    writer.close()  # no second error: it only closes the file, then writes metadata.yaml
    stored = scan_bag(writer.path, tolerant=True).topic_counts()
    assert stored == {"/big": 2} and stamp > 2
    assert writer.message_count == 2
    metadata = read_metadata_yaml(writer.directory)
    assert metadata.message_count == 2 and metadata.duration_ns == 1


def test_record_on_a_full_disk_stops_with_one_line_and_exit_code_3(tmp_path: Path) -> None:
    bag = tmp_path / "rec"
    publisher = NodeProcess([sys.executable, "-c", PUBLISHER], tmp_path / "publisher.log")
    recorder = NodeProcess(["prlimit", f"--fsize={DISK_BYTES}", sys.executable, "-m",
                            "em_exploration_ros.tools.record", "-o", str(bag), "--topics",
                            "/em_test/big", "--compression", "none", "--chunk-interval", "0.1",
                            "--poll-interval", "0.1"], tmp_path / "record.log",
                           {"PYTHONPATH": str(REPO_ROOT)})
    with publisher, recorder:
        assert recorder.wait(30.0) == EXIT_WRITE_FAILED, recorder.output()
    output = recorder.output()
    assert "Traceback" not in output, output
    errors = [line for line in output.splitlines() if line.startswith("em-record:")]
    assert len(errors) == 1, output
    assert f"cannot write to {bag}/rec_0.mcap: File too large; stopped recording after" in \
        errors[0]
    stored = sum(scan_bag(bag / "rec_0.mcap", tolerant=True).topic_counts().values())
    assert errors[0].endswith(f"after {stored} messages") and stored > 0
    assert (bag / METADATA_FILE).is_file()
    assert read_metadata_yaml(bag).message_count == stored


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
