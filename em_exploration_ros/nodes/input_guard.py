"""What every node does with input it cannot use, and with a publish that fails.

``InputGuard.drop(topic, reason)`` writes one throttled WARN per topic and kind of reason
(with the count dropped since the previous line); the checks themselves are the ROS-free functions of
``core.agent.input_checks``. ``header_problem`` and ``content_problem`` apply them to any
message: the header's stamp and frame; every floating-point number and every time it
carries; ``checked_team_update`` adds a team update's array sizes.
``publish_or_log`` publishes and logs, never raises, when the middleware refuses.
"""
from __future__ import annotations

import time
from typing import Any, Iterator

import numpy as np
from builtin_interfaces.msg import Time
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from rclpy.publisher import Publisher

from em_exploration_ros.core.agent.input_checks import (RejectionLog, array_problem,
                                                        frame_problem, reason_kind,
                                                        stamp_problem)
from em_exploration_ros.core.agent.team_data import InvalidTeamUpdate, TeamUpdate
from em_exploration_ros.core.agent.team_wire import TeamWireFormat
from em_exploration_ros.nodes.conversions import team_update_from_msg

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


def header_problem(header: Any, frame_id: str) -> str | None:
    """Reason if a std_msgs/Header has a negative or malformed stamp or another frame."""
    return (stamp_problem(header.stamp.sec, header.stamp.nanosec)
            or frame_problem(header.frame_id, frame_id))


def content_problem(message: Any) -> str | None:
    """Reason if any number of a message (nested ones included) is not finite or
    implausibly large, or any builtin_interfaces/Time in it is negative or malformed.
    Arrays of numbers are checked as arrays, without a Python object per number."""
    for kind, value in _leaves(message):
        problem = (stamp_problem(*value) if kind == "time"
                   else array_problem(value, "a number"))
        if problem:
            return problem
    return None


def _leaves(message: Any) -> Iterator[tuple[str, Any]]:
    """("numbers", array) for every float field or float array and ("time", (sec,
    nanosec)) for every builtin_interfaces/Time, nested messages included."""
    if isinstance(message, Time):
        yield "time", (message.sec, message.nanosec)
        return
    for name, kind in message.get_fields_and_field_types().items():
        value = getattr(message, name)
        base = kind.split("<", 1)[-1].rstrip(">").split(",")[0].split("[", 1)[0]
        if base in _FLOAT_TYPES:
            yield "numbers", np.asarray(value, dtype=float)
        elif "/" in base:
            items = value if ("sequence<" in kind or "[" in kind) else (value,)
            for item in items:
                yield from _leaves(item)


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


def publish_or_log(publisher: Publisher, message: Any, node: Node, what: str) -> bool:
    """Publish ``message``; if the middleware refuses, log an ERROR and return False."""
    try:
        publisher.publish(message)
    except RCLError as error:
        node.get_logger().error(f"could not publish {what} on {publisher.topic_name}: {error}",
                                throttle_duration_sec=LOG_PERIOD_S)
        return False
    return True
