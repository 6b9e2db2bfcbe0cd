"""em-fuzz: attack a running team with well-formed messages full of extreme values.

The fuzzer reads the ROS graph (``get_topic_names_and_types``,
``get_subscriptions_info_by_topic``) for every topic that one of the system's nodes
(em_world, em_robot, em_evaluator by default) subscribes to, including /clock of nodes
that use the simulation time, and for ``--duration`` seconds publishes on all of them,
round robin, at ``--rate`` messages per second. Topics that appear later are picked up
(the graph is read again every ``REDISCOVER_S``).

Every message but one in ``POOL_SIZE`` is well formed (it deserializes) but carries at
least one extreme value:
NaN, +-inf or +-1e308 in a float, the largest (or a negative) value of an integer field
(ids, steps, sequence numbers, stamps: sec < 0, nanosec >= 1e9), a huge array (10^5
numbers or ``HUGE_MESSAGE_ARRAY`` nested messages), or a wrong frame_id; the other fields
hold small plausible values (numbers 0..3, a frame name of the system), so a /clock
message is negative or goes backwards. The remaining one is such a message cut in half:
bytes that are not the topic's type at all, which the middleware refuses for a typed
subscription and a raw one must refuse itself. Nodes must drop all of it and keep their
result.
Each topic gets ``POOL_SIZE`` different messages, serialized once and then sent again in
turn, so that the rate holds even for messages with thousands of nested ones.

    em-fuzz --duration 20 --rate 500 --seed 1        # then: messages sent per topic

The run's identity: every message type of the system carries a ``run_id`` and every node
drops another run's messages at once, so a fuzz with other ids would test only that
check. em-fuzz speaks with the run's id: it listens, while it reads the graph, on the
topics with a ``run_id`` field that the target nodes publish (/world/status is latched,
the others come every step) and takes the id of the first message it gets (an attacker
on the domain can read it just as well); it attacks only once it knows the id and stops
listening then (its own messages never teach it one). ``--run-id N`` gives the id instead
(0: nodes started by hand). A foreign id stays one fault class among the others: the
``run_id`` field, like any other, is the forced extreme one of some messages (2^64 - 1 or
2^63), which the nodes drop at the run check.

With ``--topics T ...`` only those of the topics are attacked (a flood of one topic at the
highest rate the fuzzer reaches: ``em-fuzz --topics /team/update_requests --rate 5000``).

With ``--start-file FILE`` it reads the graph until FILE exists and attacks then, without
the settling pause: a test starts it with the team and attacks mid-run even when the run
lasts only seconds.

Ctrl-C or SIGTERM ends the attack early (the report tells what was sent until then).
Exit code 0 (1: the start file did not appear in time, or no message of the run told its
id within ``--start-timeout``; 2: bad arguments, such as a non-finite number or a --report
file that cannot be written); the last stdout line is a JSON report (``--report FILE``
writes it too; ``run_id`` and ``run_id_source``: the id sent and where it came from).
"""
from __future__ import annotations

import json
import math
import random
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message

from em_exploration_ros.core.output_paths import output_path_problem
from em_exploration_ros.tools.bag_ros import import_message_class
from em_exploration_ros.tools.cli_parser import CliParser

#: Node names whose subscriptions are attacked by default.
SYSTEM_NODES = ("em_world", "em_robot", "em_evaluator")
#: Wall seconds between two readings of the ROS graph, and before the first one.
REDISCOVER_S = 2.0
GRAPH_SETTLE_S = 2.0
#: Length of a huge array of numbers and of a huge array of nested messages.
HUGE_NUMBER_ARRAY = 100_000
HUGE_MESSAGE_ARRAY = 3_000
#: Messages made per topic; after that, those are sent again in turn (serializing a message
#: with thousands of nested ones takes milliseconds; reusing the bytes keeps up the rate).
POOL_SIZE = 8
#: The encapsulation header that starts every serialized message (little-endian CDR).
CDR_HEADER = b"\x00\x01\x00\x00"
#: The field of the system's messages that names their run.
RUN_ID_FIELD = "run_id"
#: Probability that a field other than the forced one is extreme too.
EXTRA_EXTREME_PROBABILITY = 0.1
#: Frame names of the system (plausible values) and wrong ones (extreme values).
PLAUSIBLE_FRAMES = ("map", "world", "robot_0/base_link", "robot_1/odom")
WRONG_FRAMES = ("", "no_such_frame", "robot_99/base_link", "x" * 10_000)
_INT_BITS = {"char": (8, False), "int8": (8, True), "uint8": (8, False), "int16": (16, True),
             "uint16": (16, False),
             "int32": (32, True), "uint32": (32, False), "int64": (64, True),
             "uint64": (64, False)}
_FLOAT_EXTREMES = {"double": (float("nan"), float("inf"), float("-inf"), 1e308, -1e308),
                   "float": (float("nan"), float("inf"), float("-inf"), 3.4e38, -3.4e38)}


def _int_extremes(kind: str) -> tuple[int, ...]:
    bits, signed = _INT_BITS[kind]
    if signed:
        return -(2 ** (bits - 1)), 2 ** (bits - 1) - 1, -1
    return 2 ** bits - 1, 2 ** (bits - 1)


@dataclass(frozen=True)
class FieldType:
    """A message field's type as rosidl spells it: base type, and array shape."""

    base: str
    sequence: bool = False
    length: int | None = None  # fixed array length
    bound: int | None = None  # upper bound of a bounded sequence or string

    @classmethod
    def parse(cls, spelling: str) -> "FieldType":
        """``double``, ``sequence<uint64>``, ``sequence<pkg/Msg, 5>``, ``double[36]``,
        ``string<=10`` as a FieldType."""
        if spelling.startswith("sequence<"):
            base, _, bound = spelling[len("sequence<"):-1].partition(",")
            return cls(base.strip(), sequence=True, bound=int(bound) if bound else None)
        if spelling.endswith("]"):
            base, _, length = spelling[:-1].partition("[")
            return cls(base, length=int(length))
        base, _, bound = spelling.partition("<=")
        return cls(base, bound=int(bound) if bound else None)

    @property
    def is_message(self) -> bool:
        return "/" in self.base


class ExtremeMessages:
    """Builds messages of one class with at least one extreme value (module docstring);
    a plausible ``run_id`` is the run's (``run_id``), an extreme one another run's."""

    def __init__(self, rng: random.Random, run_id: int = 0) -> None:
        self._rng = rng
        self.run_id = run_id

    def make(self, message_class: type, allow_huge: bool = True) -> Any:
        """A message of ``message_class``: plausible values, one forced extreme field (at
        most one huge array per message: ``allow_huge`` is False inside array elements)."""
        message = message_class()
        fields = list(message.get_fields_and_field_types().items())
        forced = self._rng.randrange(len(fields)) if fields else -1
        for index, (name, spelling) in enumerate(fields):
            kind = FieldType.parse(spelling)
            extreme = index == forced or self._rng.random() < EXTRA_EXTREME_PROBABILITY
            value = self._value(kind, extreme, name, allow_huge)
            setattr(message, name, value)
            if isinstance(value, list) and len(value) > 4:
                allow_huge = False
        return message

    def _value(self, kind: FieldType, extreme: bool, name: str, allow_huge: bool) -> Any:
        rng = self._rng
        if kind.sequence or kind.length is not None:
            huge = kind.sequence and extreme and allow_huge and rng.random() < 0.5
            if huge:
                count = HUGE_MESSAGE_ARRAY if kind.is_message else HUGE_NUMBER_ARRAY
            else:
                count = kind.length if kind.length is not None else rng.randrange(4)
            if kind.bound is not None:  # a bounded sequence at most at its bound
                count = min(count, kind.bound)
            if count == 0:
                return []
            element = FieldType(kind.base)
            first = self._value(element, extreme and not huge, name, False)
            if huge:  # one plausible element repeated: cheap to build, as big on the wire
                return [first] * count
            return [first] + [self._value(element, False, name, False) for _ in range(count - 1)]
        if kind.is_message:
            nested = import_message_class(kind.base.replace("/", "/msg/", 1))
            return self.make(nested, allow_huge) if extreme else self._plausible(nested)
        value = self._scalar(kind.base, extreme, name)
        return value[:kind.bound] if kind.bound is not None else value  # a bounded string

    def _plausible(self, message_class: type) -> Any:
        message = message_class()
        for name, spelling in message.get_fields_and_field_types().items():
            setattr(message, name, self._value(FieldType.parse(spelling), False, name, False))
        return message

    def _scalar(self, base: str, extreme: bool, name: str) -> Any:
        rng = self._rng
        if base in _FLOAT_EXTREMES:
            return rng.choice(_FLOAT_EXTREMES[base]) if extreme else float(rng.randrange(4))
        if base in _INT_BITS:
            if extreme:
                return rng.choice(_int_extremes(base))
            return self.run_id if name == RUN_ID_FIELD else rng.randrange(4)
        if base == "boolean":
            return rng.random() < 0.5
        if base in ("string", "wstring"):
            if name.endswith("frame_id"):
                return rng.choice(WRONG_FRAMES if extreme else PLAUSIBLE_FRAMES)
            return "x" * 10_000 if extreme else ""
        raise ValueError(f"unsupported field type {base}")


@dataclass
class Target:
    """A topic under attack: its publisher and what was sent."""

    topic: str
    message_class: type
    publisher: Any
    sent: int = 0
    subscribers: set[str] = field(default_factory=set)
    pool: list[bytes] = field(default_factory=list)  # serialized messages made so far
    turns: int = 0

    def next_message(self, messages: ExtremeMessages) -> bytes:
        """The next serialized message to send: a new one while the pool is not full, then
        the pool's in turn."""
        if len(self.pool) < POOL_SIZE:
            data = serialize_message(messages.make(self.message_class))
            if len(self.pool) == POOL_SIZE - 1:  # the last one cut short: not the type
                data = data[:max(len(CDR_HEADER), len(data) // 2)]
            self.pool.append(data)
        self.turns += 1
        return self.pool[(self.turns - 1) % POOL_SIZE]



def _durable(info) -> bool:
    """Whether an endpoint of the graph (``TopicEndpointInfo``) is transient local."""
    return info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL


def _reliable_qos(depth: int, durable: bool) -> QoSProfile:
    """Reliable keep-last ``depth``, transient local when ``durable`` (to match the run's
    endpoints: a latched writer's last message comes at once), else volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if durable
                                  else DurabilityPolicy.VOLATILE))

class Fuzzer(Node):
    """Finds the system's subscriptions and publishes extreme messages on them, with the
    run's id (given, or learned from the run's messages before the attack)."""

    def __init__(self, target_nodes: tuple[str, ...], seed: int,
                 topics: frozenset[str] | None = None, run_id: int | None = None) -> None:
        super().__init__("em_fuzzer")
        self._target_nodes = target_nodes
        self._topics = topics  # None: every topic the target nodes subscribe to
        self._messages = ExtremeMessages(random.Random(seed))
        self.targets: dict[str, Target] = {}
        self.failed_publishes = 0
        #: Where the run's id came from: "--run-id", the topic it was learned on, or None
        #: while it is not known.
        self.run_id_source: str | None = None
        if run_id is not None:
            self._messages.run_id, self.run_id_source = run_id, "--run-id"
        self._listeners: dict[str, Any] = {}  # topic -> subscription learning the run's id

    @property
    def run_id(self) -> int | None:
        """The run's id the messages carry (None: not learned yet)."""
        return None if self.run_id_source is None else self._messages.run_id

    def discover(self) -> None:
        """Add every topic with a subscriber among the target nodes (publishers' QoS:
        reliable, transient local when a subscriber asks for it, keep last 10); note the
        subscribers of known topics. Raises ExternalShutdownException once a signal has shut
        the context down (the graph cannot be read any more)."""
        try:
            self._read_graph()
        except RCLError:
            self._stop_if_shut_down()
            raise

    def _stop_if_shut_down(self) -> None:
        """Raise ExternalShutdownException if a signal (SIGINT, SIGTERM) has shut the
        context down: the attack ends there."""
        if not self.context.ok():
            raise ExternalShutdownException()

    def _read_graph(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if self.run_id_source is None:
                self._listen_for_run_id(topic, types[0])
            if self._topics is not None and topic not in self._topics:
                continue
            subscribers = [info for info in self.get_subscriptions_info_by_topic(topic)
                           if info.node_name in self._target_nodes]
            names = {f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in subscribers}
            if topic in self.targets:
                self.targets[topic].subscribers |= names
                continue
            if not subscribers:
                continue
            qos = _reliable_qos(10, any(_durable(info) for info in subscribers))
            message_class = import_message_class(types[0])
            self.targets[topic] = Target(topic, message_class,
                                         self.create_publisher(message_class, topic, qos),
                                         subscribers=names)

    def _listen_for_run_id(self, topic: str, type_name: str) -> None:
        """Subscribe to ``topic`` if a target node publishes it and its type has a run_id
        (reliable, transient local when every such writer is: a latched status comes at
        once)."""
        if topic in self._listeners:
            return
        writers = [info for info in self.get_publishers_info_by_topic(topic)
                   if info.node_name in self._target_nodes]
        message_class = import_message_class(type_name)
        if not writers or RUN_ID_FIELD not in message_class.get_fields_and_field_types():
            return
        qos = _reliable_qos(1, all(_durable(info) for info in writers))
        self._listeners[topic] = self.create_subscription(
            message_class, topic, lambda message: self._heard_run(topic, message), qos)

    def _heard_run(self, topic: str, message: Any) -> None:
        """A message of the run: its id is the run's, if none is known yet."""
        if self.run_id_source is None:
            self._messages.run_id = int(getattr(message, RUN_ID_FIELD))
            self.run_id_source = topic

    def _stop_listening(self) -> None:
        """No more learning: from now on this fuzzer's own messages are on those topics."""
        for subscription in self._listeners.values():
            self.destroy_subscription(subscription)
        self._listeners.clear()

    def wait_for(self, start_file: Path | None, timeout_s: float) -> str | None:
        """Read the graph every ``REDISCOVER_S`` (and take the run's messages) until
        ``start_file`` (if any) exists and the run's id is known; why not, if that does not
        happen within ``timeout_s`` wall seconds."""
        deadline = time.monotonic() + timeout_s
        next_discovery = time.monotonic() + GRAPH_SETTLE_S
        while True:
            started = start_file is None or start_file.exists()
            if started and self.run_id_source is not None:
                return None
            self._stop_if_shut_down()
            now = time.monotonic()
            if now > deadline:
                return (f"{start_file} did not appear within {timeout_s:g} s" if not started
                        else f"no message of the run told its run_id within {timeout_s:g} s "
                        f"(give it with --run-id)")
            if now >= next_discovery:
                self.discover()
                next_discovery = now + REDISCOVER_S
            rclpy.spin_once(self, timeout_sec=0.05)

    def attack(self, duration_s: float, rate_hz: float, settle_s: float = GRAPH_SETTLE_S) -> None:
        """Publish round robin over the targets for ``duration_s`` wall seconds (after
        ``settle_s`` for this new participant to learn the graph), with the run's id."""
        self._stop_listening()
        time.sleep(settle_s)
        start = time.monotonic()
        next_discovery = start
        sent = 0
        while (now := time.monotonic()) < start + duration_s:
            self._stop_if_shut_down()
            if now >= next_discovery:
                self.discover()
                next_discovery = now + REDISCOVER_S
            targets = sorted(self.targets)
            if not targets:
                time.sleep(0.1)
                continue
            target = self.targets[targets[sent % len(targets)]]
            try:
                target.publisher.publish(target.next_message(self._messages))
                target.sent += 1
            except RCLError:  # a refused publish is counted, the attack goes on
                self.failed_publishes += 1
            sent += 1
            delay = start + sent / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def report(self, duration_s: float) -> dict[str, Any]:
        """What was sent, per topic."""
        return {"duration_s": duration_s, "messages": sum(t.sent for t in self.targets.values()),
                "failed_publishes": self.failed_publishes, "run_id": self.run_id,
                "run_id_source": self.run_id_source,
                "topics": {name: {"type": t.message_class.__module__.split(".")[0] + "/"
                                  + t.message_class.__name__, "sent": t.sent,
                                  "subscribers": sorted(t.subscribers)}
                           for name, t in sorted(self.targets.items())}}


def main(argv: list[str] | None = None) -> int:
    """Entry point of em-fuzz; returns the exit code."""
    parser = CliParser(prog="em-fuzz", description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="wall seconds (20)")
    parser.add_argument("--rate", type=float, default=500.0, help="messages per second (500)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the values (0)")
    parser.add_argument("--nodes", nargs="+", default=list(SYSTEM_NODES),
                        help=f"node names whose subscriptions are attacked {SYSTEM_NODES}")
    parser.add_argument("--topics", nargs="+",
                        help="attack only these of the nodes' topics (default: all of them)")
    parser.add_argument("--report", type=Path, help="also write the JSON report here")
    parser.add_argument("--start-file", type=Path,
                        help="read the graph until this file exists, then attack at once: a "
                        "script starts the fuzzer early (discovery takes seconds) and chooses "
                        "the moment of the attack")
    parser.add_argument("--start-timeout", type=float, default=600.0,
                        help="wall seconds to wait for --start-file and the run's id (600); "
                        "exit code 1 after")
    parser.add_argument("--run-id", type=int,
                        help="the run's id to send (default: learned from the first message "
                        "of the run em-fuzz hears; 0 for nodes started by hand)")
    args = parser.parse_args(argv)
    for name in ("duration", "rate", "start_timeout"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            parser.error(f"--{name.replace('_', '-')} must be a positive finite number, "
                         f"got {value:g}")
    if args.run_id is not None and not 0 <= args.run_id < 2**64:
        parser.error(f"--run-id must be in 0..2^64 - 1, got {args.run_id}")
    if args.report is not None:
        problem = output_path_problem(args.report, "--report")
        if problem is not None:
            parser.error(problem)
    rclpy.init()
    fuzzer = Fuzzer(tuple(args.nodes), args.seed,
                    frozenset(args.topics) if args.topics else None, args.run_id)
    try:
        try:
            problem = fuzzer.wait_for(args.start_file, args.start_timeout)
            if problem is None:
                fuzzer.attack(args.duration, args.rate,
                              settle_s=GRAPH_SETTLE_S if args.start_file is None else 0.0)
        except (KeyboardInterrupt, ExternalShutdownException):  # SIGINT, SIGTERM
            problem = None  # report what was sent until then
        report = fuzzer.report(args.duration) if problem is None else None
    finally:
        fuzzer.destroy_node()
        rclpy.try_shutdown()
    if report is None:
        print(f"em-fuzz: error: {problem}; nothing sent", file=sys.stderr, flush=True)
        return 1
    text = json.dumps(report, sort_keys=True)
    if args.report:
        args.report.write_text(text + "\n", encoding="utf-8")
    print(text, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
