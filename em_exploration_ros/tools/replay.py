"""em-replay: publish a recording (bag directory or .mcap file) with its timing and QoS.

Messages go out in file order (the recorder writes them in order of receipt) as the raw CDR
bytes that were recorded, each when its log time comes due: wall time since the start times
``--rate`` equals log time since the start (``--rate 0``: as fast as possible). Each topic's
publisher offers the QoS its recorded publishers offered (rosbag2's rule: their common
profile, else reliable/volatile) with a keep-last queue of ``--queue-depth``. Unless the
played topics include ``/clock``, the replay publishes ``/clock`` from the log time (before
each message and at ``--clock-hz`` while waiting), so ``use_sim_time`` nodes follow the
recording. Ctrl-C stops cleanly. A selection with nothing to play (no topic, or no message
from the start offset on) and remaps that would put two types on one topic are refused.

    em-replay BAG [--rate F] [--start-offset S] [--loop] [--topics T ...] [--regex RE]
              [--exclude RE] [--remap OLD:=NEW ...] [--delay S] [--wait-for-subscribers S]
              [--clock-hz HZ] [--no-clock] [--queue-depth N]
              [--ros-args ...]
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import rclpy
from builtin_interfaces.msg import Time
from rclpy.duration import Duration
from rclpy.exceptions import InvalidTopicNameException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.validate_full_topic_name import validate_full_topic_name
from rosgraph_msgs.msg import Clock

from em_exploration_ros.bag_format.bag_reader import (BagError, BagInfo, BagScanner, SchemaInfo,
                                                      scan_bag)
from em_exploration_ros.bag_format.interface_index import InterfaceNameError
from em_exploration_ros.bag_format.mcap_ros2_schema import (DefinitionNotFoundError,
                                                            build_message_definition,
                                                            same_layout)
from em_exploration_ros.bag_format.qos_yaml import QosFormatError, QosProfile, offer_for_playback
from em_exploration_ros.bag_format.topic_selection import TopicSelection
from em_exploration_ros.nodes.node_main import first_node, interrupt_shuts_down
from em_exploration_ros.nodes.participant_id import own_participant_id
from em_exploration_ros.tools.bag_ros import (
    MessageTypeError, add_topic_expression_arguments, cli_args, import_message_class,
    number_type, qos_to_rclpy)
from em_exploration_ros.tools.cli_parser import CliParser

EXIT_BAD_INPUT = 2
CLOCK_TOPIC = "/clock"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
_NS_PER_S = 1_000_000_000
#: Longest sleep between two checks for Ctrl-C [s].
_MAX_SLEEP_S = 0.05
#: How long the end of playback waits for reliable subscribers to acknowledge [s].
_ACK_TIMEOUT_S = 2.0
#: Bounds of the numeric options (rate factor, start offset [s], /clock rate [Hz]): beyond
#: them the wall and log times computed from them overflow.
RATE_RANGE = (1e-6, 1e6)
MAX_START_OFFSET_S = 1e10
CLOCK_HZ_RANGE = (1e-3, 1e6)
#: Largest keep-last depth of a publisher (rmw takes a size_t; DDS may preallocate it).
MAX_QUEUE_DEPTH = 1_000_000


@dataclass(frozen=True)
class ReplayOptions:
    """Command-line options of em-replay (times in seconds)."""

    path: Path
    rate: float
    start_offset_s: float
    loop: bool
    selection: TopicSelection
    remaps: dict[str, str]
    delay_s: float
    wait_for_subscribers_s: float
    clock_hz: float
    publish_clock: bool
    queue_depth: int


@dataclass(frozen=True)
class PlaybackStats:
    """One pass over the recording: messages published, wall time taken, log time covered."""

    messages: int
    wall_s: float
    span_s: float


def _remap(text: str) -> tuple[str, str]:
    old, separator, new = text.partition(":=")
    if not separator or not old.startswith("/") or not new.startswith("/"):
        raise argparse.ArgumentTypeError(f"expected /OLD:=/NEW, got {text!r}")
    try:
        validate_full_topic_name(new)
    except InvalidTopicNameException as error:
        reason = str(error).splitlines()[0].rstrip(":")
        raise argparse.ArgumentTypeError(f"{reason}: {new!r}") from None
    return old, new


def parse_options(args: list[str]) -> ReplayOptions:
    """Parse em-replay arguments (ROS arguments removed); exits with status 2 on bad ones."""
    parser = CliParser(
        prog="em-replay", description="Publish an MCAP recording with its original timing.")
    parser.add_argument("file", type=Path,
                        help="the recording: a bag directory or an .mcap file")
    parser.add_argument("--rate", type=number_type(float, allow_zero=True, low=RATE_RANGE[0],
                                                   high=RATE_RANGE[1]), default=1.0,
                        help="playback speed factor; 0 = as fast as possible (default: 1)")
    parser.add_argument("--start-offset", default=0.0,
                        type=number_type(float, allow_zero=True, high=MAX_START_OFFSET_S),
                        metavar="S", help="skip the first S seconds of the recording")
    parser.add_argument("--loop", action="store_true", help="play again and again")
    parser.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                        help="play only these topics (default: all)")
    add_topic_expression_arguments(parser, "play",
                                   "also play topics matching this regular expression")
    parser.add_argument("--remap", nargs="+", type=_remap, default=[], metavar="OLD:=NEW",
                        help="publish topic OLD under the name NEW")
    parser.add_argument("--delay", type=number_type(float, allow_zero=True), default=0.5,
                        metavar="S", help="wait S seconds for discovery before playing "
                        "(default: 0.5)")
    parser.add_argument("--wait-for-subscribers", type=number_type(float, allow_zero=True),
                        default=0.0, metavar="S", help="after the delay, wait up to S seconds "
                        "until every played topic has a subscriber (default: 0, do not wait)")
    parser.add_argument("--clock-hz", type=number_type(float, low=CLOCK_HZ_RANGE[0],
                                                       high=CLOCK_HZ_RANGE[1]),
                        default=50.0, metavar="HZ",
                        help="rate of /clock messages while waiting (default: 50)")
    parser.add_argument("--no-clock", action="store_true",
                        help="do not publish /clock when the recording has none")
    parser.add_argument("--queue-depth", type=number_type(int, high=MAX_QUEUE_DEPTH),
                        default=1000, metavar="N",
                        help="keep-last depth of each publisher (default: 1000)")
    options = parser.parse_args(args)
    selection = TopicSelection(frozenset(options.topics), options.regex, options.exclude)
    remaps = dict(options.remap)
    if len(set(remaps.values())) != len(remaps):
        parser.error("--remap: two topics remapped to the same name")
    return ReplayOptions(
        path=options.file, rate=options.rate, start_offset_s=options.start_offset,
        loop=options.loop, selection=selection, remaps=remaps, delay_s=options.delay,
        wait_for_subscribers_s=options.wait_for_subscribers,
        clock_hz=options.clock_hz, publish_clock=not options.no_clock,
        queue_depth=options.queue_depth)


@dataclass(frozen=True)
class PlayableTopic:
    """A recorded channel that can be published: its message class and recorded QoS offers."""

    message_class: type
    offered_qos: tuple[QosProfile, ...]


def check_playable(info: BagInfo, selection: TopicSelection) -> dict[int, PlayableTopic]:
    """The selected channels by id; raises BagError if one of them cannot be played."""
    playable = {}
    for channel in info.channels.values():
        if not selection.matches(channel.topic):
            continue
        if channel.message_encoding != "cdr":
            raise BagError(f"{info.path}: topic {channel.topic} has message encoding "
                           f"{channel.message_encoding!r}, not cdr")
        if channel.schema_id not in info.schemas:
            raise BagError(f"{info.path}: topic {channel.topic} has no schema")
        schema = info.schema_of(channel)
        type_name = schema.name
        try:
            playable[channel.id] = PlayableTopic(import_message_class(type_name),
                                                 tuple(channel.offered_qos))
        except MessageTypeError:
            raise BagError(f"{info.path}: topic {channel.topic} has type {type_name}, which is "
                           "not installed (exclude it with --exclude)") from None
        except InterfaceNameError as error:
            raise BagError(f"{info.path}: topic {channel.topic}: {error} (exclude it with "
                           "--exclude)") from None
        except QosFormatError as error:
            raise BagError(f"{info.path}: topic {channel.topic}: bad offered_qos_profiles: "
                           f"{error}") from None
        if not recorded_as_installed(schema):
            raise BagError(f"{info.path}: topic {channel.topic} was recorded with another "
                           f"definition of {type_name} than the installed one (made before "
                           "the message changed?): playing it would publish misread messages; "
                           "exclude it with --exclude, or replay with the version that "
                           "recorded it")
    return playable


def playback_start_ns(info: BagInfo, options: ReplayOptions) -> int:
    """Log time [ns] from which the replay plays: the first message's plus the offset."""
    return (info.first_log_ns or 0) + int(options.start_offset_s * _NS_PER_S)


def publishes_own_clock(info: BagInfo, topics: dict[int, PlayableTopic],
                        options: ReplayOptions) -> bool:
    """True when the replay publishes /clock itself (asked to, and /clock is not played)."""
    return options.publish_clock and not any(
        info.channels[c].topic == CLOCK_TOPIC for c in topics)


def check_playback(info: BagInfo, topics: dict[int, PlayableTopic],
                   options: ReplayOptions) -> None:
    """Raise BagError if the selected topics have nothing to play from the start offset, or
    if remapping puts two types on one published topic (rmw refuses the second publisher)."""
    if not topics:
        raise BagError(f"{info.path}: no topic of the recording is selected")
    start = playback_start_ns(info, options)
    if all(info.channel_last_log_ns.get(c, start - 1) < start for c in topics):
        raise BagError(f"{info.path}: the selected topics have no messages from "
                       f"{options.start_offset_s:g} s into the recording on")
    types = {CLOCK_TOPIC: CLOCK_TYPE} if publishes_own_clock(info, topics, options) else {}
    for channel_id in topics:
        channel = info.channels[channel_id]
        name = options.remaps.get(channel.topic, channel.topic)
        type_name = info.schema_of(channel).name
        if types.setdefault(name, type_name) != type_name:
            raise BagError(f"{info.path}: --remap would publish {name} with two types, "
                           f"{types[name]} and {type_name}")


def recorded_as_installed(schema: SchemaInfo) -> bool:
    """True when a recorded schema has the installed definition's layout, or when the
    installed definition is not available to compare (the type's class alone is)."""
    try:
        installed = build_message_definition(schema.name)
    except DefinitionNotFoundError:
        return True
    return same_layout(schema.data.decode("utf-8", errors="replace"), schema.encoding, installed)


def _clock_message(ns: int) -> Clock:
    return Clock(clock=Time(sec=ns // _NS_PER_S, nanosec=ns % _NS_PER_S))


def _publish(publisher: Publisher, message: object) -> bool:
    """Publish; False if Ctrl-C shut the context down since the last ``rclpy.ok()`` check."""
    try:
        publisher.publish(message)
    except rclpy_implementation.RCLError:
        if rclpy.ok():
            raise
        return False
    return True


class Replayer(Node):
    """Publishers for the played topics and the timed playback loop."""

    def __init__(self, info: BagInfo, topics: dict[int, PlayableTopic],
                 options: ReplayOptions) -> None:
        # No /rosout of its own: a replayed recording may carry /rosout, and the last log line
        # comes after Ctrl-C has shut the context down.
        super().__init__("em_replay", enable_rosout=False)
        self._info = info
        self._options = options
        self._topic_publishers = {}
        for channel_id, topic in topics.items():
            name = info.channels[channel_id].topic
            qos = offer_for_playback(topic.offered_qos, options.queue_depth)
            self._topic_publishers[channel_id] = self.create_publisher(
                topic.message_class, options.remaps.get(name, name), qos_to_rclpy(qos))
        self._clock_publisher = None
        if publishes_own_clock(info, topics, options):
            self._clock_publisher = self.create_publisher(
                Clock, CLOCK_TOPIC, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self._clock_stamp_ns = -1

    def _publish_clock(self, ns: int) -> bool:
        """Publish /clock at ``ns`` if it advanced; False if the context was shut down."""
        if self._clock_publisher is None or ns <= self._clock_stamp_ns:
            return True
        self._clock_stamp_ns = ns
        return _publish(self._clock_publisher, _clock_message(ns))

    def _wait_until(self, due_wall_ns: int, start_log_ns: int, start_wall_ns: int) -> bool:
        """Sleep until ``due_wall_ns`` (monotonic), ticking /clock; False if shut down."""
        tick_ns = int(_NS_PER_S / self._options.clock_hz)
        while rclpy.ok():
            now = time.monotonic_ns()
            if now >= due_wall_ns:
                return True
            if not self._publish_clock(
                    start_log_ns + int((now - start_wall_ns) * self._options.rate)):
                return False
            time.sleep(min(due_wall_ns - now, tick_ns, int(_MAX_SLEEP_S * _NS_PER_S)) / _NS_PER_S)
        return False

    def play_once(self) -> PlaybackStats:
        """Publish the recording once from the start offset; stops early on shutdown."""
        rate = self._options.rate
        start_log_ns = playback_start_ns(self._info, self._options)
        start_wall_ns = time.monotonic_ns()
        self._clock_stamp_ns = -1
        published = 0
        last_log_ns = start_log_ns
        for channel, message in BagScanner(self._info.path).messages():
            publisher = self._topic_publishers.get(channel.id)
            if publisher is None or message.log_time_ns < start_log_ns:
                continue
            if rate > 0:
                due = start_wall_ns + int((message.log_time_ns - start_log_ns) / rate)
                if not self._wait_until(due, start_log_ns, start_wall_ns):
                    break
            elif not rclpy.ok():
                break
            if not (self._publish_clock(message.log_time_ns)
                    and _publish(publisher, message.data)):
                break
            published += 1
            last_log_ns = message.log_time_ns
        return PlaybackStats(published, (time.monotonic_ns() - start_wall_ns) / _NS_PER_S,
                             (last_log_ns - start_log_ns) / _NS_PER_S)

    def _all_publishers(self) -> list[Publisher]:
        extra = [] if self._clock_publisher is None else [self._clock_publisher]
        return [*self._topic_publishers.values(), *extra]

    def _unmatched_topics(self) -> list[str]:
        return [p.topic_name for p in self._all_publishers() if p.get_subscription_count() == 0]

    def _sleep_while(self, condition: Callable[[], bool], duration_s: float) -> None:
        deadline = time.monotonic() + duration_s
        while rclpy.ok() and time.monotonic() < deadline and condition():
            time.sleep(_MAX_SLEEP_S)

    def play(self) -> None:
        """Wait for discovery, play (looping if asked), then let reliable readers catch up."""
        self._sleep_while(lambda: True, self._options.delay_s)
        if self._options.wait_for_subscribers_s > 0:
            self._sleep_while(lambda: bool(self._unmatched_topics()),
                              self._options.wait_for_subscribers_s)
            if self._unmatched_topics():
                self.get_logger().warning(
                    f"playing without subscribers on {self._unmatched_topics()}")
        while rclpy.ok():
            stats = self.play_once()
            speed = f"rate {self._options.rate:g}" if self._options.rate > 0 else "rate 0 (max)"
            self.get_logger().info(
                f"played {stats.messages} messages in {stats.wall_s:.3f} s "
                f"(recording span {stats.span_s:.3f} s, {speed})")
            if not self._options.loop:
                break
        for publisher in self._all_publishers():
            if rclpy.ok():
                publisher.wait_for_all_acked(Duration(seconds=_ACK_TIMEOUT_S))


def main(argv: list[str] | None = None) -> None:
    """Entry point of em-replay."""
    full_args, tool_args = cli_args(argv)
    options = parse_options(tool_args)
    try:
        info = scan_bag(options.path)
        topics = check_playable(info, options.selection)
        check_playback(info, topics, options)
    except BagError as error:
        sys.stderr.write(f"em-replay: {error}\n")
        sys.exit(EXIT_BAD_INPUT)
    with interrupt_shuts_down() as interrupted, own_participant_id() as participant:
        rclpy.init(args=full_args)
        replayer = None
        try:
            if not interrupted():  # a Ctrl-C before rclpy.init plays nothing
                replayer = first_node(lambda: Replayer(info, topics, options), participant)
                replayer.play()
        except ExternalShutdownException:
            pass
        finally:
            if replayer is not None:
                replayer.destroy_node()
            rclpy.try_shutdown()


if __name__ == "__main__":
    main()
