"""A robot's team records on its own disk, as the robot node keeps them (ROS side of
``core.agent.stream_journal``).

The robot keeps two journals in its ``state_dir``: its own stream (``robot_<i>.journal``),
and the teammates' records it applied (``robot_<i>.team.journal``), which tie it to the map
when it was seen by a teammate rather than by itself. A record is stored as the serialized
em_exploration_msgs/TeamUpdate its teammates would send, and read back through the same
checks as a received one. A journal that cannot be written is logged once as an ERROR and
left; the robot goes on without it.
"""
from __future__ import annotations

import contextlib
import pathlib
from collections.abc import Iterable

from em_exploration_msgs.msg import TeamUpdate as TeamUpdateMsg
from rclpy._rclpy_pybind11 import RMWError
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.serialization import deserialize_message, serialize_message

from em_exploration_ros.core.agent.stream_journal import (JournalContents, JournalIdentity,
                                                          StreamJournal, mission_fingerprint,
                                                          read_journal)
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import InvalidTeamUpdate, TeamUpdate
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.sessions.robot_session import JournalRecords
from em_exploration_ros.nodes.conversions import team_update_to_msg
from em_exploration_ros.nodes.input_guard import checked_team_update


class RecordJournal:
    """One journal file of team records (module docstring); ``what`` names it in log lines
    ("stream journal", "team journal")."""

    def __init__(self, path: pathlib.Path, identity: JournalIdentity, wire: TeamWireFormat,
                 logger: RcutilsLogger, what: str) -> None:
        self._journal: StreamJournal | None = StreamJournal(path, identity)
        self.path = path
        self._identity = identity
        self._wire = wire
        self._logger = logger
        self.what = what

    def start(self, records: Iterable[TeamUpdate], fresh: bool) -> None:
        """Begin the journal with ``records``; ``fresh``: at the mission's start, when a
        journal that cannot be begun anew is removed (it is another run's)."""
        if self._journal is None:
            return
        try:
            self._journal.start(self._encoded(update) for update in records)
        except (OSError, ValueError) as error:
            if fresh:
                self._journal.discard()
            self._give_up(error)

    def append(self, update: TeamUpdate) -> None:
        """Journal one more record."""
        if self._journal is None:
            return
        try:
            self._journal.append(self._encoded(update))
        except (OSError, ValueError) as error:
            self._give_up(error)

    def read(self) -> JournalContents:
        """The journal's records as read (``read_journal``), not yet decoded."""
        return read_journal(self.path, self._identity)

    def decoded(self, contents: JournalContents) -> list[TeamUpdate]:
        """The records of ``contents`` up to the first unusable one (WARN naming it)."""
        updates = []
        for payload in contents.records:
            try:
                updates.append(checked_team_update(
                    deserialize_message(payload, TeamUpdateMsg), self._wire))
            except (RMWError, InvalidTeamUpdate, ValueError) as error:
                self._logger.warn(f"{self.what} {self.path}: record {len(updates) + 1} is "
                                  f"unusable ({str(error).splitlines()[0][:120]}); not read on")
                break
        return updates

    def read_back(self) -> JournalRecords:
        """The journal as read back, for the robot's session to check and file."""
        contents = self.read()
        return JournalRecords(self.what, str(self.path), contents.problem,
                              self.decoded(contents))

    def _encoded(self, update: TeamUpdate) -> bytes:
        return serialize_message(team_update_to_msg(update, self._wire))

    def _give_up(self, error: Exception) -> None:
        self._logger.error(f"cannot write the {self.what} {self.path}: {error}; going on "
                           f"without it (a restart then depends on the teammates' copies)")
        with contextlib.suppress(OSError):
            self._journal.close()
        self._journal = None


def robot_journals(state_dir: str, robot_id: int, params: ExplorationParams,
                   wire: TeamWireFormat, logger: RcutilsLogger
                   ) -> tuple[RecordJournal, RecordJournal] | None:
    """Robot ``robot_id``'s journals in ``state_dir`` (its own stream, the teammates'
    records it applied), None without a ``state_dir``."""
    if not state_dir:
        return None
    identity = JournalIdentity(robot_id, params.world.num_robots, mission_fingerprint(params))
    stem = pathlib.Path(state_dir) / f"robot_{robot_id}"
    return (RecordJournal(stem.with_suffix(".journal"), identity, wire, logger,
                          "stream journal"),
            RecordJournal(stem.with_suffix(".team.journal"), identity, wire, logger,
                          "team journal"))
