"""em-record: record ROS 2 topics into a bag directory as ``ros2 bag record -s mcap`` does.

The output ``-o NAME`` is a new directory holding ``NAME_0.mcap`` and, once the recording is
closed, ``metadata.yaml`` (bag_format/bag_directory.py).

The recorder polls the ROS graph and subscribes to every selected topic as soon as it has a
publisher (topics that appear later are picked up at the next poll). Subscriptions are raw:
the CDR bytes are written exactly as received, stamped with the node's ROS clock (sim time
with ``use_sim_time:=true``) as log and publish time. Each subscription asks for a QoS every
publisher can serve (reliable only if all publishers are, transient-local only if all are),
with a deep keep-last queue. Chunks close at ``--chunk-size`` bytes or every
``--chunk-interval`` seconds, whichever comes first, and go to the OS at once, so a killed
recorder leaves a file whose chunks ``em-bag repair`` recovers. Ctrl-C or SIGTERM writes the
summary, the rosbag2 metadata record and the footer, then metadata.yaml.

Messages published while the recorder listened that never reached it (a best-effort stream
dropped them, or a subscription's queue overflowed while the recorder fell behind) are
counted from the writers' publication sequence numbers (``bag_format/message_losses.py``)
and reported at the next poll and when the bag is closed.

When the OS refuses a write (a full disk), the recorder stops: it frees the space it kept in
the bag directory (``bag_directory.RESERVE_BYTES``), cuts the file back to its last whole
record and ends it there with its summary and footer, writes metadata.yaml of what reached
the file, prints one line naming the file, the error and the messages kept, and exits with
status 3. The bag then opens whole in every reader (what could not be ended is said on a
line of its own; ``em-bag repair`` recovers its complete chunks).

Exit codes: 0 the recording was closed; 2 bad arguments, or the output cannot be created;
3 the bag could not be written (``EXIT_WRITE_FAILED``).

    em-record [-o DIR] [--topics T ...] [--regex RE] [--exclude RE]
              [--compression zstd|lz4|none] [--chunk-size BYTES] [--chunk-interval S]
              [--ros-args ...]
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.topic_endpoint_info import TopicEndpointInfo

from em_exploration_ros.bag_format.bag_directory import BagDirectoryWriter
from em_exploration_ros.bag_format.bag_writer import (COMPRESSIONS, DEFAULT_CHUNK_SIZE,
                                                      BagWriteError)
from em_exploration_ros.bag_format.interface_index import read_type_hash
from em_exploration_ros.bag_format.message_losses import MessageLosses
from em_exploration_ros.bag_format.qos_yaml import request_for_offers
from em_exploration_ros.bag_format.topic_selection import TopicSelection
from em_exploration_ros.nodes import lean_executor
from em_exploration_ros.nodes.input_guard import InputGuard
from em_exploration_ros.nodes.message_info import MessageInfo, publication_sequence
from em_exploration_ros.nodes.node_main import first_node, interrupt_shuts_down
from em_exploration_ros.nodes.participant_id import own_participant_id
from em_exploration_ros.nodes.recorder_presence import RECORDER_NODE_NAME
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.tools.bag_ros import (
    MessageTypeError, add_topic_expression_arguments, cli_args, message_type_support,
    new_selected_topics, number_type, other_types_of_taken_topics, qos_from_rclpy, qos_to_rclpy)
from em_exploration_ros.tools.cli_parser import CliParser

EXIT_USAGE = 2
#: Exit code of a recording the OS refused to write (e.g. a full disk).
EXIT_WRITE_FAILED = 3


@dataclass(frozen=True)
class RecordOptions:
    """Command-line options of em-record (sizes in bytes, periods in seconds)."""

    output: str
    selection: TopicSelection
    compression: str
    chunk_size: int
    chunk_interval_s: float
    poll_interval_s: float
    queue_depth: int


def parse_options(args: list[str]) -> RecordOptions:
    """Parse em-record arguments (ROS arguments removed); exits with status 2 on bad ones."""
    parser = CliParser(
        prog="em-record",
        description="Record ROS 2 topics into a bag directory (rosbag2 format, MCAP storage).",
        epilog="exit codes: 0 recording closed; 2 bad arguments or output not creatable; "
        f"{EXIT_WRITE_FAILED} the bag could not be written (e.g. a full disk)")
    parser.add_argument("-o", "--output", default=None,
                        help="output bag directory (default: em_run_<date>_<time>); must not "
                        "exist")
    parser.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                        help="record these topics (default: all)")
    add_topic_expression_arguments(parser, "record",
                                   "also record topics matching this regular expression")
    parser.add_argument("--compression", choices=sorted(COMPRESSIONS), default="zstd",
                        help="chunk compression (default: zstd)")
    parser.add_argument("--chunk-size", type=number_type(int), default=DEFAULT_CHUNK_SIZE,
                        metavar="BYTES", help="close a chunk at this uncompressed size "
                        f"(default: {DEFAULT_CHUNK_SIZE})")
    parser.add_argument("--chunk-interval", type=number_type(float), default=1.0, metavar="S",
                        help="close the chunk in progress every S seconds (default: 1.0)")
    parser.add_argument("--poll-interval", type=number_type(float), default=0.5, metavar="S",
                        help="look for new topics every S seconds (default: 0.5)")
    parser.add_argument("--queue-depth", type=number_type(int), default=1000, metavar="N",
                        help="keep-last depth of each subscription (default: 1000)")
    options = parser.parse_args(args)
    for topic in options.topics:
        if not topic.startswith("/"):
            parser.error(f"--topics: {topic!r} is not an absolute topic name (starts with /)")
    output = options.output or time.strftime("em_run_%Y%m%d_%H%M%S")
    return RecordOptions(
        output=output,
        selection=TopicSelection(frozenset(options.topics), options.regex, options.exclude),
        compression=options.compression, chunk_size=options.chunk_size,
        chunk_interval_s=options.chunk_interval, poll_interval_s=options.poll_interval,
        queue_depth=options.queue_depth)


class Recorder(Node):
    """Subscribes to the selected topics as they appear and writes what arrives."""

    def __init__(self, writer: BagDirectoryWriter, options: RecordOptions) -> None:
        # No /rosout: the recorder would record its own log, and its last line is written
        # after a signal has already shut the context down.
        super().__init__(RECORDER_NODE_NAME, enable_rosout=False)
        # Its log times follow /clock under use_sim_time: one hostile sample must not end it.
        install_validated_clock(self, InputGuard(self))
        self._writer = writer
        self._options = options
        self._recorded: dict[str, str] = {}
        self._losses: dict[str, tuple[Subscription, MessageLosses]] = {}
        self._skipped: set[str] = set()
        self._other_types: set[tuple[str, str]] = set()
        # Wall-clock timers: with use_sim_time the ROS clock may stand still (no /clock yet).
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(options.poll_interval_s, self._discover, clock=steady)
        self.create_timer(options.chunk_interval_s, self._writer.flush, clock=steady)
        self._discover()
        # Announced from the first turn of the spin: a user (or a test) that reacts to the
        # line finds the recorder spinning, where SIGINT/SIGTERM close the bag cleanly (a
        # signal between rclpy.init and the spin can end the process without it).
        self._announcement = self.create_timer(0.0, self._announce, clock=steady)

    def _announce(self) -> None:
        self._announcement.cancel()
        self.get_logger().info(f"recording to {self._writer.directory} "
                               f"({self._options.compression}, chunks of "
                               f"{self._options.chunk_size} B or "
                               f"{self._options.chunk_interval_s:g} s)")

    def _discover(self) -> None:
        """Subscribe to every selected topic that has publishers and is not recorded yet."""
        known = self._recorded.keys() | self._skipped
        graph = self.get_topic_names_and_types()
        for topic, types, publishers in new_selected_topics(self, graph, self._options.selection,
                                                            known):
            self._subscribe(topic, types, publishers)
        for line in other_types_of_taken_topics(graph, self._recorded, self._other_types):
            self.get_logger().warning(line)
        self._report_losses()

    def _report_losses(self) -> None:
        """One line per topic that lost messages since the last poll."""
        for topic, (subscription, losses) in self._losses.items():
            losses.writers(subscription.get_publisher_count())
            new = losses.unreported()
            if new:
                self.get_logger().warning(
                    f"{topic}: {new} messages published while recording never reached the "
                    f"recorder (dropped on the way, or the recorder fell behind: "
                    f"--queue-depth); {losses.lost} in all")

    def _skip(self, topic: str, reason: str) -> None:
        self._skipped.add(topic)
        self.get_logger().warning(f"not recording {topic}: {reason}")

    def _subscribe(self, topic: str, types: list[str],
                   publishers: list[TopicEndpointInfo]) -> None:
        type_name = types[0]
        if len(types) > 1:
            self.get_logger().warning(f"{topic} has several types {types}; recording {type_name}")
        try:
            message_class, definition = message_type_support(type_name)
        except MessageTypeError as error:
            self._skip(topic, str(error))
            return
        offers = tuple(qos_from_rclpy(p.qos_profile) for p in publishers)
        type_hash = next((str(p.topic_type_hash) for p in publishers
                          if str(p.topic_type_hash).startswith("RIHS")), "")
        channel_id = self._writer.add_topic(topic, definition, offers,
                                            type_hash or read_type_hash(type_name))
        request = request_for_offers(offers, self._options.queue_depth)
        clock = self.get_clock()
        write = self._writer.write

        losses = MessageLosses(len(publishers))

        def on_message(data: bytes, info: MessageInfo) -> None:
            stamp = clock.now().nanoseconds
            write(channel_id, stamp, data, stamp)
            losses.received(publication_sequence(info))

        subscription = self.create_subscription(message_class, topic, on_message,
                                                qos_to_rclpy(request), raw=True)
        self._losses[topic] = (subscription, losses)
        self._recorded[topic] = type_name
        self.get_logger().info(f"recording {topic} [{type_name}] "
                               f"({request.reliability}, {request.durability})")

    def finish(self) -> int:
        """Close the file: summary, rosbag2 metadata and footer; returns the exit code."""
        code = close_bag(self._writer)
        counts = self._writer.topic_counts()
        self.get_logger().info(f"wrote {sum(counts.values())} messages on {len(counts)} topics "
                               f"to {self._writer.directory}")
        lost = {topic: losses.lost for topic, (_, losses) in self._losses.items() if losses.lost}
        if lost:
            self.get_logger().warning(
                f"{sum(lost.values())} messages published while recording never reached the "
                "recorder: " + ", ".join(f"{topic} {count}" for topic, count in lost.items()))
        return code


def close_bag(writer: BagDirectoryWriter) -> int:
    """Close the bag; print one line to stderr for the write that ended it (if any) and one
    for a failure to close it; returns 0 or EXIT_WRITE_FAILED."""
    try:
        writer.close()
        close_error = None
    except BagWriteError as error:
        close_error = error
    failure = writer.failure
    if failure is not None:
        ending = ("the bag is closed whole with them" if close_error is None
                  else "the bag could not be closed")
        sys.stderr.write(f"em-record: {failure}; stopped recording after "
                         f"{writer.message_count} messages; {ending}\n")
    if close_error is not None and close_error is not failure:
        sys.stderr.write(f"em-record: {close_error}\n")
    return EXIT_WRITE_FAILED if failure is not None or close_error is not None else 0


def main(argv: list[str] | None = None) -> None:
    """Entry point of em-record."""
    full_args, tool_args = cli_args(argv)
    options = parse_options(tool_args)
    try:
        writer = BagDirectoryWriter(options.output, compression=options.compression,
                                    chunk_size=options.chunk_size)
    except OSError as error:
        sys.stderr.write(f"em-record: cannot create {options.output}: {error.strerror}\n")
        sys.exit(EXIT_USAGE)
    with interrupt_shuts_down() as interrupted, own_participant_id() as participant:
        rclpy.init(args=full_args)
        recorder = None
        try:
            if not interrupted():  # a Ctrl-C before rclpy.init ends the recording empty
                recorder = first_node(lambda: Recorder(writer, options), participant)
                lean_executor.spin(recorder)
        except (ExternalShutdownException, BagWriteError):
            pass  # a BagWriteError is writer.failure, reported when the bag is closed
        finally:
            if recorder is not None:
                code = recorder.finish()
                recorder.destroy_node()
            else:
                code = close_bag(writer)
            rclpy.try_shutdown()
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
