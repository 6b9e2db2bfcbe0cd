"""What a session asks its driver to do besides its own effects: log a line.

A session (``RobotSession``, ``WorldSession``, ``EvaluatorSession``) takes inputs and
returns effects; it never logs, publishes or reads a clock itself. A ROS node turns a
``LogLine`` into its logger's call (``throttle_key`` lines at most once per ``LOG_PERIOD_S``
of wall time per key), em-sim into a line on stderr or nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class Level(Enum):
    """Severity of a log line, as the ROS logger's."""

    DEBUG = "debug"
    INFO = "info"
    WARN = "warn"
    ERROR = "error"


@dataclass(frozen=True)
class LogLine:
    """One line for the process's log. ``throttle_key``: lines with the same key are
    throttled together by the driver (None: always logged)."""

    level: Level
    text: str
    throttle_key: str | None = None


def info(text: str, throttle_key: str | None = None) -> LogLine:
    """An INFO line."""
    return LogLine(Level.INFO, text, throttle_key)


def warn(text: str, throttle_key: str | None = None) -> LogLine:
    """A WARN line."""
    return LogLine(Level.WARN, text, throttle_key)


def error(text: str, throttle_key: str | None = None) -> LogLine:
    """An ERROR line."""
    return LogLine(Level.ERROR, text, throttle_key)
