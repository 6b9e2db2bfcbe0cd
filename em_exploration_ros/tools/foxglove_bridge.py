"""em-foxglove: a live view of a running team in the Foxglove app, without a ROS 2 install.

A ROS 2 node that forwards the topics a viewer needs to a Foxglove WebSocket server (the
``foxglove-sdk`` package): every robot's virtual map, estimated path, markers, target and
landmarks, the world's markers and landmarks, the mission anchor, the metrics, /tf and
/tf_static. Each topic becomes one channel with message encoding ``cdr`` and the ``ros2msg``
schema that recordings carry (bag_format/mcap_ros2_schema.py), so the app decodes the raw
ROS 2 bytes as it does from a bag; the app's 3D panel assembles the frames from /tf.

- Topics are found by polling the ROS graph, as em-record does; ``--regex``/``--exclude``
  change the selection (default ``VIEW_TOPICS``).
- The bridge never slows a publisher: latched state is taken reliable and transient local,
  every stream (/tf, the metrics) best effort (``viewer_qos``).
- A Foxglove client that connects late still gets the state: the last message of every
  transient-local topic (maps, paths, markers, /tf_static) is sent to each client when it
  subscribes to that channel.
- Time is the ROS clock of the node (``use_sim_time:=true`` follows /clock), broadcast to
  the clients (Foxglove's server time) and used as each message's log time.

It is a viewer: no robot, world or evaluator depends on it, and it can start and stop at
any time. Listens on 127.0.0.1 unless ``--host`` says otherwise.

    em-foxglove [--port 8765] [--host 127.0.0.1] [--regex RE] [--exclude RE] [--ros-args ...]
"""
from __future__ import annotations

import sys
import threading
from dataclasses import dataclass

import foxglove
from foxglove.websocket import Capability, ChannelView, Client
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.topic_endpoint_info import TopicEndpointInfo

from em_exploration_ros.bag_format.qos_yaml import (
    KEEP_LAST, RELIABLE, TRANSIENT_LOCAL, QosProfile, request_for_offers)
from em_exploration_ros.bag_format.topic_selection import TopicSelection
from em_exploration_ros.nodes.input_guard import InputGuard
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.tools.bag_ros import (
    MessageTypeError, add_topic_expression_arguments, cli_args, message_type_support,
    new_selected_topics, number_type, other_types_of_taken_topics, qos_from_rclpy, qos_to_rclpy)
from em_exploration_ros.tools.cli_parser import CliParser

#: What a viewer of the team needs (the default selection).
VIEW_TOPICS = (r"^/(tf|tf_static|mission/anchor_pose|evaluation/metrics|world/(markers|landmarks)|"
               r"robot_\d+/(virtual_map|estimated_path|markers|target|landmarks))$")
DEFAULT_PORT = 8765
DEFAULT_HOST = "127.0.0.1"
#: Keep-last depth of the bridge's subscriptions.
QUEUE_DEPTH = 100
#: Messages the server holds for each client that reads slower than the team publishes;
#: beyond them the oldest is dropped (the SDK's default, 1024, let one stalled client
#: hold over a gigabyte of 1 MB maps).
MESSAGE_BACKLOG = 32
#: Wall period of the graph poll and of the server-time broadcast [s].
POLL_PERIOD_S = 0.5
TIME_PERIOD_S = 0.1


@dataclass(frozen=True)
class BridgeOptions:
    """Command-line options of em-foxglove."""

    host: str
    port: int
    selection: TopicSelection


def parse_options(args: list[str]) -> BridgeOptions:
    """Parse em-foxglove arguments (ROS arguments removed); exits with status 2 on bad ones."""
    parser = CliParser(
        prog="em-foxglove", description="Serve a running team to the Foxglove app (WebSocket).")
    parser.add_argument("--port", type=number_type(int, allow_zero=True), default=DEFAULT_PORT,
                        help=f"TCP port (default: {DEFAULT_PORT}; 0: any free port)")
    parser.add_argument("--host", default=DEFAULT_HOST,
                        help=f"address to listen on (default: {DEFAULT_HOST}, this machine only)")
    add_topic_expression_arguments(
        parser, "serve", "serve the topics matching this regular expression (default: the "
        "maps, paths, markers, TF and metrics of the team)", VIEW_TOPICS)
    options = parser.parse_args(args)
    if options.port > 65535:
        parser.error(f"--port must be at most 65535, got {options.port}")
    return BridgeOptions(options.host, options.port,
                         TopicSelection(include=options.regex, exclude=options.exclude))


def viewer_qos(offers: tuple[QosProfile, ...]) -> QosProfile:
    """Subscription QoS of the bridge for a topic with these publisher offers.

    Latched state (every publisher reliable and transient local, e.g. maps, paths, markers,
    /tf_static) is taken reliable and transient local, so the last value arrives even if it
    was published before the bridge started; such publishers keep only their last value, so
    a slow bridge cannot hold them back. Every stream is taken best effort: a reliable reader
    of a keep-all writer (the metrics, team data) would make the writer keep every sample the
    reader has not acknowledged, and discovery does not tell a writer's history.
    """
    request = request_for_offers(offers, QUEUE_DEPTH)
    if request.reliability == RELIABLE and request.durability == TRANSIENT_LOCAL:
        return request
    return QosProfile(history=KEEP_LAST, depth=QUEUE_DEPTH, reliability="best_effort",
                      durability=request.durability)


class LatestMessages:
    """The last message of each transient-local channel, to give a client that subscribes
    late; thread-safe (the server calls back from its own thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latest: dict[int, tuple[bytes, int]] = {}

    def keep(self, channel_id: int, data: bytes, log_time_ns: int) -> None:
        with self._lock:
            self._latest[channel_id] = (data, log_time_ns)

    def get(self, channel_id: int) -> tuple[bytes, int] | None:
        with self._lock:
            return self._latest.get(channel_id)


class _ReplayLatestOnSubscribe(foxglove.ServerListener):
    """Server listener: a client subscribing to a latched channel gets its last message."""

    def __init__(self, channels: dict[int, foxglove.Channel], latest: LatestMessages) -> None:
        self._channels = channels
        self._latest = latest

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        kept = self._latest.get(channel.id)
        target = self._channels.get(channel.id)
        if kept is not None and target is not None:
            data, log_time_ns = kept
            target.log(data, log_time=log_time_ns, sink_id=client.id)


class FoxgloveBridge(Node):
    """Subscribes to the selected topics as they appear and logs them to the server."""

    def __init__(self, options: BridgeOptions) -> None:
        super().__init__("em_foxglove", enable_rosout=False)
        # Its time follows /clock under use_sim_time: one hostile sample must not end it.
        install_validated_clock(self, InputGuard(self))
        self._options = options
        self._channels: dict[int, foxglove.Channel] = {}
        self._served: dict[str, str] = {}  # topic -> the type it is served as
        self._skipped: set[str] = set()
        self._other_types: set[tuple[str, str]] = set()
        self._latest = LatestMessages()
        try:
            self.server = foxglove.start_server(
                name="em_exploration_ros", host=options.host, port=options.port,
                capabilities=[Capability.Time],
                server_listener=_ReplayLatestOnSubscribe(self._channels, self._latest),
                message_backlog_size=MESSAGE_BACKLOG)
        except RuntimeError as error:  # port taken, address not of this machine
            raise ValueError(f"cannot serve on {options.host}:{options.port}: {error}") from None
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(POLL_PERIOD_S, self._discover, clock=steady)
        self.create_timer(TIME_PERIOD_S, self._broadcast_time, clock=steady)
        self.get_logger().info(f"serving ws://{options.host}:{self.server.port} "
                               "(Foxglove: Open connection > Foxglove WebSocket)")
        self._discover()

    def _broadcast_time(self) -> None:
        now = self.get_clock().now().nanoseconds
        if now > 0:
            self.server.broadcast_time(now)

    def _discover(self) -> None:
        known = self._served.keys() | self._skipped
        graph = self.get_topic_names_and_types()
        for topic, types, publishers in new_selected_topics(self, graph, self._options.selection,
                                                            known):
            self._serve(topic, types[0], publishers)
        for line in other_types_of_taken_topics(graph, self._served, self._other_types):
            self.get_logger().warning(line)

    def _serve(self, topic: str, type_name: str, publishers: list[TopicEndpointInfo]) -> None:
        try:
            message_class, definition = message_type_support(type_name)
        except MessageTypeError as error:
            self._skipped.add(topic)
            self.get_logger().warning(f"not serving {topic}: {error}")
            return
        channel = foxglove.Channel(topic, message_encoding="cdr", schema=foxglove.Schema(
            name=type_name, encoding=definition.encoding, data=definition.text.encode("utf-8")))
        channel_id = channel.id()
        self._channels[channel_id] = channel
        qos = viewer_qos(tuple(qos_from_rclpy(p.qos_profile) for p in publishers))
        latched = qos.durability == TRANSIENT_LOCAL
        clock = self.get_clock()
        latest = self._latest

        def forward(data: bytes) -> None:
            stamp = clock.now().nanoseconds
            if latched:
                latest.keep(channel_id, data, stamp)
            channel.log(data, log_time=stamp)

        self.create_subscription(message_class, topic, forward, qos_to_rclpy(qos), raw=True)
        self._served[topic] = type_name
        self.get_logger().info(f"serving {topic} [{type_name}] ({qos.reliability}, "
                               f"{qos.durability})")

    def stop(self) -> None:
        """Stop the WebSocket server."""
        self.server.stop()


def _stop(bridge: FoxgloveBridge) -> int:
    bridge.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of em-foxglove; returns the exit code (2: bad arguments, or the server
    cannot listen on the address and port)."""
    full_args, tool_args = cli_args(argv)
    options = parse_options(tool_args)
    return run_node(lambda: FoxgloveBridge(options), "em_foxglove", full_args, _stop)


if __name__ == "__main__":
    sys.exit(main())
