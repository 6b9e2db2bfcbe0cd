"""What any session asks its driver to do besides its own effects: log a line, drop an input.

A session (``RobotSession``, ``WorldSession``, ``EvaluatorSession``) takes inputs and
returns effects; it never logs, publishes or reads a clock itself. A ROS node turns a
``LogLine`` into its logger's call (``throttle_key`` lines at most once per ``LOG_PERIOD_S``
of wall time per key), em-sim into a line on stderr or nothing; a ``Dropped`` input into its
input guard's count and throttled line.
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


@dataclass(frozen=True)
class Dropped:
    """The input just handed to the session is dropped for ``reason`` (the driver's input
    guard counts it and logs it, throttled per kind of reason)."""

    reason: str
