"""A session's ``LogLine`` (``core/sessions/effects.py``) written to a node's logger."""
from __future__ import annotations

import time

from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node

from em_exploration_ros.core.sessions.effects import Level, LogLine
from em_exploration_ros.nodes.input_guard import LOG_PERIOD_S


class LineWriter:
    """Writes ``LogLine``s on ``node``'s logger at their level; lines with the same
    ``throttle_key`` at most once per ``period_s`` of wall time (the keys are the
    session's own, a bounded set)."""

    def __init__(self, node: Node, period_s: float = LOG_PERIOD_S) -> None:
        self._logger = node.get_logger()
        self.period_s = period_s
        self._last_s: dict[str, float] = {}

    def write(self, line: LogLine) -> None:
        """Log ``line`` unless a line with its throttle key was logged less than the
        period ago."""
        if line.throttle_key is not None:
            now_s = time.monotonic()
            last_s = self._last_s.get(line.throttle_key)
            if last_s is not None and now_s - last_s < self.period_s:
                return
            self._last_s[line.throttle_key] = now_s
        write_at(self._logger, line.level, line.text)


def write_at(logger: RcutilsLogger, level: Level, text: str) -> None:
    """``text`` on a ROS logger at ``level``. One call site per severity, shared by every
    writer: rclpy refuses a call site whose severity changes ("Logger severity cannot be
    changed between calls")."""
    if level is Level.ERROR:
        logger.error(text)
    elif level is Level.WARN:
        logger.warning(text)
    elif level is Level.INFO:
        logger.info(text)
    else:
        logger.debug(text)
