"""Plausibility checks of what a node receives, before it touches any state.

Every check returns ``None`` for usable input or a short reason (for one throttled log
line) for input that is dropped. The bounds are what the system can produce, with room
to spare, so that hostile or corrupted values (NaN, infinities, huge or negative ids,
sequence numbers and steps, huge arrays, clocks that go backwards) never reach a queue
or a loop whose size they would set. The ROS nodes call these on every message; the
checks know nothing of ROS (plain numbers in, reasons out).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from em_exploration_ros.core.records.limits import MAX_ABS_VALUE, MAX_ID
from em_exploration_ros.core.records.wire_model import seconds_to_nanoseconds

#: How far ahead of the step a robot expects next a sensor message may be [steps]. In
#: lockstep the world is never ahead by more than one step; in real time a robot that
#: lags keeps at most this many steps of sensor data (200 s at the paper's 0.2 s step).
MAX_STEP_LEAD = 1000
#: How far ahead of its newest complete step the evaluator accepts ground truth and
#: estimates [steps]: it may lag behind a fast lockstep world while it evaluates, and
#: must never drop a true pose (2000 s of simulation at the paper's 0.2 s step).
EVALUATOR_STEP_LEAD = 10_000
#: Fastest plausible simulation clock [simulated s per wall s]: lockstep on a tiny map
#: runs at a few hundred, the real-time mode at most 1000.
MAX_SIM_RATE = 10_000.0
#: Wall time [s] after which a clock that went back, and has advanced since while nothing
#: continued the later time, is taken up (``ClockGuard``): the world publishes /clock
#: every step, many times a second.
CLOCK_RECOVERY_S = 2.0
#: How far [simulated s] a clock that went back must have advanced on its own, in at least
#: ``CLOCK_RECOVERY_INCREASES`` strictly increasing samples, before ``ClockGuard`` takes it
#: up: repeated identical stamps (a publisher sending sec = 0 at 20 Hz while the world
#: paused) are no clock. The world's clock advances 0.2 s a step.
CLOCK_RECOVERY_ADVANCE_S = 1.0
CLOCK_RECOVERY_INCREASES = 3
#: Nanoseconds per second, the bound of builtin_interfaces/Time.nanosec.
_NANOSECONDS_PER_SECOND = 1_000_000_000
#: Key under which a RejectionLog counts input once it tells ``max_keys`` keys apart.
OTHER_KEY = "(other)"
_QUOTED = re.compile(r"'[^']*'?")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|nan|inf)", re.IGNORECASE)
#: Largest relative slack of a motion command over the robot's kinematic limits.
_COMMAND_SLACK = 1.01


def number_problem(values: Iterable[float], what: str) -> str | None:
    """Reason if any value is not finite or larger in magnitude than ``MAX_ABS_VALUE``."""
    for value in values:
        if not math.isfinite(value):
            return f"{what} is not finite ({value})"
        if abs(value) > MAX_ABS_VALUE:
            return f"{what} is implausibly large ({value:g})"
    return None


def array_problem(values: np.ndarray, what: str) -> str | None:
    """``number_problem`` for an array, vectorized."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return None
    largest = float(np.max(np.abs(values)))  # NaN if any value is NaN
    if largest <= MAX_ABS_VALUE:
        return None
    if not np.all(np.isfinite(values)):
        return f"{what} is not finite ({values[~np.isfinite(values)].flat[0]})"
    return f"{what} is implausibly large ({largest:g})"


def stamp_problem(sec: int, nanosec: int, what: str = "stamp") -> str | None:
    """Reason if a builtin_interfaces/Time (sec, nanosec) is negative or malformed."""
    if sec < 0:
        return f"{what} is negative ({sec} s)"
    if not 0 <= nanosec < _NANOSECONDS_PER_SECOND:
        return f"{what} has nanosec {nanosec} outside [0, 1e9)"
    return None


def frame_problem(frame_id: str, expected: str, what: str = "frame_id") -> str | None:
    """Reason if ``frame_id`` is not ``expected``."""
    if frame_id != expected:
        shown = frame_id if len(frame_id) <= 40 else frame_id[:40] + "..."
        return f"{what} '{shown}' is not '{expected}'"
    return None


def id_problem(value: int, count: int | None, what: str) -> str | None:
    """Reason if an id is not in ``0..count - 1`` (or not in ``0..MAX_ID`` if count is None)."""
    high = MAX_ID if count is None else count - 1
    if not 0 <= value <= high:
        return f"{what} {value} is not in 0..{high}"
    return None


def size_problem(size: int, limit: int, what: str) -> str | None:
    """Reason if an array has more than ``limit`` elements."""
    if size > limit:
        return f"{size} {what} (at most {limit} are plausible)"
    return None


def step_problem(step: int, next_step: int | None, max_step: int,
                 lead: int = MAX_STEP_LEAD) -> str | None:
    """Reason if a message's ``step`` is unusable for a receiver expecting ``next_step``
    next (None: no bound yet) in a run of at most ``max_step`` steps.

    Steps before ``next_step`` are stale; steps more than ``lead`` ahead, or after the
    run's last step, cannot come from the world."""
    if not 0 <= step <= max_step:
        return f"step {step} is outside the run (0..{max_step})"
    if next_step is not None and step < next_step:
        return f"step {step} is stale (next expected {next_step})"
    if next_step is not None and step > next_step + lead:
        return f"step {step} is more than {lead} steps ahead of {next_step}"
    return None


def first_problem(problems: Iterable[str | None]) -> str | None:
    """The first reason among ``problems`` (e.g. one check per array element), or None."""
    return next((problem for problem in problems if problem), None)


def sequence_entry_problem(entry: int, received_up_to: int, lead: int, what: str) -> str | None:
    """Reason if a sequence number named by a barrier or a command is implausible: more
    than ``lead`` ahead of ``received_up_to`` (the last sequence number known)."""
    if entry > received_up_to + lead:
        return (f"{what} {entry} is implausibly far ahead of {received_up_to} "
                f"(more than {lead})")
    return None


def command_sequence_problem(entry: int, last: int, lead: int) -> str | None:
    """Reason if a motion command's barrier entry (``team_sequence``) is behind the robot's
    last one (``last``: its sequence numbers only grow, a restart included) or more than
    ``lead`` ahead of it."""
    if entry < last:
        return f"team_sequence {entry} is behind {last}"
    return sequence_entry_problem(entry, last, lead, "team_sequence")


def barrier_problem(entries: Sequence[int], num_robots: int,
                    expected_next: dict[int, int], lead: int,
                    own: tuple[int, int] | None = None) -> str | None:
    """Reason if a lockstep barrier (SonarScan.team_sequences) is unusable: it must be empty
    (real time) or hold one entry per robot, each at most ``lead`` ahead of the sequence
    number the receiver expects next from that robot (``expected_next``; robots missing
    there are not bounded). ``own``: ``(receiver id, step of the scan)``; the receiver's
    own entry is then at most the step plus one, as a robot sends at most one record per
    step (a restarted robot numbers its new records after it, and keeps an empty record
    for every number its teammates did not give back)."""
    if len(entries) not in (0, num_robots):
        return f"{len(entries)} barrier entries for {num_robots} robots"
    for robot, entry in enumerate(entries):
        if robot in expected_next:
            problem = sequence_entry_problem(int(entry), expected_next[robot] - 1, lead,
                                             f"barrier entry of robot {robot}")
            if problem:
                return problem
    if entries and own is not None:
        robot, step = own
        return sequence_entry_problem(int(entries[robot]), step, 1,
                                      f"own barrier entry (robot {robot}, step {step})")
    return None


def command_problem(linear_x: float, angular_z: float, speed_mps: float,
                    max_turn_rad: float, time_step_s: float) -> str | None:
    """Reason if a motion command (m/s, rad/s) exceeds the robot's kinematic limits
    (forward speed ``speed_mps``, ``max_turn_rad`` per step of ``time_step_s``)."""
    problem = number_problem((linear_x, angular_z), "twist")
    if problem:
        return problem
    if abs(linear_x) > speed_mps * _COMMAND_SLACK:
        return f"speed {linear_x:g} m/s exceeds {speed_mps:g} m/s"
    if abs(angular_z) > max_turn_rad / time_step_s * _COMMAND_SLACK:
        return f"turn rate {angular_z:g} rad/s exceeds {max_turn_rad / time_step_s:g} rad/s"
    return None


@dataclass
class ClockGuard:
    """Accepts a clock only if it is valid, does not go backwards and does not leap ahead.

    ``check`` returns the reason to drop a /clock sample (negative, malformed, earlier
    than the last accepted one, or further ahead of it than ``max_rate`` simulated
    seconds per wall second allow, plus one second) or None and remembers it. Without the
    last bound one hostile sample at the year 2038 would make every true one "backwards".

    One hostile sample can still come first (nothing precedes it to bound it) or leap
    within the bound, and then every true sample is "backwards". So the samples dropped as
    backwards are followed as a rival timeline (each within the leap bound of the one
    before, never earlier than it): once it has run for ``recover_after_s`` wall seconds
    while no sample continued the accepted one, and has itself advanced by at least
    ``recover_advance_s`` in at least ``recover_increases`` strictly increasing samples,
    the guard takes it up (``take_notice`` says so). A clock that keeps publishing is never
    overruled, and neither is a replay that starts over while the accepted clock still
    runs, nor a rival that repeats one stamp (however long) or barely creeps.
    """

    max_rate: float = MAX_SIM_RATE
    recover_after_s: float = CLOCK_RECOVERY_S
    recover_advance_s: float = CLOCK_RECOVERY_ADVANCE_S
    recover_increases: int = CLOCK_RECOVERY_INCREASES
    latest_ns: int = -1
    latest_wall_s: float = 0.0
    _rival_ns: int = -1
    _rival_wall_s: float = 0.0
    _rival_since_s: float = 0.0
    _rival_first_ns: int = -1
    _rival_increases: int = 0
    _notice: str | None = None

    def check(self, sec: int, nanosec: int, wall_s: float) -> str | None:
        """Check a sample received at monotonic wall time ``wall_s`` [s]."""
        problem = stamp_problem(sec, nanosec, "clock")
        if problem:
            return problem
        now_ns = sec * _NANOSECONDS_PER_SECOND + nanosec
        if now_ns < self.latest_ns:
            if self._rival_continues(now_ns, wall_s):
                self._notice = (f"clock taken up again at {now_ns / 1e9:.3f} s: it went back "
                                f"from {self.latest_ns / 1e9:.3f} s, which nothing continued "
                                f"for {wall_s - self.latest_wall_s:.1f} wall seconds")
                self._accept(now_ns, wall_s)
                return None
            return (f"clock went backwards from {self.latest_ns / 1e9:.3f} s to "
                    f"{now_ns / 1e9:.3f} s")
        if self.latest_ns >= 0:
            leap = self._leap_problem(self.latest_ns, self.latest_wall_s, now_ns, wall_s)
            if leap:
                return leap
        self._accept(now_ns, wall_s)
        return None

    def take_notice(self) -> str | None:
        """What the guard did that its caller should log (taking a rival timeline up),
        once; None if nothing."""
        notice, self._notice = self._notice, None
        return notice

    def _accept(self, now_ns: int, wall_s: float) -> None:
        self.latest_ns, self.latest_wall_s = now_ns, wall_s
        self._rival_ns = -1

    def _leap_problem(self, from_ns: int, from_wall_s: float, now_ns: int,
                      wall_s: float) -> str | None:
        allowed_s = self.max_rate * max(wall_s - from_wall_s, 0.0) + 1.0
        if (now_ns - from_ns) / 1e9 > allowed_s:
            return (f"clock leapt from {from_ns / 1e9:.3f} s to {now_ns / 1e9:.3f} s "
                    f"in {wall_s - from_wall_s:.3f} wall seconds")
        return None

    def _rival_continues(self, now_ns: int, wall_s: float) -> bool:
        """Follow a backwards sample as the rival timeline; whether that timeline is now
        to be taken up (see the class docstring)."""
        if (self._rival_ns < 0 or now_ns < self._rival_ns
                or self._leap_problem(self._rival_ns, self._rival_wall_s, now_ns, wall_s)):
            self._rival_since_s = wall_s  # a new rival starts here
            self._rival_first_ns, self._rival_increases = now_ns, 0
        elif now_ns > self._rival_ns:
            self._rival_increases += 1  # the same stamp again continues it, advancing nothing
        self._rival_ns, self._rival_wall_s = now_ns, wall_s
        return (wall_s - self._rival_since_s >= self.recover_after_s
                and wall_s - self.latest_wall_s >= self.recover_after_s
                and self._rival_increases >= self.recover_increases
                and now_ns - self._rival_first_ns >= self.recover_advance_s * 1e9)


def run_problem(run_id: int, own_run_id: int) -> str | None:
    """Reason to drop a message of another run (``run_id`` not this node's ``own_run_id``:
    two runs on one ROS domain), naming both runs."""
    if run_id == own_run_id:
        return None
    return f"of run {run_id}, not of this node's run {own_run_id} (another run on the domain)"


def reason_kind(reason: str) -> str:
    """A reason with its values blanked (quoted text, numbers), so that reasons of the same
    kind share one throttled log line: ``frame_id 'x' is not 'map'`` -> ``frame_id _ is not _``."""
    return _NUMBER.sub("#", _QUOTED.sub("_", reason))[:80]


@dataclass
class RejectionLog:
    """Throttles the log lines of dropped input: at most one line per ``key`` (e.g. topic and
    reason kind) every ``period_s`` wall seconds, counting what was dropped in between.
    At most ``max_keys`` keys are told apart (the rest share one), so the log's own memory
    is bounded whatever the input."""

    period_s: float = 5.0
    max_keys: int = 256
    _last_logged_s: dict[str, float] = field(default_factory=dict)
    _dropped: dict[str, int] = field(default_factory=dict)
    total: int = 0

    def note(self, key: str, now_s: float) -> int | None:
        """Count one dropped input under ``key`` at monotonic time ``now_s`` [s]; returns
        the number dropped since the last line when a line is due, else None."""
        if key not in self._last_logged_s and len(self._last_logged_s) >= self.max_keys:
            key = OTHER_KEY
        self.total += 1
        self._dropped[key] = self._dropped.get(key, 0) + 1
        last = self._last_logged_s.get(key)
        if last is not None and now_s - last < self.period_s:
            return None
        self._last_logged_s[key] = now_s
        return self._dropped.pop(key)


def stamp_step_problem(stamp_ns: int, step: int, time_step_s: float) -> str | None:
    """Reason if a sensor stamp [ns] is not the simulation time of ``step`` (the world
    stamps step k with k * time_step_s, rounded to the nanosecond)."""
    expected_ns = seconds_to_nanoseconds(step * time_step_s)
    if stamp_ns != expected_ns:
        return f"stamp {stamp_ns / 1e9:.9f} s is not the time of step {step}"
    return None


def landmark_reading_problem(range_m: float, range_variance: float,
                             bearing_variance: float, landmark_id: int) -> str | None:
    """Reason if a sonar landmark reading cannot be a measurement: negative range,
    variance not positive, or an implausible id (numbers are checked separately)."""
    if range_m < 0 or range_variance <= 0 or bearing_variance <= 0:
        return "landmark reading with a negative range or a variance <= 0"
    return id_problem(landmark_id, None, "landmark id")


def history_request_problem(requester_id: int, first_sequence: int, last_sequence: int,
                            own_id: int, num_robots: int) -> str | None:
    """Reason to drop a request of a restarted teammate for its own stream (requester id
    equal to the owner's): the requester must be a teammate, and the range the whole
    stream (1..0), the only one a restarted robot asks for."""
    if not 0 <= requester_id < num_robots or requester_id == own_id:
        return f"request for the own stream of {requester_id}, which is not a teammate"
    if (first_sequence, last_sequence) != (1, 0):
        return (f"request for robot {requester_id}'s own stream with range "
                f"{first_sequence}..{last_sequence}, not the whole stream (1..0)")
    return None


def request_problem(requester_id: int, first_sequence: int, last_sequence: int,
                    own_id: int, num_robots: int, observer_id: int) -> str | None:
    """Reason to drop a TeamUpdateRequest addressed to robot ``own_id``: a requester that
    is neither a teammate nor the observer id, or a range that is not ``first >= 1`` and
    (``last`` = 0, or ``first <= last``)."""
    if requester_id != observer_id and (not 0 <= requester_id < num_robots
                                        or requester_id == own_id):
        return f"requester id {requester_id} is neither a teammate nor the observer"
    if first_sequence < 1 or (last_sequence != 0 and last_sequence < first_sequence):
        return f"bad range {first_sequence}..{last_sequence}"
    return None
