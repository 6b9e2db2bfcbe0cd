"""em-bag: inspect and repair recordings (no ROS needed).

A recording BAG is a bag directory (metadata.yaml and one .mcap file, as em-record and
``ros2 bag record -s mcap`` write it) or a single .mcap file.

    em-bag info BAG         topics, types, counts, duration, size, compression, start/end
    em-bag repair IN OUT    rewrite the readable chunks of a damaged recording (e.g. one whose
                            recorder was killed) as a complete, valid one: a bag directory
                            OUT for a directory IN, an .mcap file OUT for a file IN (OUT
                            must not exist; its folder must)
    em-bag render BAG --out PNG [--animate GIF]
                            draw the final team map of a recorded run (tools/bag_render.py;
                            needs the ROS message packages, not a ROS graph), and with
                            --animate the run as an animation (.gif; .mp4 with ffmpeg)

A recording that cannot be read gives a one-line error and exit status 2.
"""
from __future__ import annotations

import argparse
import io
import math
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from em_exploration_ros.bag_format.bag_directory import BagDirectoryWriter
from em_exploration_ros.bag_format.bag_reader import BagError, BagInfo, BagScanner, scan_bag
from em_exploration_ros.bag_format.bag_writer import BagWriter, new_file
from em_exploration_ros.bag_format.mcap_ros2_schema import MessageDefinition
from em_exploration_ros.bag_format.qos_yaml import QosFormatError
from em_exploration_ros.bag_format.rosbag2_metadata import MetadataFormatError
from em_exploration_ros.tools.cli_parser import CliParser

EXIT_BAD_INPUT = 2
_NS_PER_S = 1_000_000_000


def _size(num_bytes: int) -> str:
    if num_bytes < 1024:
        return f"{num_bytes} B"
    exponent = min(int(math.log(num_bytes, 1024)), 3)
    return f"{num_bytes / 1024 ** exponent:.1f} {('KiB', 'MiB', 'GiB')[exponent - 1]}"


def _time(ns: int | None) -> str:
    if ns is None:
        return "-"
    seconds, rest = divmod(ns, _NS_PER_S)
    stamp = time.strftime("%b %d %Y %H:%M:%S", time.gmtime(seconds))
    return f"{stamp}.{rest:09d} UTC ({seconds}.{rest:09d})"


def format_info(info: BagInfo) -> str:
    """The ``em-bag info`` report of a scanned recording (layout of ``ros2 bag info``)."""
    try:
        metadata = info.rosbag2_metadata()
    except MetadataFormatError:
        metadata = None
    duration_ns = 0 if info.first_log_ns is None else info.last_log_ns - info.first_log_ns
    compressions = ", ".join(sorted(info.compressions)) or "-"
    lines = [
        f"Files:             {info.path.name}",
        f"Bag size:          {_size(info.file_size)} ({info.file_size} bytes)",
        f"Storage id:        mcap (profile {info.profile or '-'}, library {info.library or '-'})",
        f"ROS distro:        {metadata.ros_distro if metadata else '- (no rosbag2 metadata)'}",
        f"Duration:          {duration_ns / _NS_PER_S:.9f}s",
        f"Start:             {_time(info.first_log_ns)}",
        f"End:               {_time(info.last_log_ns)}",
        f"Messages:          {info.message_count}",
        f"Chunks:            {info.chunk_count} (compression: {compressions}; "
        f"CRC verified: {info.crc_checked_chunks})",
    ]
    channels = sorted(info.channels.values(), key=lambda c: c.topic)
    for index, channel in enumerate(channels):
        schema = info.schemas.get(channel.schema_id)
        label = "Topic information: " if index == 0 else " " * 19
        lines.append(f"{label}Topic: {channel.topic} | "
                     f"Type: {schema.name if schema else '(no schema)'} | "
                     f"Count: {info.channel_message_counts.get(channel.id, 0)} | "
                     f"Serialization Format: {channel.message_encoding}")
    if not channels:
        lines.append("Topic information: (none)")
    return "\n".join(lines)


@dataclass(frozen=True)
class RepairResult:
    """What a repair recovered from its input."""

    messages: int
    topics: int
    input_complete: bool
    problem: str | None
    dropped_bytes: int


def _check_new_output(target: Path) -> None:
    """Raise FileExistsError if ``target`` exists, BagError if its folder does not."""
    if target.exists() or target.is_symlink():
        raise FileExistsError(target)
    if not target.parent.is_dir():
        what = "is not a folder" if target.parent.exists() else "does not exist"
        raise BagError(f"{target}: the output folder {target.parent} {what}")


def repair(source: Path, target: Path,
           create: Callable[[Path], io.FileIO] = new_file) -> RepairResult:
    """Rewrite the readable records of ``source`` as a complete recording at ``target`` (a
    new bag directory if ``source`` is one, else a new .mcap file); ``create`` makes the
    output's .mcap file (``BagWriter``'s).

    Keeps every message of every chunk that is whole and passes its CRC, with the schemas
    and channels (QoS, type hash) they use; the first damaged record ends the recovery.
    The output gets a fresh summary and rosbag2 metadata record. It is written in a hidden
    folder beside ``target`` and moved to ``target`` when complete, so a failed or killed
    repair leaves no partial ``target``. Raises BagError if ``source`` is not a recording or
    the folder of ``target`` does not exist, and FileExistsError if ``target`` exists.
    """
    if source.resolve() == target.resolve():
        raise BagError(f"{target}: repair must write to a different file than it reads")
    _check_new_output(target)
    scanner = BagScanner(source, tolerant=True)
    try:
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial",
                                        dir=target.parent))
    except OSError as error:
        raise BagError(f"{target}: cannot write: {error.strerror}") from None
    try:
        staged = staging / target.name
        writer = (BagDirectoryWriter(staged, create=create) if source.is_dir()
                  else BagWriter(staged, create=create))
        try:
            topics = _copy_readable(scanner, writer)
        finally:
            writer.close()
        _check_new_output(target)
        staged.rename(target)
    finally:
        shutil.rmtree(staging)
    info = scanner.info
    return RepairResult(messages=writer.message_count, topics=topics,
                        input_complete=info.complete, problem=info.problem,
                        dropped_bytes=info.file_size - info.readable_bytes)


def _copy_readable(scanner: BagScanner, writer: BagWriter) -> int:
    """Write what ``scanner`` can read into ``writer``; returns the number of topics."""
    channel_map: dict[int, int] = {}

    def register(channel_id: int) -> int | None:
        if channel_id not in channel_map:
            channel = scanner.info.channels[channel_id]
            schema = scanner.info.schemas.get(channel.schema_id)
            if schema is None:
                return None
            try:
                offers = tuple(channel.offered_qos)
            except QosFormatError:
                offers = ()
            definition = MessageDefinition(schema.name, schema.encoding,
                                           schema.data.decode("utf-8", errors="replace"))
            channel_map[channel_id] = writer.add_topic(channel.topic, definition, offers,
                                                       channel.type_hash)
        return channel_map[channel_id]

    for channel, message in scanner.messages():
        new_id = register(channel.id)
        if new_id is not None:
            writer.write(new_id, message.log_time_ns, message.data, message.publish_time_ns)
    for channel_id in scanner.info.channels:
        register(channel_id)
    return len(channel_map)


def _info_command(args: argparse.Namespace) -> None:
    sys.stdout.write(format_info(scan_bag(args.file)) + "\n")


def _repair_command(args: argparse.Namespace) -> None:
    try:
        result = repair(args.input, args.output)
    except FileExistsError:
        raise BagError(f"{args.output}: already exists; choose a new output file") from None
    state = ("the input was complete" if result.input_complete else
             f"stopped at: {result.problem}; {result.dropped_bytes} bytes dropped")
    sys.stdout.write(f"recovered {result.messages} messages on {result.topics} topics into "
                     f"{args.output} ({state})\n")


def _render_command(args: argparse.Namespace) -> None:
    # Imported here: the other commands need no ROS message packages.
    from em_exploration_ros.core.evaluation.run_animation import ANIMATION_SUFFIXES
    from em_exploration_ros.tools.bag_render import animate_recording, render_recording
    if args.out.suffix.lower() != ".png":
        raise BagError(f"{args.out}: the picture is written as PNG; name it *.png")
    animation = args.animate
    if animation is not None and animation.suffix.lower() not in ANIMATION_SUFFIXES:
        raise BagError(f"{animation}: the animation is written as "
                       f"{' or '.join(ANIMATION_SUFFIXES)}; name it so")
    if animation is not None and animation.suffix.lower() == ".mp4" and not shutil.which(
            "ffmpeg"):
        raise BagError(f"{animation}: an MP4 needs ffmpeg, which is not installed (use .gif)")
    try:
        team_map = render_recording(args.file, args.out)
    except OSError as error:
        raise BagError(f"{args.out}: cannot write the picture: {error.strerror}") from None
    sys.stdout.write(f"wrote {args.out}: {team_map.describe()}\n")
    if animation is not None:
        try:
            frames = animate_recording(args.file, animation)
        except OSError as error:
            raise BagError(f"{animation}: cannot write the animation: {error.strerror}"
                           ) from None
        sys.stdout.write(f"wrote {animation}: {frames} frames\n")


def main(argv: list[str] | None = None) -> None:
    """Entry point of em-bag."""
    parser = CliParser(
        prog="em-bag", description="Inspect recordings (bag directories or .mcap files).")
    commands = parser.add_subparsers(dest="command", required=True)
    info = commands.add_parser("info", help="summarize a recording")
    info.add_argument("file", type=Path, metavar="BAG")
    info.set_defaults(run=_info_command)
    fix = commands.add_parser("repair", help="recover the readable part of a damaged recording")
    fix.add_argument("input", type=Path)
    fix.add_argument("output", type=Path)
    fix.set_defaults(run=_repair_command)
    draw = commands.add_parser("render", help="draw the final team map of a recorded run")
    draw.add_argument("file", type=Path, metavar="BAG")
    draw.add_argument("--out", type=Path, required=True, metavar="PNG",
                      help="the picture to write (PNG)")
    draw.add_argument("--animate", type=Path, metavar="GIF",
                      help="also draw the run as an animation into this .gif (.mp4 with ffmpeg)")
    draw.set_defaults(run=_render_command)
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        args.run(args)
    except BagError as error:
        hint = "; `em-bag repair IN OUT` recovers its complete chunks" if (
            "truncated" in str(error) and args.command in ("info", "render")) else ""
        sys.stderr.write(f"em-bag: {error}{hint}\n")
        sys.exit(EXIT_BAD_INPUT)


if __name__ == "__main__":
    main()
