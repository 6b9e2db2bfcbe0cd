"""What every node does with input it cannot use, and with a publish that fails.

``InputGuard.drop(topic, reason)`` writes one throttled WARN per topic and kind of reason
(with the count dropped since the previous line); the checks themselves are the ROS-free
functions of ``core.agent.input_checks``. ``header_problem`` and ``content_problem`` apply them
to any message: the header's stamp and frame; every floating-point number and every time it
carries; ``checked_team_update`` adds a team update's array sizes.
``size_limited`` drops a serialized message longer than the topic's largest valid one
before it is deserialized; ``screened_team_updates`` deserializes a team update only once
its head passed ``core.records.update_screening``.
``publish_or_log`` publishes and logs, never raises, when the middleware refuses (silently
once the node's context is shut down: the process is stopping).
"""
from __future__ import annotations

import functools
import importlib
import operator
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from builtin_interfaces.msg import Time
from em_exploration_msgs.msg import TeamUpdate as TeamUpdateMessage
from rclpy._rclpy_pybind11 import RCLError, RMWError
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.serialization import deserialize_message, serialize_message

from em_exploration_ros.core.agent.input_checks import (RejectionLog, array_problem, frame_problem,
                                                        reason_kind, stamp_problem)
from em_exploration_ros.core.records.team_data import InvalidTeamUpdate, TeamUpdate
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.records.update_screening import screen_team_update
from em_exploration_ros.core.records.wire_model import NANOSECONDS_PER_SECOND
from em_exploration_ros.nodes.conversions import team_update_from_msg
from em_exploration_ros.nodes.path_cdr import DecodedPath

#: Wall seconds between two log lines about the same topic's dropped input.
LOG_PERIOD_S = 5.0
_FLOAT_TYPES = ("double", "float")


class InputGuard:
    """Counts and logs (throttled) the input a node drops, per topic and kind of reason."""

    def __init__(self, node: Node, period_s: float = LOG_PERIOD_S) -> None:
        self._logger = node.get_logger()
        self._log = RejectionLog(period_s)

    @property
    def dropped(self) -> int:
        """Messages dropped so far."""
        return self._log.total

    def drop(self, topic: str, reason: str) -> None:
        """Drop one message of ``topic`` for ``reason``; log it unless a line about the same
        kind of reason on the topic was written less than the period ago."""
        count = self._log.note(f"{topic} {reason_kind(reason)}", time.monotonic())
        if count is not None:
            suffix = f" ({count} such since the last line)" if count > 1 else ""
            self._logger.warn(f"dropped a message on {topic}: {reason}{suffix}")

    def check(self, topic: str, *problems: str | None) -> bool:
        """True if every problem is None; otherwise drops the message for the first one."""
        for problem in problems:
            if problem:
                self.drop(topic, problem)
                return False
        return True


def size_limited(guard: InputGuard, topic: str, message_class: type, max_bytes: int,
                 callback: Callable[..., None], raw: bool = False,
                 with_info: bool = False) -> Callable[..., None]:
    """The callback of a raw subscription (``create_subscription(..., raw=True)``) that
    drops a serialized message longer than ``max_bytes`` (the largest valid message of the
    topic) before it is deserialized, and hands the others, deserialized, to ``callback``
    (with the message info too, with ``with_info``).
    rclpy takes 30-60 ms to turn a message with thousands of nested messages into Python
    objects; under a flood of them a node fell behind while the middleware's queues held
    what it had not taken yet (tens of MB). Bytes that do not deserialize (a raw writer
    can send anything) are dropped too. With ``raw``, ``callback`` gets the bytes themselves
    (it reads them its own way)."""
    def taken(data: bytes) -> Any | None:
        if len(data) > max_bytes:
            guard.drop(topic, f"{len(data)} bytes, more than the {max_bytes} of the largest "
                              "valid message")
            return None
        return data if raw else deserialized(guard, topic, message_class, data)
    return _raw_callback(taken, callback, with_info)


def screened_team_updates(guard: InputGuard, topic: str,
                          run_problem: Callable[[int], str | None],
                          owner_problem: Callable[[int], str | None],
                          next_expected: Callable[[int], int] | None,
                          callback: Callable[..., None], with_info: bool = False
                          ) -> Callable[..., None]:
    """The callback of a raw subscription (``raw=True``) of team updates that deserializes a
    message only once its head passed ``core.records.update_screening.screen_team_update``
    (the run, the owner the topic may carry, the number of keyframes, the sequence number
    against ``next_expected``); the others are dropped with the reason the receiver gives
    after reading them, or ignored without a line (a long copy of a record already held).
    ``callback`` gets the message (and, with ``with_info``, the message info). rclpy took
    30-180 ms to deserialize a team update with thousands of nested messages; under
    em-fuzz's flood of the team topics every robot fell tens of seconds behind the
    barrier."""
    def screened(data: bytes) -> Any | None:
        screening = screen_team_update(data, run_problem, owner_problem, next_expected)
        if not screening.read:
            if screening.problem is not None:
                guard.drop(topic, screening.problem)
            return None
        return deserialized(guard, topic, TeamUpdateMessage, data)
    return _raw_callback(screened, callback, with_info)


def _raw_callback(take: Callable[[bytes], Any | None], callback: Callable[..., None],
                  with_info: bool) -> Callable[..., None]:
    """A raw subscription's callback: ``callback`` gets what ``take`` makes of the bytes
    unless that is None (and the message info, with ``with_info``: rclpy passes it to a
    callback of two parameters)."""
    def on_serialized(data: bytes) -> None:
        message = take(data)
        if message is not None:
            callback(message)

    def on_serialized_with_info(data: bytes, info: Any) -> None:
        message = take(data)
        if message is not None:
            callback(message, info)
    return on_serialized_with_info if with_info else on_serialized


def deserialized(guard: InputGuard, topic: str, message_class: type, data: bytes) -> Any | None:
    """``data`` as a ``message_class`` message, or None (dropped, with the reason) if the
    bytes are not one: a raw writer can send anything."""
    try:
        return deserialize_message(data, message_class)
    except RMWError as error:
        guard.drop(topic, f"malformed {message_class.__name__}: "
                          f"{str(error).splitlines()[0][:80]}")
        return None


def serialized_size(message: Any) -> int:
    """Bytes of a message on the wire (CDR) [B]."""
    return len(serialize_message(message))


def header_problem(header: Any, frame_id: str) -> str | None:
    """Reason if a std_msgs/Header has a negative or malformed stamp or another frame."""
    return (stamp_problem(header.stamp.sec, header.stamp.nanosec)
            or frame_problem(header.frame_id, frame_id))


def content_problem(message: Any) -> str | None:
    """Reason if any number of a message (nested ones included) is not finite or
    implausibly large, or any builtin_interfaces/Time in it is negative or malformed.
    The message is read along its class's cached plan (``_content_plan``: one C-level
    attribute fetch for every float, float array and time reached through nested messages,
    a loop only over sequences of messages), and every number is checked in one array, so
    a message with thousands of nested messages costs milliseconds (a flood of such
    messages used to take a node 0.1-0.2 s each, and the node fell tens of seconds behind
    the team)."""
    floats: list[float] = []
    arrays: list[Any] = []
    times: list[Time] = []
    _collect(message, floats, arrays, times)
    for stamp in times:
        problem = stamp_problem(stamp.sec, stamp.nanosec)
        if problem:
            return problem
    if arrays:
        floats = np.concatenate([np.asarray(floats, dtype=float)]
                                + [np.asarray(values, dtype=float).ravel() for values in arrays])
    return array_problem(floats, "a number")


def path_problem(path: DecodedPath, frame_id: str) -> str | None:
    """``header_problem`` and ``content_problem`` of a path read by ``path_cdr.decode_path``
    (every pose is in the header's frame)."""
    stamps = path.pose_stamps
    bad = (stamps[:, 0] < 0) | (stamps[:, 1] >= NANOSECONDS_PER_SECOND)
    return (stamp_problem(*path.stamp) or frame_problem(path.frame_id, frame_id)
            or (stamp_problem(*(int(v) for v in stamps[np.argmax(bad)])) if bad.any() else None)
            or array_problem(path.poses, "a number"))


def _collect(message: Any, floats: list[float], arrays: list[Any], times: list[Time]) -> None:
    """Float fields of ``message`` and its nested messages into ``floats``, float arrays
    into ``arrays``, builtin_interfaces/Time values into ``times``."""
    if isinstance(message, Time):
        times.append(message)
        return
    plan = _content_plan(type(message))
    if plan.floats is not None:
        floats.extend(plan.floats(message))
    if plan.arrays is not None:
        arrays.extend(plan.arrays(message))
    if plan.times is not None:
        times.extend(plan.times(message))
    for sequence in plan.sequences:
        for item in sequence(message):
            _collect(item, floats, arrays, times)


_FLOAT, _FLOATS, _MESSAGE, _MESSAGES = "float", "floats", "message", "messages"


@dataclass(frozen=True)
class _ContentPlan:
    """Getters (``operator.attrgetter`` over dotted paths, each returning a tuple) of what
    ``content_problem`` checks in one message class; None where the class has none."""

    floats: Callable[[Any], tuple] | None
    arrays: Callable[[Any], tuple] | None
    times: Callable[[Any], tuple] | None
    #: getters of each sequence of nested messages (walked item by item)
    sequences: tuple[Callable[[Any], Any], ...]


def _tuple_getter(paths: list[str]) -> Callable[[Any], tuple] | None:
    if not paths:
        return None
    if len(paths) == 1:
        single = operator.attrgetter(paths[0])
        return lambda message: (single(message),)
    return operator.attrgetter(*paths)


@functools.lru_cache(maxsize=None)
def _content_plan(message_class: type) -> _ContentPlan:
    """The dotted paths of ``message_class``'s floats, float arrays and times, reached
    through its nested (non-sequence) messages, and of its sequences of messages."""
    floats: list[str] = []
    arrays: list[str] = []
    times: list[str] = []
    sequences: list[str] = []

    def walk(cls: type, prefix: str) -> None:
        for name, kind, nested in _field_plan(cls):
            path = prefix + name
            if kind == _FLOAT:
                floats.append(path)
            elif kind == _FLOATS:
                arrays.append(path)
            elif kind == _MESSAGES:
                sequences.append(path)
            elif nested is Time:
                times.append(path)
            else:
                walk(nested, path + ".")

    walk(message_class, "")
    return _ContentPlan(_tuple_getter(floats), _tuple_getter(arrays), _tuple_getter(times),
                        tuple(operator.attrgetter(path) for path in sequences))


@functools.lru_cache(maxsize=None)
def _field_plan(message_class: type) -> tuple[tuple[str, str, type | None], ...]:
    """(field name, kind, nested message class or None) of the fields of a message class
    that can hold floats or times: a float, an array of floats, a nested message, an array
    of nested messages."""
    plan = []
    for (name, spelling), slot in zip(message_class.get_fields_and_field_types().items(),
                                      message_class.SLOT_TYPES):
        base = spelling.split("<", 1)[-1].rstrip(">").split(",")[0].split("[", 1)[0]
        is_array = "sequence<" in spelling or "[" in spelling
        if base in _FLOAT_TYPES:
            plan.append((name, _FLOATS if is_array else _FLOAT, None))
        elif "/" in base:
            nested = getattr(slot, "value_type", slot)  # the item type of an array
            module = importlib.import_module(".".join(nested.namespaces))
            plan.append((name, _MESSAGES if is_array else _MESSAGE,
                         getattr(module, nested.name)))
    return tuple(plan)


def checked_team_update(message: Any, wire: TeamWireFormat) -> TeamUpdate:
    """A received em_exploration_msgs/TeamUpdate as core data (``wire``: the team's shared
    parameters that rebuild what is not sent), after the checks that do not need the
    receiver's state: array sizes (before anything is converted), every number and time.
    ``InvalidTeamUpdate`` says why not; the receiver's inbox then validates the content
    against the team."""
    update = team_update_from_msg(message, wire)
    problem = content_problem(message)
    if problem:
        raise InvalidTeamUpdate(problem)
    return update


def listened(publisher: Publisher) -> bool:
    """True when some subscription matches ``publisher``: messages only users look at
    (markers, maps, transforms) are built only then."""
    return publisher.get_subscription_count() > 0


def publish_or_log(publisher: Publisher, message: Any, node: Node, what: str) -> bool:
    """Publish ``message``; if the middleware refuses, log an ERROR and return False.

    A refusal once ``node``'s context is shut down is the process stopping, not an error:
    False, without a line. Ctrl-C / SIGTERM shut the context down from rclpy's signal
    thread while a callback may be running (as in a stopped process continued with a
    pending SIGINT, the way run_team.sh stops one); its publish then fails with "publisher's
    context is invalid", which was logged as an ERROR. A refusal while the context is
    valid is still one.
    """
    try:
        publisher.publish(message)
    except RCLError as error:
        if not node.context.ok():
            return False
        node.get_logger().error(f"could not publish {what} on {publisher.topic_name}: {error}",
                                throttle_duration_sec=LOG_PERIOD_S)
        return False
    return True
