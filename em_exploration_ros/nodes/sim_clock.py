"""A /clock subscription that survives hostile clocks (use_sim_time).

rclpy's own ``TimeSource`` (rclpy/time_source.py) subscribes /clock when ``use_sim_time``
is true and, in ``clock_callback``, converts every message with ``Time.from_msg``, whose
constructor raises ``ValueError("Seconds value must not be negative")`` for ``sec < 0``
(rclpy/time.py). The exception leaves the executor's spin, so one /clock message with a
negative time ends the node. Nothing checks that the clock goes forward either.

Choice: the node's time source is replaced at construction by ``ValidatedTimeSource``,
an rclpy ``TimeSource`` whose ``clock_callback`` first asks ``core.agent.input_checks.
ClockGuard``: a negative, malformed or backwards clock (or one that leaps further ahead
than any simulation runs) is dropped with a throttled WARN
(``InputGuard``) and the node's ROS clock keeps its last valid time (a clock that went
back and runs on alone is taken up again after a while, with a WARN, once it has itself
advanced: never one that repeats a stamp); everything else goes to rclpy's own handling,
so ``use_sim_time`` set at start or later keeps working. (Keeping rclpy's TimeSource
and subscribing /clock a second time would not help: its callback would still raise.)
rclpy creates the time source inside ``Node.__init__`` and offers no hook, so
``install_validated_clock`` swaps the node's private ``_time_source`` attribute after
detaching the original from the node and its parameter callback.
"""
from __future__ import annotations

import time

from rclpy.node import Node
from rclpy.time_source import CLOCK_TOPIC, TimeSource
from rosgraph_msgs.msg import Clock

from em_exploration_ros.core.agent.input_checks import ClockGuard
from em_exploration_ros.nodes.input_guard import InputGuard


class ValidatedTimeSource(TimeSource):
    """rclpy's TimeSource with every /clock message checked first (module docstring)."""

    def __init__(self, node: Node, guard: InputGuard) -> None:
        self._guard = guard
        self._node_logger = node.get_logger()
        self._clock_check = ClockGuard()
        super().__init__(node=node)

    def clock_callback(self, msg: Clock) -> None:
        problem = self._clock_check.check(msg.clock.sec, msg.clock.nanosec, time.monotonic())
        if problem:
            self._guard.drop(CLOCK_TOPIC, problem)
            return
        notice = self._clock_check.take_notice()
        if notice:
            self._node_logger.warning(notice)
        super().clock_callback(msg)


def install_validated_clock(node: Node, guard: InputGuard) -> ValidatedTimeSource:
    """Replace ``node``'s rclpy TimeSource by a ``ValidatedTimeSource``; call it in the
    node's constructor, before anything reads the clock."""
    original: TimeSource = node._time_source  # noqa: SLF001 (no public hook, see docstring)
    node.remove_on_set_parameters_callback(original._on_parameter_event)  # noqa: SLF001
    original.detach_node()
    source = ValidatedTimeSource(node, guard)
    source.attach_clock(node.get_clock())
    node._time_source = source  # noqa: SLF001
    return source
