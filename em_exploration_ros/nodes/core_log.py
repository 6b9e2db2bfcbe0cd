"""The ROS-free core's log records (Python ``logging``, under ``em_exploration_ros``) written
to a node's ROS logger, so that they reach its console, log file and /rosout with the
node's name, like the node's own lines. Without this, Python drops the core's INFO lines (a
robot's "finished", its rendezvous) and prints its warnings bare on stderr."""
from __future__ import annotations

import logging
from contextlib import contextmanager
from typing import Iterator

from rclpy.impl.rcutils_logger import RcutilsLogger

from em_exploration_ros.core.sessions.effects import Level
from em_exploration_ros.nodes.log_lines import write_at

#: The Python logger above every module of the package.
PACKAGE_LOGGER = "em_exploration_ros"


class RosLogHandler(logging.Handler):
    """Writes each Python log record on a ROS logger at the matching severity (DEBUG,
    INFO, WARN, ERROR; CRITICAL as FATAL), formatted as ``logging`` would (the message,
    then a traceback if the record carries one)."""

    def __init__(self, logger: RcutilsLogger) -> None:
        super().__init__()
        self._logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
        except Exception:  # noqa: BLE001 (a bad format string: logging's own report)
            self.handleError(record)
            return
        if record.levelno >= logging.CRITICAL:
            self._logger.fatal(text)
        elif record.levelno >= logging.ERROR:
            write_at(self._logger, Level.ERROR, text)
        elif record.levelno >= logging.WARNING:
            write_at(self._logger, Level.WARN, text)
        else:
            write_at(self._logger, Level.INFO if record.levelno >= logging.INFO
                     else Level.DEBUG, text)


@contextmanager
def core_logs_to(logger: RcutilsLogger, level: int = logging.INFO) -> Iterator[None]:
    """Within the block, the package's Python log records at ``level`` and above go to
    ``logger`` (and to no other handler: they do not propagate to the root logger)."""
    package = logging.getLogger(PACKAGE_LOGGER)
    handler = RosLogHandler(logger)
    saved = package.level, package.propagate
    package.addHandler(handler)
    package.setLevel(level)
    package.propagate = False
    try:
        yield
    finally:
        package.removeHandler(handler)
        package.setLevel(saved[0])
        package.propagate = saved[1]
