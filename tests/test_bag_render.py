"""The committed sample recording and ``em-bag info`` / ``em-bag render`` on it.

bags/sample_3robots/ is a real 3-robot lockstep run recorded with run_team.sh --record
(bags/README.md), a bag directory. It is read back by readers other than the writer (the
``mcap`` stream reader with CRC validation, the ``mcap_ros2`` schema-driven decoder, rclpy's
deserializer, rosbags) and by the project's validating scanner; then the CLI reports on it
and draws its map.
"""
from __future__ import annotations

import array
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.image import imread
from PIL import Image
from mcap.records import Chunk, Footer, Header, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from visualization_msgs.msg import MarkerArray
from std_msgs.msg import String

from em_exploration_ros.bag_format.bag_directory import mcap_file, read_metadata_yaml
from em_exploration_ros.bag_format.bag_reader import BagScanner, scan_bag
from em_exploration_ros.bag_format.bag_writer import BagWriter
from em_exploration_ros.bag_format.mcap_ros2_schema import build_message_definition
from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.core.evaluation.summary import TARGET_TYPES
from em_exploration_ros.tools.bag_ros import import_message_class
from em_exploration_ros.core.evaluation.run_animation import render_animation
from em_exploration_ros.tools.bag_render import read_team_frames, read_team_map
from em_bag_cli import run_em_bag

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "bags" / "sample_3robots"
SAMPLE_FILE = mcap_file(SAMPLE)
SAMPLE_PARAMS = load_params(REPO / "bags" / "sample_3robots.params.yaml")
ROBOTS = range(SAMPLE_PARAMS.world.num_robots)
#: Topics the sample must hold (with messages) and their types.
EXPECTED_TOPICS = {
    "/clock": "rosgraph_msgs/msg/Clock",
    "/mission/anchor_pose": "geometry_msgs/msg/PoseStamped",
    "/world/landmarks": "em_exploration_msgs/msg/LandmarkArray",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    **{f"/world/ground_truth/robot_{i}": "nav_msgs/msg/Odometry" for i in ROBOTS},
    **{f"/robot_{i}/{name}": type_name for i in ROBOTS for name, type_name in (
        ("sonar", "em_exploration_msgs/msg/SonarScan"), ("odom", "nav_msgs/msg/Odometry"),
        ("team/updates", "em_exploration_msgs/msg/TeamUpdate"),
        ("estimated_path", "nav_msgs/msg/Path"),
        ("landmarks", "em_exploration_msgs/msg/LandmarkArray"),
        ("markers", "visualization_msgs/msg/MarkerArray"),
        ("virtual_map", "nav_msgs/msg/OccupancyGrid"))},
}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# ----- the sample file itself -------------------------------------------------------------
def test_sample_is_small_and_reads_back_with_independent_readers() -> None:
    assert SAMPLE_FILE.stat().st_size < 2 * 1024 * 1024
    # Every record parses; every chunk and the data section match their CRCs.
    with SAMPLE_FILE.open("rb") as stream:
        chunks = [r for r in StreamReader(stream, emit_chunks=True).records
                  if isinstance(r, Chunk)]
    assert chunks and all(chunk.uncompressed_crc != 0 for chunk in chunks)
    with SAMPLE_FILE.open("rb") as stream:
        records = list(StreamReader(stream, validate_crcs=True).records)
    assert isinstance(records[0], Header) and isinstance(records[-1], Footer)
    messages = [r for r in records if isinstance(r, Message)]

    # The project's validating scanner agrees, chunk for chunk and message for message.
    scanner = BagScanner(SAMPLE)
    walked = list(scanner.messages())
    info = scanner.info
    assert info.complete and info.problem is None
    assert info.crc_checked_chunks == info.chunk_count == len(chunks)
    assert [m.data for _c, m in walked] == [m.data for m in messages]
    # rosbags reads the bag directory whole; its metadata.yaml is the embedded metadata.
    with RosbagsReader(SAMPLE) as reader:
        assert reader.message_count == info.message_count == len(messages)
    assert read_metadata_yaml(SAMPLE) == info.rosbag2_metadata()

    # Every message deserializes into its installed ROS type, and the schema text alone
    # (mcap_ros2) decodes it to the same values.
    decoder = DecoderFactory()
    decoders = {}
    for channel, message in walked:
        schema = info.schema_of(channel)
        ros_message = deserialize_message(message.data, import_message_class(schema.name))
        if schema.id not in decoders:
            decoders[schema.id] = decoder.decoder_for("cdr", Schema(
                id=schema.id, name=schema.name, encoding=schema.encoding, data=schema.data))
        assert same_values(ros_message, decoders[schema.id](message.data)), channel.topic


def same_values(ros_value: Any, decoded: Any) -> bool:
    """True if an rclpy message and an mcap_ros2 decoded message hold the same values."""
    if hasattr(ros_value, "get_fields_and_field_types"):
        return all(same_values(getattr(ros_value, name), getattr(decoded, name))
                   for name in ros_value.get_fields_and_field_types())
    if isinstance(ros_value, (bytes, list, tuple, array.array, np.ndarray)):
        items = list(ros_value)
        return len(items) == len(decoded) and all(map(same_values, items, decoded))
    if isinstance(ros_value, float) and math.isnan(ros_value):
        return math.isnan(decoded)
    return ros_value == decoded


def test_sample_stamps_are_simulation_times() -> None:
    """Markers (the clearing entry included), the mission anchor and the odometry carry the
    simulation time of their content; the odometry carries its noise's covariance."""
    clock_ns = 10**9 * SAMPLE_PARAMS.motion.time_step_s
    last_odom, marker_stamps = None, []
    for channel, message in BagScanner(SAMPLE).messages():
        if channel.topic == "/mission/anchor_pose":
            anchor = deserialize_message(message.data, PoseStamped)
            assert (anchor.header.stamp.sec, anchor.header.stamp.nanosec) == (0, 0)  # step 0
        elif channel.topic == "/robot_0/markers":
            markers = deserialize_message(message.data, MarkerArray).markers
            stamps = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in markers}
            assert len(stamps) == 1, stamps  # one decision, one time
            [stamp] = stamps
            assert round(stamp / clock_ns) * clock_ns == stamp  # the time of a step
            marker_stamps.append(stamp)
        elif channel.topic == "/robot_0/odom":
            last_odom = deserialize_message(message.data, Odometry)
    assert marker_stamps == sorted(marker_stamps) and marker_stamps[-1] > 0
    assert last_odom is not None and last_odom.pose.covariance[0] > 0.0


# ----- em-bag info ------------------------------------------------------------------------
def test_info_lists_the_runs_topics(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_em_bag(capsys, "info", str(SAMPLE))
    assert code == 0, err
    listed = {m.group(1): (m.group(2), int(m.group(3))) for m in re.finditer(
        r"Topic: (\S+) \| Type: (\S+) \| Count: (\d+)", out)}
    for topic, type_name in EXPECTED_TOPICS.items():
        assert topic in listed, topic
        assert listed[topic][0] == type_name and listed[topic][1] > 0, (topic, listed[topic])
    # Lockstep: the world published every step to every robot.
    steps = {listed[f"/robot_{i}/{name}"][1] for i in ROBOTS for name in ("sonar", "odom")}
    assert steps == {listed["/clock"][1]}
    assert "CRC verified: " in out and "ROS distro:        jazzy" in out


# ----- em-bag render ----------------------------------------------------------------------
def test_final_team_map_of_the_sample() -> None:
    team_map = read_team_map(SAMPLE)
    layers = team_map.layers
    world = SAMPLE_PARAMS.world
    assert team_map.robots == list(ROBOTS)
    assert (layers.width_m, layers.height_m) == (world.width_m, world.height_m)
    assert len(layers.true_landmarks) == world.num_landmarks
    assert layers.landmark_radius_m == world.landmark_radius_m
    assert layers.explored.shape == (int(world.height_m / SAMPLE_PARAMS.map.cell_size_m),
                                     int(world.width_m / SAMPLE_PARAMS.map.cell_size_m))
    assert 0.3 < layers.explored.mean() < 1.0
    for robot in ROBOTS:
        truth = layers.true_paths[robot]
        estimate = layers.estimated_paths[robot]
        assert len(truth) > 100 and len(estimate) > 5
        # Every estimated keyframe lies close to the true trajectory (loc RMSE ~ 0.1 m).
        gaps = np.linalg.norm(estimate[:, None, :2] - truth[None, :, :2], axis=-1).min(axis=1)
        assert gaps.max() < 0.5, (robot, gaps.max())
        # Landmark estimates lie on true landmarks.
        known = layers.estimated_landmarks[robot]
        assert len(known) > 0
        assert np.linalg.norm(known[:, None] - layers.true_landmarks[None], axis=-1).min(
            axis=1).max() < 0.5
        assert len(layers.targets[robot]) >= 3
        assert all(t.type in TARGET_TYPES for t in layers.targets[robot])
        ellipses = team_map.ellipses[robot]
        assert ellipses.count > 50
        assert np.all(ellipses.axes[:, 0] >= ellipses.axes[:, 1]) and np.all(ellipses.axes > 0)
        inside = (ellipses.centres >= 0).all() and (ellipses.centres <= world.width_m).all()
        assert inside
        assert team_map.frontiers[robot] and all(
            f.type in TARGET_TYPES for f in team_map.frontiers[robot])


def test_the_samples_rendezvous_are_judged_from_the_team_updates() -> None:
    # Robot 2 asked robot 0 twice (11 decisions, 2 rendezvous targets); both met.
    rendezvous = read_team_map(SAMPLE).layers.rendezvous
    assert [(r.requester_id, r.partner_id, r.outcome) for r in rendezvous] == [
        (2, 0, "met"), (2, 0, "met")]
    assert all(0.0 <= r.x <= 40.0 and 0.0 <= r.y <= 40.0 for r in rendezvous)


def test_the_samples_frames_follow_the_run_to_its_final_map(tmp_path: Path) -> None:
    frames = read_team_frames(SAMPLE, max_frames=5)
    final = read_team_map(SAMPLE).layers
    assert len(frames) == 5 and frames[-1].title == final.title
    times = [float(re.search(r"t = ([0-9.]+) s", f.title).group(1)) for f in frames]
    assert times == sorted(set(times)) and times[-1] == 31.8  # strictly increasing
    for robot in ROBOTS:
        lengths = [len(f.true_paths.get(robot, ())) for f in frames]
        chosen = [len(f.targets.get(robot, ())) for f in frames]
        assert lengths == sorted(lengths) and lengths[-1] == len(final.true_paths[robot])
        assert chosen == sorted(chosen) and chosen[-1] == len(final.targets[robot])
    assert all(not f.uncertainty_ellipses for f in frames[:-1]) and frames[-1].uncertainty_ellipses
    gif = render_animation(frames, tmp_path / "sample.gif", dpi=40)
    with Image.open(gif) as image:
        assert image.n_frames == 5


def test_render_writes_a_png(tmp_path: Path) -> None:
    out = tmp_path / "maps" / "sample.png"
    # A separate process: rendering needs no ROS graph and no rclpy.init.
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.bag", "render",
                             str(SAMPLE), "--out", str(out)], cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert f"wrote {out}: 3 robots" in result.stdout
    assert out.read_bytes()[:8] == PNG_MAGIC and out.stat().st_size > 30_000
    image = imread(out)
    assert image.shape[0] > 500 and image.shape[1] > 700
    # Not a blank picture: many distinct colours (paths, landmarks, explored area).
    assert len(np.unique(image[..., :3].reshape(-1, 3), axis=0)) > 50


def _one_message_bag(path: Path, topic: str, message: Any) -> Path:
    type_name = f"{type(message).__module__.split('.')[0]}/msg/{type(message).__name__}"
    with BagWriter(path) as writer:
        channel = writer.add_topic(topic, build_message_definition(type_name))
        writer.write(channel, 0, serialize_message(message))
    return path


def test_render_gives_one_line_errors(tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(SAMPLE_FILE.read_bytes()[: SAMPLE_FILE.stat().st_size // 2])
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("not a recording")
    no_robots = _one_message_bag(tmp_path / "clock_only.mcap", "/clock", Clock())
    wrong_type = _one_message_bag(tmp_path / "wrong_type.mcap", "/robot_0/estimated_path",
                                  String(data="not a path"))
    cases = {truncated: ("truncated", "em-bag repair"), not_mcap: ("not an MCAP file", ""),
             no_robots: ("no robot topics", ""), tmp_path / "missing.mcap": ("no such file", ""),
             wrong_type: ("has type std_msgs/msg/String, expected nav_msgs/msg/Path", "")}
    for path, (phrase, hint) in cases.items():
        out = tmp_path / f"{path.stem}.png"
        code, _out, err = run_em_bag(capsys, "render", str(path), "--out", str(out))
        assert code == 2 and phrase in err and hint in err, err
        assert len(err.strip().splitlines()) == 1 and not out.exists()
    assert scan_bag(no_robots).message_count == scan_bag(wrong_type).message_count == 1


#: A TeamUpdate definition as recordings made before issue 12 hold it (header, landmark
#: estimates and a TargetRecord with robot id, stamp and utility), shortened to the fields
#: render reads around: the recording's own schema decodes it, not the installed type.
OLDER_TEAM_UPDATE = """std_msgs/Header header
uint32 robot_id
uint64 sequence
TargetRecord[] targets
bool finished
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: em_exploration_msgs/TargetRecord
uint32 robot_id
uint32 decision_index
builtin_interfaces/Time stamp
float64 x
float64 y
uint8 frontier_type
uint32 partner_id
float64 utility
float64 planning_time
bool planner_failed
"""


def test_render_reads_targets_recorded_with_an_older_schema(tmp_path: Path) -> None:
    from mcap_ros2._dynamic import serialize_dynamic

    from em_exploration_ros.bag_format.mcap_ros2_schema import MessageDefinition

    type_name = "em_exploration_msgs/msg/TeamUpdate"
    encode = serialize_dynamic(type_name, OLDER_TEAM_UPDATE)[type_name]

    def target(index: int, x: float, kind: int) -> dict:
        return {"robot_id": 0, "decision_index": index, "stamp": {"sec": index, "nanosec": 0},
                "x": x, "y": 2.0 * x, "frontier_type": kind, "partner_id": 0, "utility": 0.5,
                "planning_time": 0.1, "planner_failed": False}

    path = tmp_path / "older.mcap"
    with BagWriter(path) as writer:
        channel = writer.add_topic("/robot_0/team/updates",
                                   MessageDefinition(type_name, "ros2msg", OLDER_TEAM_UPDATE))
        for sequence, targets in ((1, [target(0, 3.0, 0)]), (2, [target(1, 5.0, 1)]),
                                  (2, [target(1, 5.0, 1)])):  # a re-sent update counts once
            writer.write(channel, sequence, encode({
                "header": {"stamp": {"sec": sequence, "nanosec": 0}, "frame_id": "map"},
                "robot_id": 0, "sequence": sequence, "targets": targets, "finished": False}))
    targets = read_team_map(path).layers.targets[0]
    assert [(t.x, t.y, t.type) for t in targets] == [(3.0, 6.0, "exploration"),
                                                     (5.0, 10.0, "revisiting")]
