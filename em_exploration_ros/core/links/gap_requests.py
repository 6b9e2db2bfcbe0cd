"""When a robot asks a teammate again for records its links lost: driven by steps.

Over imperfect links (``core/links/link_model.py``) records of a teammate's stream go missing;
the receiver sees a gap when a later record arrives (``TeamUpdateInbox.missing``). Every
request crosses the same links as the data and costs bandwidth, so a robot asks for **one
gap per repair interval**, taking the teammates with gaps in turn (round robin from the
one after the last asked). The timing depends only on the step and the inbox, never on
wall time, so seeded lockstep runs repeat exactly.
"""
from __future__ import annotations

from em_exploration_ros.core.records.team_data import MissingRange, TeamUpdateInbox


class GapRequests:
    """One robot's schedule of requests for missing records (see module docstring)."""

    def __init__(self, robot_id: int, num_robots: int, interval_steps: int) -> None:
        """``interval_steps``: steps between two requests (at least 1)."""
        if interval_steps < 1:
            raise ValueError(f"interval_steps must be >= 1, got {interval_steps}")
        self.robot_id = robot_id
        self.num_robots = num_robots
        self.interval_steps = interval_steps
        self._next_step = 0
        self._last_asked = robot_id

    def due(self, step: int, inbox: TeamUpdateInbox) -> MissingRange | None:
        """The gap to ask for at ``step`` (the earliest of the next teammate in turn that
        has one), or None when it is not time yet or nothing is missing."""
        if step < self._next_step:
            return None
        gaps: dict[int, MissingRange] = {}
        for gap in inbox.missing():
            gaps.setdefault(gap.robot_id, gap)
        if not gaps:
            return None
        order = [(self._last_asked + offset) % self.num_robots
                 for offset in range(1, self.num_robots + 1)]
        teammate = next(robot for robot in order if robot in gaps)
        self._last_asked = teammate
        self._next_step = step + self.interval_steps
        return gaps[teammate]
