"""Throughput of the MCAP bag tools: writer and validating reader, em-record under load, replay.

1. ``BagWriter`` and the validating ``scan_bag`` in-process, per chunk compression, for
   messages of 100 B, 1 KB and 100 KB (random payloads, 16 distinct ones).
2. em-record as a separate process under a synthetic DDS load: this process publishes
   ``std_msgs/UInt8MultiArray`` messages of ``--size`` bytes on ``--topics`` topics at each
   total rate of ``--rates`` for ``--seconds``, waits for acknowledgements and for the
   recorder's periodic flush, then prints messages sent and recorded, MB/s and the
   recorder's CPU time as a share of one core over the publishing window.
3. The cost of publishing the recorded CDR bytes as they are (what em-replay does) against
   deserializing them into the message class and publishing that.

ROS_DOMAIN_ID defaults to 0 (the usual domain); set it to isolate a run.
Usage: ``python benchmarks/bench_bag.py [--rates 1000 4000] [--size 1000] [--seconds 5]``
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from rclpy.duration import Duration
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import UInt8MultiArray

from em_exploration_ros.bag_format.bag_reader import scan_bag
from em_exploration_ros.bag_format.bag_writer import COMPRESSIONS, BagWriter
from em_exploration_ros.bag_format.mcap_ros2_schema import build_message_definition

_TYPE = "std_msgs/msg/UInt8MultiArray"


def bench_writer(directory: Path) -> None:
    """Messages/s and MB/s of BagWriter.write and scan_bag per compression and size."""
    definition = build_message_definition(_TYPE)
    for compression in COMPRESSIONS:
        for size, count in ((100, 100_000), (1000, 50_000), (100_000, 1000)):
            path = directory / f"writer_{compression}_{size}.mcap"
            payloads = [os.urandom(size) for _ in range(16)]
            started = time.perf_counter()
            with BagWriter(path, compression=compression) as writer:
                channel = writer.add_topic("/bench", definition)
                for k in range(count):
                    writer.write(channel, k, payloads[k % 16])
            write_s = time.perf_counter() - started
            started = time.perf_counter()
            scan_bag(path)
            scan_s = time.perf_counter() - started
            print(f"writer {compression:4s} {size:6d} B: write {count / write_s:8.0f} msg/s "
                  f"{count * size / write_s / 1e6:6.1f} MB/s; validating read "
                  f"{count / scan_s:8.0f} msg/s {count * size / scan_s / 1e6:6.1f} MB/s")
            path.unlink()


def _group_cpu_s(group: int) -> float:
    """User + system CPU seconds of the live processes in a process group."""
    total = 0.0
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            if os.getpgid(int(entry)) != group:
                continue
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, ProcessLookupError):
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def bench_recorder(directory: Path, rate: float, size: int, topics: int, seconds: float) -> None:
    """Publish at ``rate`` msg/s in total and compare what em-record wrote."""
    bag = directory / f"load_{int(rate)}_{size}"  # a bag directory
    recorder = subprocess.Popen(
        [sys.executable, "-m", "em_exploration_ros.tools.record", "-o", str(bag),
         "--regex", "^/bench/", "--poll-interval", "0.2", "--chunk-interval", "0.2"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    node = rclpy.create_node("bench_bag_publisher")
    try:
        publishers = [node.create_publisher(UInt8MultiArray, f"/bench/t{i}", QoSProfile(depth=1000))
                      for i in range(topics)]
        deadline = time.monotonic() + 30
        while any(p.get_subscription_count() == 0 for p in publishers):
            if time.monotonic() > deadline:
                raise RuntimeError("em-record did not subscribe within 30 s")
            time.sleep(0.05)
        time.sleep(0.5)
        messages = [UInt8MultiArray(data=os.urandom(size)) for _ in range(16)]
        cpu_before, started = _group_cpu_s(recorder.pid), time.monotonic()
        sent, next_due = 0, started
        while time.monotonic() - started < seconds:
            for publisher in publishers:
                publisher.publish(messages[sent % 16])
                sent += 1
            next_due += topics / rate
            time.sleep(max(0.0, next_due - time.monotonic()))
        for publisher in publishers:
            publisher.wait_for_all_acked(Duration(seconds=10))
        publish_s = time.monotonic() - started
        wait_end = time.monotonic() + 10
        while scan_bag(bag, tolerant=True).message_count < sent and time.monotonic() < wait_end:
            time.sleep(0.2)
        cpu_s, window_s = _group_cpu_s(recorder.pid) - cpu_before, time.monotonic() - started
    finally:
        node.destroy_node()
        os.killpg(recorder.pid, signal.SIGINT)
        recorder.wait(timeout=30)
    recorded = scan_bag(bag).message_count
    print(f"em-record at {sent / publish_s:7.0f} msg/s x {size} B on {topics} topics "
          f"({sent * size / publish_s / 1e6:6.2f} MB/s): sent {sent}, recorded {recorded}, "
          f"recorder CPU {100 * cpu_s / window_s:4.0f}% of one core")
    shutil.rmtree(bag)


def bench_publish(count: int = 20_000) -> None:
    """Microseconds per message: raw CDR publish (em-replay) vs deserialize + publish."""
    node = rclpy.create_node("bench_bag_replay")
    publisher = node.create_publisher(UInt8MultiArray, "/bench_replay", 1000)
    data = serialize_message(UInt8MultiArray(data=os.urandom(1000)))
    started = time.perf_counter()
    for _ in range(count):
        publisher.publish(data)
    raw_s = time.perf_counter() - started
    started = time.perf_counter()
    for _ in range(count):
        publisher.publish(deserialize_message(data, UInt8MultiArray))
    typed_s = time.perf_counter() - started
    node.destroy_node()
    print(f"replay publish of 1 KB: raw bytes {1e6 * raw_s / count:.1f} us/msg, "
          f"deserialize + publish {1e6 * typed_s / count:.1f} us/msg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[1000.0, 4000.0])
    parser.add_argument("--size", type=int, default=1000, help="payload bytes")
    parser.add_argument("--topics", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory(prefix="bench_bag_") as tmp:
        bench_writer(Path(tmp))
        rclpy.init()
        try:
            for rate in args.rates:
                bench_recorder(Path(tmp), rate, args.size, args.topics, args.seconds)
            bench_publish()
        finally:
            rclpy.try_shutdown()


if __name__ == "__main__":
    main()
