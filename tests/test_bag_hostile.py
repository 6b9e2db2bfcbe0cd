"""Hostile recordings and arguments: em-bag and em-replay answer with one clear error (or a
bounded result), never a traceback, a hang or a huge allocation."""
from __future__ import annotations

import io
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from em_bag_cli import run_em_bag
from em_exploration_ros.bag_format.bag_directory import METADATA_FILE, BagPathError, mcap_file
from em_exploration_ros.bag_format.bag_reader import BagError, scan_bag
from em_exploration_ros.bag_format.bag_writer import BagWriter
from em_exploration_ros.bag_format.mcap_ros2_schema import build_message_definition
from em_exploration_ros.bag_format.qos_yaml import QosFormatError, qos_profiles_from_yaml
from em_exploration_ros.bag_format.rosbag2_metadata import (MetadataFormatError,
                                                            parse_bag_metadata)
from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.map_render import drawable_layers, render_team_map
from em_exploration_ros.tools import bag, replay

#: Deeper than PyYAML can parse within the default recursion limit (1000 frames).
DEEP_YAML = "[" * 600 + "]" * 600
#: The CDR of the std_msgs/msg/String "a".
STRING_A = b"\x00\x01\x00\x00\x02\x00\x00\x00a\x00"


def _alias_bomb(levels: int) -> str:
    """YAML lines of a list whose full repr has 10**levels items (each level 10 aliases)."""
    lines = ["    - &a [1,1,1,1,1,1,1,1,1,1]"]
    lines += [f"    - &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 10) + "]"
              for i in range(levels - 1)]
    return "\n".join(lines)


def _mcap(path: Path, *, type_name: str = "std_msgs/msg/String", qos: str | None = None,
          metadata: str | None = None) -> Path:
    """A one-message recording written with the mcap library (any schema name and text)."""
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(name=type_name, encoding="ros2msg",
                                        data=b"string data\n")
        channel = writer.register_channel(
            topic="/chatter", message_encoding="cdr", schema_id=schema,
            metadata={} if qos is None else {"offered_qos_profiles": qos})
        writer.add_message(channel_id=channel, log_time=1, publish_time=1, data=STRING_A)
        if metadata is not None:
            writer.add_metadata("rosbag2", {"serialized_metadata": metadata})
        writer.finish()
    return path


# ----- 3: alias bombs in QoS metadata; no partial repair output ------------------------------
def test_qos_error_shows_a_bounded_value() -> None:
    text = ("- history: keep_last\n  depth: 1\n  reliability: reliable\n"
            "  durability: volatile\n  deadline:\n" + _alias_bomb(6) + "\n")
    with pytest.raises(QosFormatError) as raised:
        qos_profiles_from_yaml(text)
    assert "deadline" in str(raised.value) and len(str(raised.value)) < 300


def test_repair_output_appears_only_when_complete(tmp_path: Path) -> None:
    source = _mcap(tmp_path / "in.mcap")
    target = tmp_path / "out.mcap"
    seen_while_writing = []

    class WatchedFile(io.FileIO):
        """The output file; as it is closed (written whole), whether ``target`` exists."""

        def close(self) -> None:
            if not self.closed:
                seen_while_writing.append(target.exists())
            super().close()

    assert bag.repair(source, target, create=lambda path: WatchedFile(path, "xb")).messages == 1
    assert seen_while_writing == [False]
    assert scan_bag(target).complete
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.mcap", "out.mcap"]


# ----- 4: declared lengths beyond the record ----------------------------------------------
def _record(opcode: int, body: bytes) -> bytes:
    return bytes([opcode]) + struct.pack("<Q", len(body)) + body


def _string(text: str) -> bytes:
    return struct.pack("<I", len(text)) + text.encode()


@pytest.mark.parametrize("record", [
    # a Chunk whose data length is 1 TiB
    _record(6, struct.pack("<QQQI", 0, 0, 10, 0) + _string("") + struct.pack("<Q", 2**40)
            + b"xx"),
    # a Schema whose name length is 0xffffffff
    _record(3, struct.pack("<H", 1) + struct.pack("<I", 0xFFFFFFFF) + b"xx"),
], ids=["chunk_data_length", "schema_string_length"])
def test_overlong_length_field_is_a_corrupt_record(tmp_path: Path, record: bytes,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "huge.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + _record(1, _string("ros2") + _string("x")) + record)
    with pytest.raises(BagError, match="truncated or corrupt record"):
        scan_bag(path)
    code, _, err = run_em_bag(capsys, "info", str(path))
    assert code == 2 and "corrupt record" in err


# ----- 9 and 24: metadata.yaml contents and where its storage file may be -------------------
def _bag_directory(tmp_path: Path, metadata: bytes) -> Path:
    directory = tmp_path / "bag"
    directory.mkdir()
    (directory / METADATA_FILE).write_bytes(metadata)
    return directory


def _metadata(files: str) -> bytes:
    return (f"rosbag2_bagfile_information:\n  storage_identifier: mcap\n"
            f"  relative_file_paths: {files}\n").encode()


@pytest.mark.parametrize("metadata", [
    _metadata("5"), _metadata('["a\\0b"]'), _metadata("[null]"),
    b"rosbag2_bagfile_information:\n  x: \"\xff\"\n", DEEP_YAML.encode()],
    ids=["not_a_list", "nul", "null", "not_utf8", "deep"])
def test_bad_metadata_yaml_is_a_path_error(tmp_path: Path, metadata: bytes) -> None:
    with pytest.raises(BagPathError):
        mcap_file(_bag_directory(tmp_path, metadata))


@pytest.mark.parametrize("name", ["../outside.mcap", "sub/../../outside.mcap", "ABSOLUTE"])
def test_storage_file_must_be_inside_the_bag_directory(tmp_path: Path, name: str) -> None:
    outside = _mcap(tmp_path / "outside.mcap")
    name = str(outside) if name == "ABSOLUTE" else name
    with pytest.raises(BagPathError, match="not a file inside the bag directory"):
        mcap_file(_bag_directory(tmp_path, _metadata(f"[{name}]")))


def test_storage_file_that_is_a_fifo_is_refused(tmp_path: Path) -> None:
    directory = _bag_directory(tmp_path, _metadata("[bag_0.mcap]"))
    os.mkfifo(directory / "bag_0.mcap")
    with pytest.raises(BagPathError, match="not a regular file"):
        mcap_file(directory)
    with pytest.raises(BagPathError, match="not a regular file"):
        mcap_file(directory / "bag_0.mcap")


# ----- 10 and 11: deeply nested YAML in the metadata record and in QoS -----------------------
def test_deep_metadata_record_is_reported_as_absent(tmp_path: Path) -> None:
    info = scan_bag(_mcap(tmp_path / "deep.mcap", metadata=DEEP_YAML))
    assert "no rosbag2 metadata" in bag.format_info(info)
    with pytest.raises(MetadataFormatError, match="expected text"):
        parse_bag_metadata("version: 9\nrelative_file_paths:\n  -\n" + _alias_bomb(6) + "\n")


def test_deep_qos_yaml_is_a_format_error(tmp_path: Path) -> None:
    with pytest.raises(QosFormatError, match="nested too deeply"):
        qos_profiles_from_yaml(DEEP_YAML)
    repaired = bag.repair(_mcap(tmp_path / "deep.mcap", qos=DEEP_YAML), tmp_path / "out.mcap")
    assert repaired.messages == 1


# ----- 12: repair into a folder that is not there -----------------------------------------
@pytest.mark.parametrize("directory_form", [False, True])
def test_repair_output_folder_must_exist(tmp_path: Path, directory_form: bool,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    source = _mcap(tmp_path / "in.mcap")
    if directory_form:
        source = _bag_directory(tmp_path, _metadata("[in.mcap]"))
        os.replace(tmp_path / "in.mcap", source / "in.mcap")
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for target, reason in ((tmp_path / "missing" / "deeper" / "out", "does not exist"),
                           (a_file / "out", "is not a folder")):
        code, _, err = run_em_bag(capsys, "repair", str(source), str(target))
        assert code == 2 and reason in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "missing").exists()


# ----- 13: render: output format; coordinates that cannot be drawn -------------------------
def test_render_needs_a_png_name(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_em_bag(capsys, "render", str(_mcap(tmp_path / "x.mcap")),
                              "--out", str(tmp_path / "r.xyz"))
    assert code == 2 and "PNG" in err


def test_far_out_and_non_finite_points_are_left_out(tmp_path: Path) -> None:
    # Five poses of a corrupt recording's ground truth, which overflowed Agg.
    path = np.array([[12.1185392, 13.8400749, -2.1], [12.0107567, 13.6716025, -2.1],
                     [-3.26506621e304, 131072.0, -2.1], [11.7956726, 13.3343510, -2.1],
                     [11.6869779, np.nan, -2.1]])
    layers = TeamMapLayers(width_m=40.0, height_m=40.0, cell_size_m=2.0,
                           explored=np.zeros((20, 20), dtype=bool),
                           true_landmarks=np.array([[np.inf, 1.0]]), landmark_radius_m=1.0,
                           true_paths={0: path})
    drawable, left_out = drawable_layers(layers)
    assert left_out == 3 and len(drawable.true_paths[0]) == 3
    assert render_team_map(layers, tmp_path / "map.png").stat().st_size > 0


# ----- 14 to 16 and 23: em-replay's checks before playing ----------------------------------
@pytest.mark.parametrize("type_name", ["", "a", "std_msgs/msg/../String", "rclpy/msg/__init__"])
def test_replay_refuses_malformed_type_names(tmp_path: Path, type_name: str) -> None:
    info = scan_bag(_mcap(tmp_path / "typ.mcap", type_name=type_name))
    with pytest.raises(BagError, match="invalid interface type name"):
        replay.check_playable(info, replay.parse_options(["x.mcap"]).selection)


@pytest.mark.parametrize("type_name", ["antigravity/msg/Flight", "os/path/join",
                                       "rclpy/msg/Node"])
def test_replay_imports_nothing_a_recording_names_that_is_no_installed_message(
        tmp_path: Path, type_name: str) -> None:
    """A schema name is imported as ``pkg.msg``: one naming another Python module would run
    it (``antigravity`` opens a web browser). Only a message the ament index defines is
    imported."""
    info = scan_bag(_mcap(tmp_path / "typ.mcap", type_name=type_name))
    with pytest.raises(BagError, match="which is not installed"):
        replay.check_playable(info, replay.parse_options(["x.mcap"]).selection)
    assert "antigravity" not in sys.modules


@pytest.mark.parametrize("option", [
    ["--start-offset", "nan"], ["--start-offset", "inf"], ["--start-offset", "1e300"],
    ["--rate", "1e-300"], ["--rate", "nan"], ["--rate", "1e300"], ["--clock-hz", "nan"],
    ["--clock-hz", "1e-300"], ["--delay", "inf"]])
def test_replay_refuses_unusable_numbers(option: list[str]) -> None:
    with pytest.raises(SystemExit):
        replay.parse_options(["x.mcap", *option])


@pytest.mark.parametrize("option", [
    ["--remap", "/chatter:=/bad topic"], ["--remap", "/chatter:=/a//b"],
    ["--queue-depth", "99999999999999999999"]])
def test_replay_refuses_bad_names_and_depths(option: list[str]) -> None:
    with pytest.raises(SystemExit):
        replay.parse_options(["x.mcap", *option])


def _chatter_bag(path: Path) -> Path:
    with BagWriter(path) as writer:
        channel = writer.add_topic("/chatter", build_message_definition("std_msgs/msg/String"))
        writer.write(channel, 1_000_000_000, STRING_A)
        writer.write(channel, 2_000_000_000, STRING_A)
        other = writer.add_topic("/other", build_message_definition("rosgraph_msgs/msg/Clock"))
        writer.write(other, 1_500_000_000, bytes(12))
    return path


@pytest.mark.parametrize("args, phrase", [
    (["--remap", "/chatter:=/clock"], "two types"),
    (["--remap", "/chatter:=/other"], "two types"),
    (["--exclude", ".*"], "no topic of the recording is selected"),
    (["--topics", "/nothing"], "no topic of the recording is selected"),
    (["--loop", "--start-offset", "100"], "no messages from 100 s"),
    (["--topics", "/other", "--start-offset", "0.6"], "no messages from 0.6 s")])
def test_replay_refuses_what_cannot_play(tmp_path: Path, args: list[str], phrase: str) -> None:
    path = _chatter_bag(tmp_path / "chatter.mcap")
    options = replay.parse_options([str(path), *args])
    info = scan_bag(path)
    with pytest.raises(BagError, match=phrase):
        replay.check_playback(info, replay.check_playable(info, options.selection), options)


def test_replay_accepts_a_playable_selection(tmp_path: Path) -> None:
    path = _chatter_bag(tmp_path / "chatter.mcap")
    options = replay.parse_options([str(path), "--start-offset", "0.9", "--remap",
                                    "/chatter:=/talk"])
    info = scan_bag(path)
    replay.check_playback(info, replay.check_playable(info, options.selection), options)
