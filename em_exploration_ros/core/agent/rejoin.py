"""Rejoining the team after a restart: teammates keep each robot's stream, the restarted
robot takes its own back.

A robot process that crashed and was started again with the same id has lost everything
it knew, but its teammates hold every record of its team-update stream they applied
(``StreamArchive``). The restarted robot asks for its own stream (a ``TeamUpdateRequest``
whose requester is the robot itself); each teammate re-sends what it holds, and the robot
collects the records (``OwnHistoryRecovery``) until it holds its stream up to the sequence
number the world's barrier names for it, and for ``settle_s`` more so that records a
teammate holds beyond the barrier are not numbered twice. Then ``RobotAgent.resume``
rebuilds its graph, targets and sequence numbering from them. A robot that journals its
own stream (``core.agent.stream_journal``) files its journal's records first.

A robot whose process lived on but stopped answering (wedged, stopped, starved) rejoins too:
the world went on without it, and the sensor data of the steps it missed is lost (the
sensor topics keep only the newest messages) or no longer answered. It resumes at the
world's step (``step_to_resume_at``) instead of waiting for data that never comes.

Memory: an archive holds what the team published, the same amount as each robot's own
outbox holds of its own stream (about 200 bytes per robot and simulated second).
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence

import numpy as np

from em_exploration_ros.core.records.team_data import (InvalidTeamUpdate, TeamUpdate,
                                                       validate_team_update)


class StreamArchive:
    """Teammates' update records as applied, in sequence order, to serve a teammate that
    restarted (``held``)."""

    def __init__(self, own_robot_id: int, num_robots: int) -> None:
        self._own = own_robot_id
        self._streams: dict[int, list[TeamUpdate]] = {
            robot: [] for robot in range(num_robots) if robot != own_robot_id}

    def keep(self, updates: list[TeamUpdate]) -> list[TeamUpdate]:
        """File applied records (each stream's records arrive in sequence order, from 1);
        returns those filed."""
        filed = []
        for update in updates:
            stream = self._streams.get(update.robot_id)
            if stream is not None and update.sequence == len(stream) + 1:
                stream.append(update)
                filed.append(update)
        return filed

    def held(self, robot_id: int) -> list[TeamUpdate]:
        """Every record of ``robot_id``'s stream held, sequence 1 onwards (empty for this
        robot itself or an unknown id)."""
        return list(self._streams.get(robot_id, ()))


class OwnHistoryRecovery:
    """Collects this robot's own earlier records relayed by teammates (module docstring).

    ``needed_sequence``: the last sequence number of this robot the team is known to hold
    (the world's barrier entry); ``settle_s`` [s]: how long to keep listening after the
    request started, for records beyond it; ``give_up_s`` [s]: after this long the robot
    goes on with what it has (``complete`` is then True and ``short_of`` says how many
    records are missing).
    """

    def __init__(self, robot_id: int, num_robots: int, needed_sequence: int, started_s: float,
                 settle_s: float, give_up_s: float) -> None:
        self.robot_id = robot_id
        self.needed_sequence = needed_sequence
        self._num_robots = num_robots
        self._started_s = started_s
        self._settle_s = settle_s
        self._give_up_s = give_up_s
        self._records: dict[int, TeamUpdate] = {}

    def receive(self, update: TeamUpdate) -> bool:
        """File one relayed record; False for a duplicate. Raises InvalidTeamUpdate for a
        malformed record or one of another robot."""
        validate_team_update(update, self._num_robots)
        if update.robot_id != self.robot_id:
            raise InvalidTeamUpdate(f"record of robot {update.robot_id} relayed as robot "
                                    f"{self.robot_id}'s history")
        if update.sequence in self._records:
            return False
        self._records[update.sequence] = update
        return True

    def history(self) -> list[TeamUpdate]:
        """The records held without a gap from sequence 1."""
        records = []
        while len(records) + 1 in self._records:
            records.append(self._records[len(records) + 1])
        return records

    @property
    def short_of(self) -> int:
        """How many records up to ``needed_sequence`` are still missing."""
        return max(self.needed_sequence - len(self.history()), 0)

    def complete(self, now_s: float) -> bool:
        """True when the history up to the needed sequence is held and ``settle_s`` passed
        since the start, or when ``give_up_s`` passed."""
        waited = now_s - self._started_s
        return waited >= self._give_up_s or (self.short_of == 0 and waited >= self._settle_s)


def records_beyond_the_team(updates: Sequence[TeamUpdate],
                            team_holds: Sequence[int]) -> str | None:
    """Why journaled records cannot be this run's, None if they can be: they hold more of a
    robot's stream than ``team_holds[robot]`` (the last sequence number of it the team
    knows, the world's barrier) plus the one record a process can make before the world
    counts it. (The same mission run again into the same folder left a journal of the same
    identity; a full disk kept an earlier run's 42 records where a restarted robot read
    them as its own, with the team at 27.)"""
    for robot, count in sorted(Counter(update.robot_id for update in updates).items()):
        holds = team_holds[robot] if robot < len(team_holds) else 0
        if count > holds + 1:
            return (f"it holds {count} records of robot {robot}, more than the {holds} the "
                    f"team holds (+1): the journal of another run; not read")
    return None


def step_to_resume_at(next_step: int, complete_steps: Iterable[int],
                      world_step: int) -> int | None:
    """The step a robot skips ahead to, or None to keep waiting for ``next_step``.

    ``complete_steps``: the steps whose sensor data (sonar and odometry) the robot holds;
    ``world_step``: the step of the world's clock (/clock). In lockstep the world sends
    step k + 1 only once every robot it waits for answered step k, so holding a later step
    than the one awaited means the world went on without this robot: its newest complete
    step is the world's open step, the one to answer. A step the world's clock has not
    reached is not the world's (a forged message) and is never skipped to.
    """
    newest = max((step for step in complete_steps if step <= world_step), default=None)
    return newest if newest is not None and newest > next_step else None


def keyframe_ranges(indices: np.ndarray) -> str:
    """Keyframe indices for a log line, as ``count [a-b c-d ...]`` (sorted, runs merged), so
    a gap (keyframes lost, or a robot's downtime) shows at a glance."""
    runs: list[list[int]] = []
    for value in sorted(int(i) for i in indices):
        if runs and value == runs[-1][1] + 1:
            runs[-1][1] = value
        else:
            runs.append([value, value])
    return f"{sum(b - a + 1 for a, b in runs)} [" + " ".join(f"{a}-{b}" for a, b in runs) + "]"
