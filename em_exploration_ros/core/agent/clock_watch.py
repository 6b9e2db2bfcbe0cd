"""Whether the world's steps still come, from the steps seen over wall time.

A world stopped by SIGSTOP (or wedged) stays on the ROS graph, so ``WorldWatch`` says
nothing and every node just waits. ``ClockWatch`` turns "the newest step seen" and wall
ticks into the lines a person needs: the step stood still for ``stopped_after_s`` wall
seconds (then again every ``repeat_s`` while it stands), and it moved again after standing
so long; and, for a node started with its start time, that no first step came
``first_step_after_s`` wall seconds after its start (then every ``repeat_s`` until one
comes). It judges nothing else: whoever holds the clock (the world waiting for a robot's
answer, or the robot waiting for teammates' data) is the caller's to say.
"""
from __future__ import annotations

import math

#: Wall seconds without a new step before a node says its clock stopped.
CLOCK_STOPPED_S = 5.0
#: Wall seconds between two lines while it stays stopped.
CLOCK_STOPPED_REPEAT_S = 30.0
#: Wall seconds after a node's start without a first step before it says so. At a first
#: start the world holds its first step while the team connects, 2-4 s here but up to 20 s
#: on a loaded host, which is no fault: the line is information, not a warning.
FIRST_STEP_AFTER_S = 10.0


class ClockWatch:
    """The newest step seen and since when [s, monotonic wall time]; before the first step
    only :meth:`no_first_step` reports, and only with ``started_s`` given."""

    def __init__(self, stopped_after_s: float = CLOCK_STOPPED_S,
                 repeat_s: float = CLOCK_STOPPED_REPEAT_S, started_s: float | None = None,
                 first_step_after_s: float = FIRST_STEP_AFTER_S) -> None:
        self.stopped_after_s = stopped_after_s
        self.repeat_s = repeat_s
        self.step: int | None = None
        self.since_s = 0.0
        self._next_report_s = math.inf
        self._reported = False
        self._started_s = started_s
        self._next_first_step_report_s = (math.inf if started_s is None
                                          else started_s + first_step_after_s)

    def no_first_step(self, now_s: float) -> float | None:
        """How long [s] after the start no step came yet, when a line is due at ``now_s``
        (the first ``first_step_after_s`` after the start, then every ``repeat_s``); None
        otherwise, and always once a step was seen."""
        if self.step is not None or now_s < self._next_first_step_report_s:
            return None
        self._next_first_step_report_s = now_s + self.repeat_s
        return now_s - self._started_s

    def seen(self, step: int, now_s: float) -> float | None:
        """Step ``step`` seen at ``now_s``. Returns how long [s] the clock had stood still
        when it was reported stopped and this step is newer (the "moving again" line), else
        None."""
        if self.step is not None and step <= self.step:
            return None
        stood_s = now_s - self.since_s if self._reported else None
        self.step, self.since_s = step, now_s
        self._next_report_s = now_s + self.stopped_after_s
        self._reported = False
        return stood_s

    def stopped(self, now_s: float) -> float | None:
        """How long [s] no new step came, when a line is due at ``now_s`` (the first after
        ``stopped_after_s``, then every ``repeat_s``); None otherwise."""
        if now_s < self._next_report_s:
            return None
        self._reported = True
        self._next_report_s = now_s + self.repeat_s
        return now_s - self.since_s
