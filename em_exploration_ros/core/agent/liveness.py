"""Which robots of the team are alive: status per robot with the times it changed.

A robot is ``active`` from the start, ``lost`` when the middleware reports its liveliness
lost (its process died, was stopped or wedged: its participant no longer asserts
liveliness within the lease) or when it stayed silent too long, ``rejoined`` when it is
heard again after being lost, and ``finished`` when it reports that it has nothing left
to explore. Every change is kept with the simulation time and the wall time (seconds since
the tracker was made) at which it was noticed, so a run's summary can show downtimes.
"""
from __future__ import annotations

from dataclasses import dataclass

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

    def __init__(self, num_robots: int) -> None:
        self._changes: list[list[StatusChange]] = [[] for _ in range(num_robots)]

    def status(self, robot: int) -> str:
        """The robot's current status."""
        changes = self._changes[robot]
        return changes[-1].status if changes else ACTIVE

    def changes(self, robot: int) -> list[StatusChange]:
        """The robot's status changes in order (empty: active all along)."""
        return list(self._changes[robot])

    def lost(self, robot: int, sim_time_s: float, wall_s: float, reason: str) -> bool:
        """Mark a robot lost; True if that is news."""
        if self.status(robot) == LOST:
            return False
        return self._change(robot, LOST, sim_time_s, wall_s, reason)

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

    def downtime_s(self, robot: int, until_sim_time_s: float) -> float:
        """Simulation seconds the robot spent lost up to ``until_sim_time_s``."""
        total, lost_since = 0.0, None
        for change in self._changes[robot]:
            if change.status == LOST and lost_since is None:
                lost_since = change.sim_time_s
            elif change.status != LOST and lost_since is not None:
                total += change.sim_time_s - lost_since
                lost_since = None
        if lost_since is not None:
            total += max(until_sim_time_s - lost_since, 0.0)
        return total

    def _change(self, robot: int, status: str, sim_time_s: float, wall_s: float,
                reason: str) -> bool:
        self._changes[robot].append(StatusChange(status, sim_time_s, wall_s, reason))
        return True
