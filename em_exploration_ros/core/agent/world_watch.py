"""Whether the world simulator is still there, from what the ROS graph shows over time.

A robot or an evaluator started on its own (outside run_team.sh) must not run forever
after its world is gone. ``WorldWatch`` turns periodic observations "the world's
publisher is on the graph" into events: LOST when it left after being seen, BACK when it
returned, GONE when it stayed away ``timeout_s`` wall seconds. Before the world was
first seen nothing is reported (the node is simply waiting for it).
"""
from __future__ import annotations

from enum import Enum


class WorldEvent(Enum):
    """A change in the world's presence."""

    LOST = "lost"
    BACK = "back"
    GONE = "gone"


class WorldWatch:
    """Presence of the world over time (see module docstring); times are monotonic [s]."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.seen = False
        self.lost_since_s: float | None = None
        self._gone_reported = False

    def update(self, present: bool, now_s: float) -> WorldEvent | None:
        """Record one observation; returns the event it makes, if any."""
        if present:
            back = self.lost_since_s is not None
            self.seen, self.lost_since_s, self._gone_reported = True, None, False
            return WorldEvent.BACK if back else None
        if not self.seen:
            return None
        if self.lost_since_s is None:
            self.lost_since_s = now_s
            return WorldEvent.LOST
        if not self._gone_reported and now_s - self.lost_since_s >= self.timeout_s:
            self._gone_reported = True
            return WorldEvent.GONE
        return None
