"""Values the robots published over time, by stamp, read as of a simulation time."""
from __future__ import annotations

from typing import Any

from em_exploration_ros.core.evaluation.evaluator import stamp_key


class StampedEstimates:
    """What each robot published over time (paths, landmark sets, progress values), keyed by
    their stamps, so that an evaluation reads every robot's value as of a simulation time."""

    def __init__(self) -> None:
        self._items: dict[int, dict[int, Any]] = {}

    def add(self, robot: int, stamp_s: float, value: Any) -> None:
        """Keep ``value`` of ``robot`` stamped ``stamp_s`` [s]."""
        self._items.setdefault(robot, {})[stamp_key(stamp_s)] = value

    def newest_key(self, robot: int) -> int | None:
        """Stamp key of the newest value of ``robot`` (None if nothing arrived)."""
        items = self._items.get(robot)
        return max(items) if items else None

    def newest(self, robot: int) -> Any:
        """The newest value of ``robot`` (None if nothing arrived)."""
        key = self.newest_key(robot)
        return None if key is None else self._items[robot][key]

    def as_of(self, stamp_s: float) -> dict[int, Any]:
        """Each robot's newest value stamped at or before ``stamp_s`` [s], in robot id order
        (so pooled sums add up the same way every run); older values, no longer needed by
        later evaluations, are dropped."""
        limit = stamp_key(stamp_s)
        chosen = {}
        for robot, items in sorted(self._items.items()):
            keys = [key for key in items if key <= limit]
            if keys:
                newest = max(keys)
                chosen[robot] = items[newest]
                for key in keys:
                    if key != newest:
                        del items[key]
        return chosen
