"""The stall rule of a run: the team made no progress for ``run.stall_timeout_s``.

Progress is judged by the observer of a run (em-sim's runner, the evaluator node) from
the team metrics it evaluates anyway: the true distance the team travelled and the
team's explored ratio. A run in which neither grew for the timeout ends as stalled
instead of idling to its step limit; the programs exit with ``EXIT_STALLED``.
"""
from __future__ import annotations

#: Exit status of em-sim, the evaluator node and run_team.sh for a stalled run.
EXIT_STALLED = 4
#: Stop reasons of stalled runs start with this.
STALLED_PREFIX = "stalled: "
#: The team distance must grow by more than this to count as travel [m] (far below the
#: 0.2 m of one step, far above round-off).
_MIN_TRAVEL_M = 0.01


class StallWatch:
    """Watches the team metrics for progress; ``update`` returns a stop reason or ""."""

    def __init__(self, timeout_s: float) -> None:
        """Args: time without progress that ends a run [s sim time]; 0 disables the rule."""
        self.timeout_s = float(timeout_s)
        self._since_s: float | None = None
        self._distance_m = 0.0
        self._explored_ratio = 0.0

    def update(self, stamp_s: float, distance_m: float, explored_ratio: float) -> str:
        """The stop reason ("stalled: ...") when the team made no progress for the timeout
        up to ``stamp_s`` [s], else "". Args: team distance [m] and explored ratio now."""
        if (self._since_s is None or distance_m > self._distance_m + _MIN_TRAVEL_M
                or explored_ratio > self._explored_ratio):
            self._since_s = stamp_s
            self._distance_m, self._explored_ratio = float(distance_m), float(explored_ratio)
            return ""
        idle_s = stamp_s - self._since_s
        if self.timeout_s <= 0.0 or idle_s < self.timeout_s:
            return ""
        return (f"{STALLED_PREFIX}no distance and no newly explored area for {idle_s:.0f} s "
                f"(distance {self._distance_m:.1f} m, explored {self._explored_ratio:.3f})")
