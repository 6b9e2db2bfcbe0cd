"""Tests of the ROS-free MCAP bag format: schemas, QoS and metadata YAML, writer, reader, repair.

Every written file is read back by readers other than the writer: the ``mcap`` library's
stream reader with CRC validation, its seeking reader with the ``mcap_ros2`` decoder (which
only works if the schema text holds every dependency), rclpy's deserializer, and the
project's own validating scanner.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from builtin_interfaces.msg import Time
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer, Header, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from mcap_ros2.decoder import DecoderFactory
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from em_exploration_ros.bag_format.bag_directory import (
    METADATA_FILE, BagDirectoryWriter, BagPathError, mcap_file, read_metadata_yaml)
from em_exploration_ros.bag_format.bag_reader import BagError, BagScanner, NotMcapError, scan_bag
from em_exploration_ros.bag_format.bag_writer import BagWriter
from em_exploration_ros.bag_format.interface_index import find_interface_file, read_type_hash
from em_exploration_ros.bag_format.mcap_ros2_schema import (
    DELIMITER_LINE, DefinitionNotFoundError, build_message_definition, parse_msg_dependencies)
from em_exploration_ros.bag_format.qos_yaml import (
    DURATION_INFINITE_NS, QosFormatError, QosProfile, offer_for_playback,
    qos_profiles_from_yaml, qos_profiles_to_yaml, request_for_offers)
from em_exploration_ros.bag_format.rosbag2_metadata import (
    BagMetadata, TopicInformation, parse_bag_metadata, serialize_bag_metadata)
from em_exploration_ros.bag_format.topic_selection import TopicSelection
from em_exploration_ros.tools.bag import format_info, repair
from em_bag_cli import run_em_bag

REPO = Path(__file__).resolve().parents[1]
MSG_DIR = REPO / "msg_schemas" / "msg"
INFINITE = DURATION_INFINITE_NS


def _msg_text(type_name: str) -> str:
    return find_interface_file(type_name, ".msg").read_text()


def _section(name: str) -> str:
    return f"\n{DELIMITER_LINE}\nMSG: {name}\n"


# ----- schema text ------------------------------------------------------------------------
def test_schema_text_is_rosbag2s_depth_first_sorted_concatenation() -> None:
    definition = build_message_definition("geometry_msgs/msg/PoseStamped")
    expected = (_msg_text("geometry_msgs/msg/PoseStamped")
                + _section("geometry_msgs/Pose") + _msg_text("geometry_msgs/msg/Pose")
                + _section("geometry_msgs/Point") + _msg_text("geometry_msgs/msg/Point")
                + _section("geometry_msgs/Quaternion") + _msg_text("geometry_msgs/msg/Quaternion")
                + _section("std_msgs/Header") + _msg_text("std_msgs/msg/Header")
                + _section("builtin_interfaces/Time") + _msg_text("builtin_interfaces/msg/Time"))
    assert definition.encoding == "ros2msg"
    assert definition.type_name == "geometry_msgs/msg/PoseStamped"
    assert definition.text == expected


def test_each_dependency_appears_once() -> None:
    text = build_message_definition("nav_msgs/msg/Odometry").text
    for name in ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Point",
                 "geometry_msgs/PoseWithCovariance", "geometry_msgs/Vector3"):
        assert text.count(f"MSG: {name}\n") == 1, name


def test_dependency_parser_handles_arrays_constants_and_package_context() -> None:
    text = ("# comment Foo bar\nuint8 MODE_A=1\nint32[<=5] bounded\nstring<=8 name\n"
            "Point[] points\ngeometry_msgs/Vector3[3] vectors\n  builtin_interfaces/Time stamp\n"
            "wstring w\nfloat64 x 0.5\n")
    assert parse_msg_dependencies(text, "my_pkg") == [
        "builtin_interfaces/Time", "geometry_msgs/Vector3", "my_pkg/Point"]


@pytest.fixture()
def project_prefix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An ament prefix holding the project's .msg files as package em_exploration_msgs."""
    prefix = tmp_path / "prefix"
    (prefix / "share" / "em_exploration_msgs").mkdir(parents=True)
    shutil.copytree(MSG_DIR, prefix / "share" / "em_exploration_msgs" / "msg")
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages"
    marker.mkdir(parents=True)
    (marker / "em_exploration_msgs").write_text("")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    return prefix


def test_project_messages_have_complete_definitions(project_prefix: Path) -> None:
    for msg_file in sorted(MSG_DIR.glob("*.msg")):
        type_name = f"em_exploration_msgs/msg/{msg_file.stem}"
        definition = build_message_definition(type_name)
        assert definition.encoding == "ros2msg"
        assert definition.text.startswith(msg_file.read_text())
        # The mcap_ros2 codec builds an encoder and decoder from the text alone: this fails
        # if a dependency is missing.
        encoders = serialize_dynamic(type_name, definition.text)
        assert type_name in encoders
    team_update = build_message_definition("em_exploration_msgs/msg/TeamUpdate").text
    for dependency in ("em_exploration_msgs/Keyframe", "em_exploration_msgs/KeyframeLandmark",
                       "em_exploration_msgs/KeyframeTeammate", "builtin_interfaces/Time"):
        assert team_update.count(f"MSG: {dependency}\n") == 1


def test_project_message_round_trips_through_schema_codec(project_prefix: Path) -> None:
    type_name = "em_exploration_msgs/msg/SonarScan"
    text = build_message_definition(type_name).text
    encode = serialize_dynamic(type_name, text)[type_name]
    decode = generate_dynamic(type_name, text)[type_name]
    message = {"header": {"stamp": {"sec": 3, "nanosec": 7}, "frame_id": "robot_0/base_link"},
               "robot_id": 2, "step": 41, "max_range": 7.5, "landmarks": [],
               "teammates": [], "team_sequences": [1, 5, 9]}
    decoded = decode(encode(message))
    assert decoded.header.frame_id == "robot_0/base_link"
    assert (decoded.robot_id, decoded.step, decoded.max_range) == (2, 41, 7.5)
    assert list(decoded.team_sequences) == [1, 5, 9]


def test_idl_fallback_when_msg_files_are_missing(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    prefix = tmp_path / "idl_prefix"
    share = prefix / "share" / "idl_only_msgs" / "msg"
    share.mkdir(parents=True)
    (share / "Outer.idl").write_text('#include "idl_only_msgs/msg/Inner.idl"\nmodule x {};\n')
    (share / "Inner.idl").write_text("module y {};\n")
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages"
    marker.mkdir(parents=True)
    (marker / "idl_only_msgs").write_text("")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    definition = build_message_definition("idl_only_msgs/msg/Outer")
    assert definition.encoding == "ros2idl"
    assert definition.text == (
        f"{DELIMITER_LINE}\nIDL: idl_only_msgs/msg/Outer\n"
        '#include "idl_only_msgs/msg/Inner.idl"\nmodule x {};\n'
        f"\n{DELIMITER_LINE}\nIDL: idl_only_msgs/msg/Inner\nmodule y {{}};\n")


def test_missing_type_raises() -> None:
    with pytest.raises(DefinitionNotFoundError):
        build_message_definition("no_such_msgs/msg/Nothing")


def test_type_hash_from_the_type_description_file() -> None:
    assert read_type_hash("std_msgs/msg/String") == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert read_type_hash("no_such_msgs/msg/Nothing") == ""


# ----- QoS and metadata YAML --------------------------------------------------------------
#: One profile as rosbag2 Jazzy dumps it (layout of ros2/rosbag2 pull request 1476).
ROSBAG2_QOS_TEXT = (
    "- history: keep_last\n  depth: 1\n  reliability: reliable\n  durability: volatile\n"
    "  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n"
    "  liveliness: system_default\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
    "  avoid_ros_namespace_conventions: false")


def test_qos_yaml_reads_rosbag2_text_and_round_trips() -> None:
    profile = QosProfile(history="keep_last", depth=1)
    assert qos_profiles_from_yaml(ROSBAG2_QOS_TEXT) == [profile]
    assert yaml.safe_load(qos_profiles_to_yaml([profile])) == yaml.safe_load(ROSBAG2_QOS_TEXT)
    latched = QosProfile(history="unknown", depth=0, durability="transient_local",
                         deadline_ns=INFINITE, lifespan_ns=INFINITE, liveliness="automatic",
                         liveliness_lease_duration_ns=INFINITE)
    text = qos_profiles_to_yaml([profile, latched])
    assert yaml.safe_load(text)[1]["deadline"] == {"sec": 9223372036, "nsec": 854775807}
    assert qos_profiles_from_yaml(text) == [profile, latched]
    assert qos_profiles_from_yaml(qos_profiles_to_yaml([])) == []
    assert qos_profiles_from_yaml("") == []


def test_qos_yaml_reads_pre_jazzy_integers_and_foxy_infinity() -> None:
    legacy = ("- history: 1\n  depth: 5\n  reliability: 2\n  durability: 1\n"
              "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
              "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n"
              "  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
              "  avoid_ros_namespace_conventions: false")
    [profile] = qos_profiles_from_yaml(legacy)
    assert (profile.history, profile.depth, profile.reliability, profile.durability,
            profile.liveliness) == ("keep_last", 5, "best_effort", "transient_local", "automatic")
    assert profile.deadline_ns == INFINITE
    for bad in ("- history: sideways\n  depth: 1", "not: [a, list", "{a: 1}"):
        with pytest.raises(QosFormatError):
            qos_profiles_from_yaml(bad)


def test_subscription_qos_serves_every_publisher() -> None:
    reliable = QosProfile(reliability="reliable")
    best_effort = QosProfile(reliability="best_effort")
    latched = QosProfile(durability="transient_local")
    assert request_for_offers([reliable, reliable], 50) == QosProfile(depth=50)
    assert request_for_offers([reliable, best_effort], 50).reliability == "best_effort"
    assert request_for_offers([latched, latched], 50).durability == "transient_local"
    assert request_for_offers([latched, reliable], 50).durability == "volatile"


def test_playback_qos_follows_recorded_offers() -> None:
    latched = QosProfile(history="unknown", depth=0, durability="transient_local",
                         deadline_ns=INFINITE)
    assert offer_for_playback([latched, latched], 100) == QosProfile(
        history="keep_last", depth=100, durability="transient_local", deadline_ns=INFINITE)
    assert offer_for_playback([latched, QosProfile()], 100) == QosProfile(depth=100)
    assert offer_for_playback([], 7) == QosProfile(depth=7)


def _metadata() -> BagMetadata:
    qos = QosProfile(history="unknown", depth=0)
    return BagMetadata(
        relative_file_path="run.mcap", starting_time_ns=5, duration_ns=20, message_count=3,
        topics=(TopicInformation("/chatter", "std_msgs/msg/String", 3, (qos,), "RIHS01_ab"),))


def test_bag_metadata_yaml_reads_rosbag2_text_and_writes_the_same_document() -> None:
    rosbag2_text = (
        "version: 9\nstorage_identifier: mcap\nduration:\n  nanoseconds: 20\n"
        "starting_time:\n  nanoseconds_since_epoch: 5\nmessage_count: 3\n"
        "topics_with_message_count:\n  - topic_metadata:\n      name: /chatter\n"
        "      type: std_msgs/msg/String\n      serialization_format: cdr\n"
        "      offered_qos_profiles:\n        - history: unknown\n          depth: 0\n"
        "          reliability: reliable\n          durability: volatile\n"
        "          deadline:\n            sec: 0\n            nsec: 0\n"
        "          lifespan:\n            sec: 0\n            nsec: 0\n"
        "          liveliness: system_default\n          liveliness_lease_duration:\n"
        "            sec: 0\n            nsec: 0\n"
        "          avoid_ros_namespace_conventions: false\n"
        "      type_description_hash: RIHS01_ab\n    message_count: 3\n"
        'compression_format: ""\ncompression_mode: ""\nrelative_file_paths:\n  - run.mcap\n'
        "files:\n  - path: run.mcap\n    starting_time:\n      nanoseconds_since_epoch: 5\n"
        "    duration:\n      nanoseconds: 20\n    message_count: 3\n"
        "custom_data: ~\nros_distro: jazzy")  # as yaml-cpp's YAML::Dump lays it out
    assert parse_bag_metadata(rosbag2_text) == _metadata()
    written = serialize_bag_metadata(_metadata())
    assert yaml.safe_load(written) == yaml.safe_load(rosbag2_text)
    assert list(yaml.safe_load(written)) == list(yaml.safe_load(rosbag2_text))  # key order


def test_bag_metadata_reads_version_8_with_qos_string() -> None:
    text = ("version: 8\nstorage_identifier: mcap\nduration:\n  nanoseconds: 1\n"
            "starting_time:\n  nanoseconds_since_epoch: 2\nmessage_count: 4\n"
            "topics_with_message_count:\n  - topic_metadata:\n      name: /a\n"
            "      type: std_msgs/msg/String\n      serialization_format: cdr\n"
            f"      offered_qos_profiles: {json.dumps(ROSBAG2_QOS_TEXT)}\n"
            '      type_description_hash: ""\n    message_count: 4\n'
            'compression_format: ""\ncompression_mode: ""\nrelative_file_paths:\n  - a.mcap\n'
            "files:\n  []\ncustom_data: ~\nros_distro: humble")
    metadata = parse_bag_metadata(text)
    assert metadata.version == 8 and metadata.ros_distro == "humble"
    assert metadata.topics[0].offered_qos_profiles == (QosProfile(depth=1),)


def test_topic_selection() -> None:
    everything = TopicSelection.from_strings()
    assert everything.matches("/anything")
    chosen = TopicSelection.from_strings(["/a"], r"^/robot_\d+/", r"debug")
    assert chosen.matches("/a") and chosen.matches("/robot_1/sonar")
    assert not chosen.matches("/b") and not chosen.matches("/robot_1/debug")
    assert not TopicSelection.from_strings(exclude="a").matches("/a")


# ----- writer and readers -----------------------------------------------------------------
def _messages(count: int) -> list[tuple[str, object]]:
    out: list[tuple[str, object]] = []
    for k in range(count):
        out.append(("/clock", Clock(clock=Time(sec=100 + k // 10, nanosec=(k % 10) * 10**8))))
        out.append(("/chatter", String(data=f"message {k} " + "x" * (k % 37))))
        odom = Odometry()
        odom.header.frame_id = "map"
        odom.child_frame_id = f"robot_{k % 3}/base_link"
        odom.pose.pose.position.x = 0.25 * k
        odom.pose.covariance[0] = float(k)
        out.append(("/robot/odom", odom))
    return out


TYPES = {"/clock": "rosgraph_msgs/msg/Clock", "/chatter": "std_msgs/msg/String",
         "/robot/odom": "nav_msgs/msg/Odometry"}
CLASSES = {"/clock": Clock, "/chatter": String, "/robot/odom": Odometry}
OFFERS = {"/chatter": (QosProfile(history="unknown", depth=0),),
          "/robot/odom": (QosProfile(durability="transient_local"),) * 2,
          "/clock": (QosProfile(reliability="best_effort"),)}


def _write_bag(path: Path, count: int = 300, compression: str = "zstd",
               chunk_size: int = 2048, directory: bool = False) -> list[tuple[str, int, bytes]]:
    """Write a bag (an .mcap file, or a bag directory); returns what was written as (topic,
    log time, data)."""
    written = []
    writer_class = BagDirectoryWriter if directory else BagWriter
    with writer_class(path, compression=compression, chunk_size=chunk_size) as writer:
        channels = {topic: writer.add_topic(topic, build_message_definition(type_name),
                                            OFFERS[topic], read_type_hash(type_name))
                    for topic, type_name in TYPES.items()}
        for index, (topic, message) in enumerate(_messages(count)):
            data = serialize_message(message)
            log_time = 1_000_000_000 + index * 1_000_000
            writer.write(channels[topic], log_time, data)
            written.append((topic, log_time, data))
    return written


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_written_bag_reads_back_with_independent_readers(tmp_path: Path,
                                                         compression: str) -> None:
    path = tmp_path / f"bag_{compression}.mcap"
    written = _write_bag(path, compression=compression)

    # 1. the mcap stream reader with CRC validation: every record parses.
    with path.open("rb") as stream:
        records = list(StreamReader(stream, emit_chunks=True, validate_crcs=True).records)
    header = records[0]
    assert isinstance(header, Header) and header.profile == "ros2"
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) > 5
    assert all(c.compression == ("" if compression == "none" else compression) for c in chunks)
    assert all(c.uncompressed_crc != 0 for c in chunks)
    with path.open("rb") as stream:
        inner = list(StreamReader(stream, validate_crcs=True).records)
    schemas = {r.name: r for r in inner if isinstance(r, Schema)}
    assert set(schemas) == set(TYPES.values())
    assert all(s.encoding == "ros2msg" for s in schemas.values())
    channels = {r.topic: r for r in inner if isinstance(r, Channel)}
    assert set(channels) == set(TYPES)
    for topic, channel in channels.items():
        assert channel.message_encoding == "cdr"
        assert channel.metadata["topic_type_hash"] == read_type_hash(TYPES[topic])
        assert qos_profiles_from_yaml(channel.metadata["offered_qos_profiles"]) == list(
            OFFERS[topic])
    messages = [r for r in inner if isinstance(r, Message)]
    assert len(messages) == len(written)

    # 2. the seeking reader with the ros2msg decoder, driven by the schema text alone.
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = list(reader.iter_decoded_messages(log_time_order=True))
        summary = reader.get_summary()
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert [(c.topic, m.log_time, m.data) for _s, c, m, _d in decoded] == written
    odometry = [d for _s, c, _m, d in decoded if c.topic == "/robot/odom"]
    assert odometry[-1].pose.pose.position.x == 0.25 * 299
    assert summary.statistics.message_count == len(written)

    # 3. rclpy's deserializer into the ROS types; first and last message per topic.
    for topic, cls in CLASSES.items():
        ours = [data for t, _time, data in written if t == topic]
        stored = [m.data for _s, c, m, _d in decoded if c.topic == topic]
        assert deserialize_message(stored[0], cls) == deserialize_message(ours[0], cls)
        assert deserialize_message(stored[-1], cls) == deserialize_message(ours[-1], cls)

    # 4. the rosbag2 metadata record agrees with the statistics.
    bag_metadata = parse_bag_metadata(metadata["rosbag2"]["serialized_metadata"])
    assert bag_metadata.message_count == len(written)
    assert bag_metadata.starting_time_ns == written[0][1]
    assert bag_metadata.duration_ns == written[-1][1] - written[0][1]
    assert {t.name: t.message_count for t in bag_metadata.topics} == {
        topic: 300 for topic in TYPES}
    assert bag_metadata.relative_file_path == path.name

    # 5. the project's scanner.
    info = scan_bag(path)
    assert info.complete and info.problem is None
    assert info.message_count == len(written)
    assert info.crc_checked_chunks == info.chunk_count == len(chunks)
    assert info.topic_counts() == {topic: 300 for topic in TYPES}


def test_empty_bag_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    BagWriter(path).close()
    info = scan_bag(path)
    assert info.complete and info.message_count == 0 and info.channels == {}
    assert info.rosbag2_metadata().starting_time_ns == 2**63 - 1


def test_writer_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "exists.mcap"
    path.write_bytes(b"keep me")
    with pytest.raises(FileExistsError):
        BagWriter(path)
    assert path.read_bytes() == b"keep me"


def test_flush_makes_chunks_readable_before_close(tmp_path: Path) -> None:
    path = tmp_path / "open.mcap"
    writer = BagWriter(path, chunk_size=10**9)
    channel = writer.add_topic("/chatter", build_message_definition("std_msgs/msg/String"))
    for k in range(5):
        writer.write(channel, k, serialize_message(String(data=str(k))))
    writer.flush()
    writer.write(channel, 9, serialize_message(String(data="unflushed")))
    info = scan_bag(path, tolerant=True)
    assert not info.complete and "truncated" in info.problem
    assert info.message_count == 5
    writer.close()
    assert scan_bag(path).message_count == 6


def test_bag_directory_is_what_rosbag2_writes(tmp_path: Path) -> None:
    bag = tmp_path / "run"
    written = _write_bag(bag, count=40, directory=True)
    assert sorted(p.name for p in bag.iterdir()) == [METADATA_FILE, "run_0.mcap"]
    assert mcap_file(bag) == bag / "run_0.mcap"
    metadata = read_metadata_yaml(bag)
    assert metadata == scan_bag(bag).rosbag2_metadata()  # metadata.yaml = embedded record
    assert metadata.relative_file_path == "run_0.mcap"
    assert metadata.message_count == len(written) == scan_bag(bag).message_count
    # rosbags, an independent reader of rosbag2 bag directories, reads every message.
    with RosbagsReader(bag) as reader:
        assert reader.message_count == len(written)
        assert {c.topic: c.msgtype for c in reader.connections} == TYPES
        read = [(c.topic, stamp, bytes(data)) for c, stamp, data in reader.messages()]
    assert read == written
    with pytest.raises(FileExistsError):
        BagDirectoryWriter(bag)


def test_bag_directory_of_a_killed_recording_and_unsupported_ones(tmp_path: Path) -> None:
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / "killed_0.mcap").write_bytes(b"")  # no metadata.yaml: the recorder died
    assert mcap_file(killed) == killed / "killed_0.mcap"
    (killed / "killed_1.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="2 storage files"):
        scan_bag(killed)
    sqlite = tmp_path / "sqlite"
    sqlite.mkdir()
    (sqlite / METADATA_FILE).write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n"
        "  relative_file_paths: [sqlite_0.db3]\n")
    with pytest.raises(BagPathError, match="not mcap"):
        mcap_file(sqlite)
    with pytest.raises(BagError, match="no such file or directory"):
        scan_bag(tmp_path / "nothing")


# ----- damaged files ----------------------------------------------------------------------
def test_scanner_reports_damage(tmp_path: Path) -> None:
    path = tmp_path / "good.mcap"
    _write_bag(path, compression="none")
    data = path.read_bytes()

    flipped = tmp_path / "flipped.mcap"
    position = data.index(b"message 150")
    flipped.write_bytes(data[:position] + b"M" + data[position + 1:])
    with pytest.raises(BagError, match="CRC mismatch"):
        scan_bag(flipped)

    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="truncated"):
        scan_bag(truncated)

    not_mcap = tmp_path / "notes.txt"
    not_mcap.write_text("hello")
    with pytest.raises(NotMcapError, match="not an MCAP file"):
        scan_bag(not_mcap, tolerant=True)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(NotMcapError, match="empty file"):
        scan_bag(empty)
    with pytest.raises(BagError, match="no such file"):
        scan_bag(tmp_path / "missing.mcap")


def test_tolerant_scan_and_repair_keep_every_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "good.mcap"
    written = _write_bag(path)
    data = path.read_bytes()
    with path.open("rb") as stream:
        footer = [r for r in StreamReader(stream, emit_chunks=True).records
                  if isinstance(r, Footer)][0]
    for fraction in (0.25, 0.5, 0.75):
        cut = tmp_path / f"cut_{fraction}.mcap"
        cut.write_bytes(data[: int(footer.summary_start * fraction)])
        scanner = BagScanner(cut, tolerant=True)
        recovered = [(c.topic, m.log_time_ns, m.data) for c, m in scanner.messages()]
        assert not scanner.info.complete and "truncated" in scanner.info.problem
        assert 0 < len(recovered) < len(written)
        assert recovered == written[: len(recovered)]

        fixed = tmp_path / f"fixed_{fraction}.mcap"
        result = repair(cut, fixed)
        assert result.messages == len(recovered) and not result.input_complete
        info = scan_bag(fixed)
        assert info.complete and info.message_count == len(recovered)
        with fixed.open("rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            again = [(c.topic, m.log_time, m.data)
                     for _s, c, m, _d in reader.iter_decoded_messages(log_time_order=True)]
        assert again == recovered
        channels = {c.topic: c for c in info.channels.values()}
        assert channels["/robot/odom"].offered_qos == list(OFFERS["/robot/odom"])
        assert channels["/chatter"].type_hash == read_type_hash("std_msgs/msg/String")


def test_info_report_lists_topics(tmp_path: Path) -> None:
    path = tmp_path / "report.mcap"
    _write_bag(path, count=20)
    report = format_info(scan_bag(path))
    assert "Messages:          60" in report
    assert "Topic: /robot/odom | Type: nav_msgs/msg/Odometry | Count: 20" in report
    assert "ROS distro:        jazzy" in report
    assert "compression: zstd" in report
    assert "Duration:          0.059000000s" in report


def _em_bag(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.bag", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=60)


def test_em_bag_cli_gives_one_line_errors(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / "good.mcap"
    _write_bag(good, count=30)
    code, out, _err = run_em_bag(capsys, "info", str(good))
    assert code == 0 and "Topic: /chatter" in out

    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[:-200])
    not_mcap = tmp_path / "text.mcap"
    not_mcap.write_text("plain text, no magic")
    cases = {str(truncated): "truncated", str(not_mcap): "not an MCAP file",
             str(tmp_path / "missing.mcap"): "no such file"}
    for target, phrase in cases.items():
        code, _out, err = run_em_bag(capsys, "info", target)
        assert code == 2 and phrase in err and len(err.strip().splitlines()) == 1, err

    fixed = tmp_path / "fixed.mcap"
    code, out, _err = run_em_bag(capsys, "repair", str(truncated), str(fixed))
    assert code == 0 and "recovered 90 messages" in out
    assert scan_bag(fixed).message_count == 90
    code, _out, err = run_em_bag(capsys, "repair", str(truncated), str(fixed))
    assert code == 2 and "already exists" in err
    code, _out, _err = run_em_bag(capsys, "repair", str(not_mcap),
                                          str(tmp_path / "never.mcap"))
    assert code == 2 and not (tmp_path / "never.mcap").exists()

    # End to end: the one-line error is all the user sees.
    result = _em_bag("info", str(truncated))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
