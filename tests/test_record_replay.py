"""Process-level tests of em-record, em-replay and em-bag repair over real DDS.

em-record writes bag directories (metadata.yaml + one .mcap); ``rosbags``, a reader of
rosbag2 bag directories independent of this project and of rosbag2, reads them too.

A publisher process sends a known sequence on several topics (one of the project's own
types, one transient-local topic published before the recorder exists, and /clock, which
the recorder follows as sim time); em-record runs as a separate process; the files are read
back with readers other than the writer. Replays go into a subscriber process that reports
what it received. Every process is bounded in time and stopped (whole process group) when
its test ends (tests/ros_process.py).

Run as a script, this file is the helper node: ``publish`` or ``subscribe``.
"""
from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest
import rclpy
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from msg_samples import make_sample
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader
from ros_process import REPO_ROOT, NodeProcess, wait_until
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from em_exploration_ros.bag_format.bag_directory import (METADATA_FILE, mcap_file,
                                                        read_metadata_yaml)
from em_exploration_ros.bag_format.bag_reader import BagScanner, scan_bag
from em_exploration_ros.bag_format.bag_writer import BagWriter
from em_exploration_ros.bag_format.interface_index import read_type_hash
from em_exploration_ros.bag_format.mcap_ros2_schema import (
    MessageDefinition, build_message_definition)
from em_exploration_ros.tools import record, replay
from em_exploration_ros.tools.bag_ros import import_message_class

STREAM_COUNT = 150
LATCHED_COUNT = 3
CLOCK_START_NS = 100 * 10**9
CLOCK_STEP_NS = 10**7
TOPIC_TYPES = {
    "/clock": "rosgraph_msgs/msg/Clock",
    "/em_test/chatter": "std_msgs/msg/String",
    "/em_test/odom": "nav_msgs/msg/Odometry",
    "/em_test/team": "em_exploration_msgs/msg/TeamUpdate",
    "/em_test/latched": "std_msgs/msg/String",
    "/em_test/ignored": "std_msgs/msg/String",
}
LATCHED = "/em_test/latched"
IGNORED = "/em_test/ignored"
RECORDED = [t for t in TOPIC_TYPES if t != IGNORED]
RECORD_FILTER = ["--regex", r"^/(clock|em_test/.*)$", "--exclude", "ignored"]
# Script mode needs the package importable without an installed project.
HELPER_ENV = {"PYTHONPATH": str(REPO_ROOT)}


# ----- the known sequence -----------------------------------------------------------------
def make_message(topic: str, k: int) -> object:
    """The k-th message the publisher sends on ``topic`` (equal in every process)."""
    cls = import_message_class(TOPIC_TYPES[topic])
    if topic == "/em_test/team":
        message = make_sample(cls)
        message.sequence = k
        return message
    message = cls()
    if topic == "/clock":
        stamp = CLOCK_START_NS + k * CLOCK_STEP_NS
        message.clock.sec, message.clock.nanosec = divmod(stamp, 10**9)
    elif topic == "/em_test/odom":
        message.header.frame_id = "map"
        message.child_frame_id = f"robot_{k % 3}/base_link"
        message.pose.pose.position.x = 0.5 * k
        message.twist.covariance[35] = float(k)
    else:
        message.data = f"{topic} #{k}"
    return message


def expected_count(topic: str) -> int:
    return LATCHED_COUNT if topic == LATCHED else STREAM_COUNT


# ----- helper nodes (run as a script) -----------------------------------------------------
def _qos(reliable: bool = True, latched: bool = False, depth: int = 1000) -> QoSProfile:
    return QoSProfile(
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _holds(condition: Callable[[], bool], timeout_s: float) -> bool:
    try:
        wait_until(condition, timeout_s, "condition", poll_s=0.02)
    except TimeoutError:
        return False
    return True


def run_publisher(args: argparse.Namespace) -> None:
    """Latched messages first; once ``--go`` exists, the streams; then wait for acks."""
    rclpy.init()
    node = rclpy.create_node("em_test_publisher")
    publishers = {t: node.create_publisher(import_message_class(TOPIC_TYPES[t]), t,
                                           _qos(latched=t == LATCHED))
                  for t in TOPIC_TYPES}
    for k in range(LATCHED_COUNT):
        publishers[LATCHED].publish(make_message(LATCHED, k))
    print("ready", flush=True)
    go = Path(args.go)
    _holds(go.exists, 60.0)
    minimum = {t: 1 for t in TOPIC_TYPES}
    minimum["/clock"] = 2  # the recorder's time source and its recording subscription
    if not _holds(lambda: all(publishers[t].get_subscription_count() >= minimum[t]
                              for t in RECORDED), 15.0):
        print("subscribers missing", flush=True)
    time.sleep(0.3)
    streams = [t for t in TOPIC_TYPES if t != LATCHED]
    for k in range(STREAM_COUNT):
        for topic in streams:
            publishers[topic].publish(make_message(topic, k))
        time.sleep(0.002)
    for publisher in publishers.values():
        publisher.wait_for_all_acked(Duration(seconds=5.0))
    print("done", flush=True)
    _holds(lambda: not rclpy.ok(), 60.0)  # keep the latched history until stopped
    node.destroy_node()
    rclpy.try_shutdown()


def run_subscriber(args: argparse.Namespace) -> None:
    """Subscribe raw; exit once every expected count is reached (or at the timeout)."""
    rclpy.init()
    node = rclpy.create_node("em_test_subscriber")
    received: dict[str, list[str]] = {}
    expected = dict(item.split("=") for item in args.expect)
    for spec in args.topic:
        topic, type_name, qos = spec.split(",")
        received[topic] = []
        node.create_subscription(
            import_message_class(type_name), topic,
            lambda data, topic=topic: received[topic].append(data.hex()),
            _qos(reliable="reliable" in qos, latched="latched" in qos, depth=10000), raw=True)
    print("ready", flush=True)
    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline and not all(
            len(received[t]) >= int(n) for t, n in expected.items()):
        rclpy.spin_once(node, timeout_sec=0.05)
    end = time.monotonic() + args.settle
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    Path(args.out).write_text(json.dumps(received))
    node.destroy_node()
    rclpy.try_shutdown()


def helper_main() -> None:
    """Command line of the helper nodes."""
    parser = argparse.ArgumentParser()
    modes = parser.add_subparsers(dest="mode", required=True)
    publish = modes.add_parser("publish")
    publish.add_argument("--go", required=True, help="start streaming once this file exists")
    subscribe = modes.add_parser("subscribe")
    subscribe.add_argument("--out", required=True)
    subscribe.add_argument("--topic", action="append", default=[], help="topic,type,qos")
    subscribe.add_argument("--expect", action="append", default=[], help="topic=count")
    subscribe.add_argument("--timeout", type=float, default=30.0)
    subscribe.add_argument("--settle", type=float, default=0.3)
    args = parser.parse_args()
    if args.mode == "publish":
        run_publisher(args)
    else:
        run_subscriber(args)


# ----- process handling -------------------------------------------------------------------
def helper(mode: str, args: list[str], log: Path) -> NodeProcess:
    return NodeProcess([sys.executable, str(Path(__file__)), mode, *args], log, HELPER_ENV)


def tool(name: str, args: list[str], log: Path) -> NodeProcess:
    return NodeProcess.start_module(f"em_exploration_ros.tools.{name}", args, log, HELPER_ENV)


def wait_until_flushed(bag: Path, timeout_s: float = 20.0) -> None:
    """Wait until the file's complete chunks hold the whole sequence (--chunk-interval)."""
    expected = {t: expected_count(t) for t in RECORDED}
    wait_until(lambda: scan_bag(bag, tolerant=True).topic_counts() == expected, timeout_s,
               f"{bag.name} to hold {expected}")


def record_session(tmp: Path, name: str, finish: Callable[[NodeProcess], None]) -> Path:
    """Publisher + recorder (sim time); ``finish`` ends the recorder after the streams."""
    bag, go = tmp / name, tmp / f"{name}.go"
    with helper("publish", ["--go", str(go)], tmp / f"{name}_publish.log") as publisher:
        publisher.wait_for_output("ready", 20.0)
        with tool("record", ["-o", str(bag), *RECORD_FILTER, "--poll-interval", "0.2",
                             "--chunk-interval", "0.2", "--chunk-size", "4096",
                             "--ros-args", "-p", "use_sim_time:=true"],
                  tmp / f"{name}_record.log") as recorder:
            for topic in RECORDED:
                recorder.wait_for_output(f"recording {topic} [", 20.0)
            go.touch()
            publisher.wait_for_output("done", 30.0)
            assert "subscribers missing" not in publisher.output()
            wait_until_flushed(bag)
            finish(recorder)
    return bag


def _file_order(bag: Path) -> list:
    """(channel, message) pairs in file order, read by the validating scanner."""
    return list(BagScanner(bag).messages())


def _read_all(bag: Path) -> dict[str, list]:
    by_topic: dict[str, list] = {}
    for channel, message in _file_order(bag):
        by_topic.setdefault(channel.topic, []).append(message)
    return by_topic


def _assert_holds_the_sequence(bag: Path) -> None:
    by_topic = _read_all(bag)
    assert set(by_topic) == set(RECORDED)
    for topic in RECORDED:
        cls = import_message_class(TOPIC_TYPES[topic])
        stored = [deserialize_message(m.data, cls) for m in by_topic[topic]]
        assert stored == [make_message(topic, k) for k in range(expected_count(topic))], topic


# ----- recording ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording closed by SIGINT after the whole sequence was published."""
    def interrupt(recorder: NodeProcess) -> None:
        assert recorder.stop() == 0, recorder.output()
        assert "wrote " in recorder.output()

    return record_session(tmp_path_factory.mktemp("record"), "run", interrupt)


def test_recording_holds_exactly_what_was_published(recording: Path) -> None:
    with mcap_file(recording).open("rb") as stream:
        records = list(StreamReader(stream, validate_crcs=True).records)
    assert type(records[0]).__name__ == "Header" and records[0].profile == "ros2"
    info = scan_bag(recording)
    assert info.complete and info.crc_checked_chunks == info.chunk_count > 3
    assert info.topic_counts() == {t: expected_count(t) for t in RECORDED}
    _assert_holds_the_sequence(recording)
    by_topic = _read_all(recording)
    assert all([m.sequence for m in by_topic[t]] == list(range(1, expected_count(t) + 1))
               for t in RECORDED)

    # Log time is the recorder's ROS clock, which follows /clock (sim time), in file order.
    log_times = [m.log_time_ns for _c, m in _file_order(recording)]
    assert log_times == sorted(log_times)
    last_clock = CLOCK_START_NS + (STREAM_COUNT - 1) * CLOCK_STEP_NS
    assert CLOCK_START_NS <= log_times[-1] <= last_clock

    channels = {c.topic: c for c in info.channels.values()}
    for topic in RECORDED:
        assert channels[topic].type_hash == read_type_hash(TOPIC_TYPES[topic])
        assert channels[topic].type_hash.startswith("RIHS01_")
        assert info.schema_of(channels[topic]).name == TOPIC_TYPES[topic]
        [offer] = channels[topic].offered_qos
        assert offer.reliability == "reliable"
        assert offer.durability == ("transient_local" if topic == LATCHED else "volatile")

    metadata = info.rosbag2_metadata()
    assert metadata.message_count == info.message_count
    assert {t.name: t.message_count for t in metadata.topics} == info.topic_counts()
    assert metadata.ros_distro == "jazzy" and metadata.storage_identifier == "mcap"

    # The bag directory's metadata.yaml holds the same bag metadata as the MCAP file.
    assert read_metadata_yaml(recording) == metadata

    # rosbags reads the bag directory and counts every message.
    with RosbagsReader(recording) as reader:
        assert reader.message_count == info.message_count
        counted: dict[str, int] = {}
        for connection, _stamp, _data in reader.messages():
            counted[connection.topic] = counted.get(connection.topic, 0) + 1
    assert counted == info.topic_counts()

    # The schema text alone decodes every message, the project's own type included.
    with mcap_file(recording).open("rb") as stream:
        decoded = list(make_reader(stream, decoder_factories=[DecoderFactory()])
                       .iter_decoded_messages())
    assert len(decoded) == info.message_count
    team = [d for _s, c, _m, d in decoded if c.topic == "/em_test/team"]
    assert [d.sequence for d in team] == list(range(STREAM_COUNT))
    assert len(team[0].keyframes) == len(make_message("/em_test/team", 0).keyframes) > 0


def test_sigterm_closes_the_recording(tmp_path: Path) -> None:
    bag = tmp_path / "term"
    with tool("record", ["-o", str(bag), "--topics", "/em_test/nobody"],
              tmp_path / "term.log") as recorder:
        recorder.wait_for_output("recording to ", 20.0)
        recorder.signal_group(signal.SIGTERM)
        assert recorder.wait(15.0) == 0, recorder.output()
        assert "wrote 0 messages on 0 topics" in recorder.output()
    info = scan_bag(bag)
    assert info.complete and info.message_count == 0
    assert info.rosbag2_metadata().message_count == 0
    assert read_metadata_yaml(bag).message_count == 0


def test_killed_recording_is_repaired(tmp_path: Path) -> None:
    def kill(recorder: NodeProcess) -> None:
        recorder.signal_group(signal.SIGKILL)
        recorder.wait(10.0)

    bag = record_session(tmp_path, "killed", kill)
    assert not (bag / METADATA_FILE).exists()  # written only when a recording is closed
    info = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.bag", "info",
                           str(bag)], cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
    assert info.returncode == 2 and "truncated" in info.stderr
    assert "Traceback" not in info.stderr

    fixed = tmp_path / "fixed"
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.bag", "repair", str(bag), str(fixed)],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    repaired = scan_bag(fixed)
    assert repaired.complete and read_metadata_yaml(fixed).message_count == repaired.message_count
    assert repaired.topic_counts() == {t: expected_count(t) for t in RECORDED}
    _assert_holds_the_sequence(fixed)
    latched = next(c for c in repaired.channels.values() if c.topic == LATCHED)
    assert latched.offered_qos[0].durability == "transient_local"


# ----- replay ---------------------------------------------------------------------------------
def replay_into_subscriber(tmp: Path, bag: Path, topics: list[str], expect: dict[str, int],
                           replay_args: list[str], timeout_s: float = 40.0) -> tuple[dict, str]:
    """Start a subscriber, replay ``bag``; returns (received hex per topic, replay log)."""
    out = tmp / "received.json"
    sub_args = ["--out", str(out), "--timeout", str(timeout_s)]
    sub_args += [f"--topic={t}" for t in topics] + [f"--expect={t}={n}" for t, n in expect.items()]
    with helper("subscribe", sub_args, tmp / "subscriber.log") as subscriber:
        subscriber.wait_for_output("ready", 20.0)
        with tool("replay", [str(bag), "--delay", "0", "--wait-for-subscribers", "30",
                             *replay_args], tmp / "replay.log") as player:
            assert player.wait(timeout_s) == 0, player.output()
            log = player.output()
        assert subscriber.wait(timeout_s) == 0, subscriber.output()
    return json.loads(out.read_text()), log


def test_replay_reproduces_the_recording(recording: Path, tmp_path: Path) -> None:
    recorded = _read_all(recording)
    topics = [f"{t},{TOPIC_TYPES[t]},reliable{'+latched' if t == LATCHED else ''}"
              for t in RECORDED]
    received, log = replay_into_subscriber(
        tmp_path, recording, topics, {t: expected_count(t) for t in RECORDED},
        ["--rate", "0", "--topics", *RECORDED])
    for topic in RECORDED:
        # Same messages, same order, same bytes; /clock comes from the recording only.
        assert received[topic] == [m.data.hex() for m in recorded[topic]], topic
    assert f"played {sum(expected_count(t) for t in RECORDED)} messages" in log


def _synthetic_bag(path: Path, count: int, period_ns: int, start_ns: int) -> None:
    definition = build_message_definition("std_msgs/msg/String")
    with BagWriter(path) as writer:
        kept = writer.add_topic("/a", definition)
        skipped = writer.add_topic("/skip", definition)
        for k in range(count):
            writer.write(kept, start_ns + k * period_ns, serialize_message(String(data=f"a{k}")))
            writer.write(skipped, start_ns + k * period_ns, serialize_message(String(data="s")))


def _played_wall_s(log: str) -> float:
    return float(re.search(r"played \d+ messages in ([0-9.]+) s", log).group(1))


def test_replay_timing_clock_remap_and_filters(tmp_path: Path) -> None:
    bag = tmp_path / "timed.mcap"
    _synthetic_bag(bag, count=16, period_ns=10**8, start_ns=10 * 10**9)  # 10.0 s .. 11.5 s
    received, log = replay_into_subscriber(
        tmp_path, bag, ["/b,std_msgs/msg/String,reliable",
                        "/clock,rosgraph_msgs/msg/Clock,best_effort",
                        "/skip,std_msgs/msg/String,reliable"],
        {"/b": 11}, ["--rate", "2", "--start-offset", "0.5", "--remap", "/a:=/b",
                     "--exclude", "^/skip$"])
    assert [deserialize_message(bytes.fromhex(h), String).data for h in received["/b"]] == [
        f"a{k}" for k in range(5, 16)]
    assert received["/skip"] == []
    clock = [deserialize_message(bytes.fromhex(h), Clock).clock for h in received["/clock"]]
    stamps = [c.sec * 10**9 + c.nanosec for c in clock]
    assert len(stamps) > 5 and stamps == sorted(stamps)
    assert 10_500_000_000 <= stamps[0] and stamps[-1] <= 11_500_000_000
    # 1.0 s of recording at rate 2: the schedule cannot finish in less than 0.5 s.
    assert _played_wall_s(log) >= 0.5 - 1e-3


def test_replay_rate_zero_is_much_faster_than_real_time(tmp_path: Path) -> None:
    bag = tmp_path / "long.mcap"
    _synthetic_bag(bag, count=101, period_ns=10 * 10**9, start_ns=0)  # 1000 s of recording
    started = time.monotonic()
    with tool("replay", [str(bag), "--rate", "0", "--delay", "0"], tmp_path / "fast.log") as fast:
        assert fast.wait(60.0) == 0, fast.output()
        log = fast.output()
    assert time.monotonic() - started < 60
    assert "played 202 messages" in log
    assert _played_wall_s(log) < 10.0


def test_looping_replay_stops_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    bag = tmp_path / "loop.mcap"
    _synthetic_bag(bag, count=200, period_ns=10**6, start_ns=0)
    with tool("replay", [str(bag), "--loop", "--rate", "0", "--delay", "0"],
              tmp_path / "loop.log") as player:
        wait_until(lambda: player.output().count("played 400 messages") >= 2, 20.0,
                   "two passes of the loop")
        assert player.stop() == 0, player.output()
        assert "Traceback" not in player.output()


# ----- bad input --------------------------------------------------------------------------------
def _exit_code(main: Callable[[list[str]], None], argv: list[str]) -> int:
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    return stopped.value.code


def test_bad_files_give_one_line_errors(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / "good.mcap"
    _synthetic_bag(good, count=50, period_ns=10**6, start_ns=0)
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[:-100])
    text = tmp_path / "text.mcap"
    text.write_text("not a recording")
    unknown = tmp_path / "unknown.mcap"
    with BagWriter(unknown) as writer:
        channel = writer.add_topic("/x", MessageDefinition("ghost_msgs/msg/Ghost", "ros2msg",
                                                           "int32 boo\n"))
        writer.write(channel, 1, b"\x00\x01\x00\x00\x07\x00\x00\x00")
    # A recording of an installed type made with another definition of it (an older
    # TeamUpdate): playing it would publish misread messages.
    older = tmp_path / "older.mcap"
    with BagWriter(older) as writer:
        channel = writer.add_topic("/robot_0/team/updates", MessageDefinition(
            "em_exploration_msgs/msg/TeamUpdate", "ros2msg", "uint32 robot_id\nuint64 sequence\n"))
        writer.write(channel, 1, bytes(16))
    # Comments aside, a definition as installed plays (as recorded by another rosbag2).
    commented = tmp_path / "commented.mcap"
    installed = build_message_definition("em_exploration_msgs/msg/TeamUpdate")
    with BagWriter(commented) as writer:
        writer.add_topic("/robot_0/team/updates", MessageDefinition(
            installed.type_name, installed.encoding,
            "# another comment\n" + installed.text.replace("# ", "#  ")))
    assert replay.recorded_as_installed(next(iter(scan_bag(commented).schemas.values())))
    cases = {truncated: "truncated", text: "not an MCAP file",
             tmp_path / "missing.mcap": "no such file",
             unknown: "ghost_msgs/msg/Ghost, which is not installed",
             older: "recorded with another definition of em_exploration_msgs/msg/TeamUpdate"}
    for path, phrase in cases.items():
        assert _exit_code(replay.main, ["em-replay", str(path)]) == 2
        stderr = capsys.readouterr().err
        assert phrase in stderr and len(stderr.strip().splitlines()) == 1, stderr
    # End to end: the error is all the user sees.
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.replay",
                             str(truncated)], cwd=REPO_ROOT, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_record_and_replay_reject_bad_arguments(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    existing = tmp_path / "exists.mcap"
    existing.write_bytes(b"keep")
    cases = [(["--compression", "bzip9"], "invalid choice"),
             (["--regex", "("], "invalid regular expression"),
             (["--chunk-size", "-5"], "must be positive"),
             (["--topics", "no_slash"], "not an absolute topic name"),
             (["-o", str(existing)], "File exists")]
    for args, phrase in cases:
        assert _exit_code(record.main, ["em-record", *args]) == 2, args
        assert phrase in capsys.readouterr().err, args
    assert existing.read_bytes() == b"keep"
    assert _exit_code(replay.main, ["em-replay", str(existing), "--remap", "a-b"]) == 2
    assert "expected /OLD:=/NEW" in capsys.readouterr().err
    assert _exit_code(replay.main, ["em-replay", str(existing), "--rate", "-1"]) == 2
    assert "must be non-negative" in capsys.readouterr().err


if __name__ == "__main__":
    helper_main()
