"""Which robots of the team are alive: status per robot with the times it changed.

A robot is ``active`` from the start; ``lost`` when the middleware reported its liveliness
lost (its process died, was stopped or wedged: its participant no longer asserts
liveliness within the lease) and did not report it back within ``grace_s`` (on a lossy
network a liveliness assertion can miss its lease while the robot works on); ``rejoined``
when it is heard again after being lost; ``finished`` when it reports that it has nothing
left to explore. Every change is listed with the simulation time and the wall time (seconds
since the caller's start) at which it happened, so a run's summary can show downtimes: the
first and the latest ``MAX_STATUS_CHANGES // 2`` of a robot's changes, with the number left
out between them (a flood of liveliness identities makes a lost and a rejoined change for
each); the downtimes count every change.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from em_exploration_ros.core.records.limits import MAX_LIVELINESS_WRITERS, MAX_STATUS_CHANGES

ACTIVE, FINISHED, LOST, REJOINED = "active", "finished", "lost", "rejoined"


@dataclass(frozen=True)
class StatusChange:
    """A robot's status from ``sim_time_s`` / ``wall_s`` on [s], and why it changed."""

    status: str
    sim_time_s: float
    wall_s: float
    reason: str


class TeamLiveness:
    """Status of every robot of a team (see module docstring); no clock of its own."""

    def __init__(self, num_robots: int, grace_s: float,
                 max_changes: int = MAX_STATUS_CHANGES) -> None:
        """``grace_s``: wall seconds a liveliness loss must last to count as lost;
        ``max_changes``: status changes listed per robot (the first and latest half)."""
        self.grace_s = grace_s
        self._first_changes: list[list[StatusChange]] = [[] for _ in range(num_robots)]
        self._latest_changes = [deque(maxlen=max_changes - max_changes // 2)
                                for _ in range(num_robots)]
        self._first_kept = max_changes // 2
        self._omitted = [0] * num_robots
        # Per robot: (simulated, wall) seconds lost in closed intervals, and the times of
        # the loss that is still open (None: not lost).
        self._lost_closed = [(0.0, 0.0)] * num_robots
        self._lost_since: list[tuple[float, float] | None] = [None] * num_robots
        self._unconfirmed: dict[int, tuple[float, float]] = {}
        # Per robot: processes whose liveliness was lost and whose successor has not
        # reported its own yet.
        self._successors_due: dict[int, int] = {}

    def status(self, robot: int) -> str:
        """The robot's current status: its latest change's (active with none)."""
        latest = self._latest_changes[robot] or self._first_changes[robot]
        return latest[-1].status if latest else ACTIVE

    def changes(self, robot: int) -> list[StatusChange]:
        """The robot's status changes in order (empty: active all along): the first and the
        latest, ``omitted_changes`` of them left out between."""
        return self._first_changes[robot] + list(self._latest_changes[robot])

    def omitted_changes(self, robot: int) -> int:
        """How many of the robot's status changes ``changes`` leaves out."""
        return self._omitted[robot]

    def liveliness_lost(self, robot: int, sim_time_s: float, wall_s: float) -> None:
        """The middleware reported the robot's liveliness lost at these times [s]."""
        self._successors_due[robot] = self._successors_due.get(robot, 0) + 1
        if self.status(robot) != LOST and robot not in self._unconfirmed:
            self._unconfirmed[robot] = (sim_time_s, wall_s)

    def liveliness_back(self, robot: int, restarted: bool, sim_time_s: float,
                        wall_s: float) -> bool:
        """The middleware reported the robot's liveliness again (at these times [s]): an
        unconfirmed loss is void, unless the liveliness comes from a new process
        (``restarted``): then the robot was lost from the time of the loss, or from now if
        the new process came up within the old one's lease, before that loss was reported
        (returns True). A lost robot rejoins only when ``heard``. A new process that follows
        a lost one whose loss is already counted is no new restart, even when it was heard
        before its liveliness was reported (discovery can take a second longer than its
        first answer, on separate hosts or after quick restarts)."""
        unconfirmed = self._unconfirmed.pop(robot, None)
        successor = self._successors_due.get(robot, 0) > 0
        if successor:  # the lost process came back, or a successor took its place
            self._successors_due[robot] -= 1
        if not restarted:
            return False
        if unconfirmed is not None:
            return self._change(robot, LOST, *unconfirmed, "process restarted")
        if successor or self.status(robot) == LOST:
            return False
        return self._change(robot, LOST, sim_time_s, wall_s,
                            "process restarted within its liveliness lease")

    def confirm(self, wall_s: float) -> list[int]:
        """Robots whose liveliness loss has lasted ``grace_s`` at ``wall_s``: now lost (from
        the time of the loss); returns them."""
        confirmed = [r for r, (_, since) in sorted(self._unconfirmed.items())
                     if wall_s - since >= self.grace_s]
        for robot in confirmed:
            sim_time_s, since = self._unconfirmed.pop(robot)
            self._change(robot, LOST, sim_time_s, since,
                         f"liveliness lost for {wall_s - since:.1f} s")
        return confirmed

    def heard(self, robot: int, sim_time_s: float, wall_s: float, reason: str) -> bool:
        """A robot gave a sign of life: a lost robot has rejoined; True if that is news."""
        if self.status(robot) != LOST:
            return False
        return self._change(robot, REJOINED, sim_time_s, wall_s, reason)

    def finished(self, robot: int, sim_time_s: float, wall_s: float) -> bool:
        """A robot reported that it finished; True if that is news."""
        if self.status(robot) in (FINISHED, LOST):
            return False
        return self._change(robot, FINISHED, sim_time_s, wall_s, "reported finished")

    def downtime_s(self, robot: int, until_sim_time_s: float, until_wall_s: float
                   ) -> tuple[float, float]:
        """(simulation, wall) seconds the robot spent lost up to the given times [s]. The
        simulated downtime is 0 when the world waited for the robot."""
        closed_sim_s, closed_wall_s = self._lost_closed[robot]
        since = self._lost_since[robot]
        if since is None:
            return closed_sim_s, closed_wall_s
        return (closed_sim_s + max(until_sim_time_s - since[0], 0.0),
                closed_wall_s + max(until_wall_s - since[1], 0.0))

    def _change(self, robot: int, status: str, sim_time_s: float, wall_s: float,
                reason: str) -> bool:
        since = self._lost_since[robot]
        if status == LOST and since is None:
            self._lost_since[robot] = (sim_time_s, wall_s)
        elif status != LOST and since is not None:
            closed_sim_s, closed_wall_s = self._lost_closed[robot]
            self._lost_closed[robot] = (closed_sim_s + sim_time_s - since[0],
                                        closed_wall_s + wall_s - since[1])
            self._lost_since[robot] = None
        change = StatusChange(status, sim_time_s, wall_s, reason)
        if len(self._first_changes[robot]) < self._first_kept:
            self._first_changes[robot].append(change)
            return True
        latest = self._latest_changes[robot]
        if len(latest) == latest.maxlen:
            self._omitted[robot] += 1
        latest.append(change)
        return True


class UnseenLiveliness:
    """Which robots' liveliness the middleware has never reported, for the one look a
    watcher takes a lease after the run's first step: such a robot is treated as if its
    liveliness had been lost then (a robot that died or stopped before its liveliness was
    reported would otherwise never count as lost). A live robot's liveliness is reported up
    to about a second after the first step. No clock of its own (wall seconds given)."""

    def __init__(self, num_robots: int, lease_s: float) -> None:
        self.lease_s = lease_s
        self._unseen = set(range(num_robots))
        self._first_step_s: float | None = None
        self._looked = False

    def seen(self, robot: int) -> None:
        """The robot's liveliness was reported."""
        self._unseen.discard(robot)

    def was_seen(self, robot: int) -> bool:
        """Whether the robot's liveliness was ever reported."""
        return robot not in self._unseen

    def first_step(self, wall_s: float) -> None:
        """The run's first step happened at ``wall_s`` (later calls are ignored)."""
        if self._first_step_s is None:
            self._first_step_s = wall_s

    def due(self, wall_s: float) -> list[int]:
        """Once, from a lease after the first step: the robots never seen alive (sorted);
        [] before and after."""
        if (self._looked or self._first_step_s is None
                or wall_s - self._first_step_s < self.lease_s):
            return []
        self._looked = True
        return sorted(self._unseen)


class LivelinessWriters:
    """The liveliness writers (the middleware's endpoint ids) a watcher has seen for each
    robot, to tell a restarted robot (its liveliness gained from a writer never seen before,
    while one was seen earlier) from one whose liveliness came back. At most ``limit`` per
    robot, those present most recently: under a flood of identities on a robot's alive
    topic the ones absent longest are forgotten (one note per robot the first time)."""

    def __init__(self, robots: Iterable[int], limit: int = MAX_LIVELINESS_WRITERS) -> None:
        self.limit = limit
        self._seen: dict[int, dict[bytes, None]] = {robot: {} for robot in robots}
        self._told: set[int] = set()

    def gained(self, robot: int, writers: Iterable[bytes]) -> tuple[bool, str | None]:
        """The robot's liveliness was gained while ``writers`` write its alive topic:
        (restarted: a writer is new and one was seen before, a note when writers are
        forgotten for the first time for this robot, else None)."""
        seen = self._seen[robot]
        # Known writers last: the most recent, kept when more than the limit are present.
        present = sorted(set(writers), key=lambda writer: writer in seen)
        restarted = bool(seen) and any(writer not in seen for writer in present)
        for writer in present:
            seen.pop(writer, None)
            seen[writer] = None
        forgotten = len(seen) - self.limit
        for writer in list(seen)[:max(forgotten, 0)]:
            del seen[writer]
        if forgotten <= 0 or robot in self._told:
            return restarted, None
        self._told.add(robot)
        return restarted, (f"robot {robot}'s liveliness: more than {self.limit} writers seen "
                           f"(a flood of identities?); those absent longest are forgotten, "
                           f"and one of them back counts as a restart")
