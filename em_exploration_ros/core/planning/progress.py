"""Progress toward a target, targets given up, and the turn away from a blocked direction.

A robot judges its progress only from its own data, as a vehicle does with its odometry
(a DVL on an AUV, wheel odometry on a ground robot) and its own pose estimate:

* **blocked**: forward motion was commanded at every step of the last ``window_s`` seconds
  but the odometry shows less than ``min_progress_m`` of translation over that time (the
  vehicle pushes against something it does not know of, e.g. the map edge or a landmark
  its estimate places elsewhere);
* **no progress**: the estimated distance to the target has not shrunk by
  ``min_progress_m`` for ``window_s`` seconds (the robot moves but does not get closer,
  e.g. it circles); reported as blocked if the odometry of the last step showed the
  robot blocked.

A target given up (for either reason or after its deadline) goes into the robot's
``TargetBlacklist``: no candidate within ``radius_m`` of it is chosen again for
``duration_s``. A blocked robot first turns on the spot until its heading points away
from the blocked direction (``RecoveryTurn``), so the next target is not approached
along the same blocked line. Everything here is pure bookkeeping on numbers the robot
already has: positions in the map frame [m], headings [rad], simulation time [s].
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum
from typing import Sequence

import numpy as np

from em_exploration_ros.core.geometry import wrap_angle
from em_exploration_ros.core.params import ProgressParams
from em_exploration_ros.core.planning.frontiers import Frontier

#: A step is blocked when the odometry measured less than this fraction of the commanded
#: forward distance (the sensor noise of a moving robot is a few per cent of a step).
_BLOCKED_FRACTION = 0.1
#: A recovery turn is complete when the heading is within this of the reversed blocked
#: heading [rad] (half of one 15-degree step, so the turn ends on the step that gets there).
_REVERSED_TOLERANCE_RAD = np.radians(7.5)


def blocked_step(commanded_forward_m: float, odometry_forward_m: float) -> bool:
    """Whether one step was blocked: forward motion commanded [m] but the odometry measured
    less than a tenth of it [m]."""
    return (commanded_forward_m > 0.0
            and odometry_forward_m < _BLOCKED_FRACTION * commanded_forward_m)


class GiveUpReason(str, Enum):
    """Why a robot gave a target up."""

    BLOCKED = "blocked"
    NO_PROGRESS = "no progress"
    DEADLINE = "deadline"


@dataclass(frozen=True)
class GivenUpTarget:
    """A target a robot gave up: map-frame position (2,) [m], when [s] and why."""

    position: np.ndarray
    stamp_s: float
    reason: GiveUpReason


class ProgressMonitor:
    """Watches one robot's approach to its current target (see the module docstring).

    Call ``restart`` whenever a new target is set (or the robot drove elsewhere for a
    while, e.g. to a meeting point), then ``update`` once per step while driving to it.
    State is a few numbers, independent of the window length; ``blocked_now`` tells
    whether the odometry of the last step showed the robot blocked.
    """

    def __init__(self, params: ProgressParams) -> None:
        self.window_s = params.window_s
        self.min_progress_m = params.min_progress_m
        self._best_distance_m = np.inf
        self._best_since_s: float | None = None
        self._pushing_since_s: float | None = None
        self._pushed_m = 0.0
        self.blocked_now = False

    def restart(self) -> None:
        """Forget the approach so far; the next ``update`` starts a new one."""
        self._best_distance_m = np.inf
        self._best_since_s = None
        self._pushing_since_s = None
        self._pushed_m = 0.0
        self.blocked_now = False

    def update(self, stamp_s: float, distance_m: float, commanded_forward_m: float,
               odometry_forward_m: float) -> GiveUpReason | None:
        """One step of the approach; returns BLOCKED, NO_PROGRESS or None (all well).

        Args:
            stamp_s: simulation time of this step [s].
            distance_m: estimated distance from the robot to its target now [m].
            commanded_forward_m: forward distance the robot commanded for the step that
                just ended [m] (0 while it turned on the spot or stood).
            odometry_forward_m: translation its odometry measured over that step [m].
        """
        self.blocked_now = blocked_step(commanded_forward_m, odometry_forward_m)
        if self._best_since_s is None or distance_m <= self._best_distance_m - self.min_progress_m:
            self._best_distance_m = float(distance_m)
            self._best_since_s = stamp_s
        if commanded_forward_m <= 0.0:
            self._pushing_since_s = None
        else:
            if self._pushing_since_s is None:
                self._pushing_since_s, self._pushed_m = stamp_s, 0.0
            self._pushed_m += max(float(odometry_forward_m), 0.0)
            if self._pushed_m >= self.min_progress_m:
                self._pushing_since_s, self._pushed_m = stamp_s, 0.0
        if self._pushing_since_s is not None and stamp_s - self._pushing_since_s >= self.window_s:
            return GiveUpReason.BLOCKED
        if stamp_s - self._best_since_s >= self.window_s:
            return GiveUpReason.BLOCKED if self.blocked_now else GiveUpReason.NO_PROGRESS
        return None


class TargetBlacklist:
    """Targets a robot gave up, each excluding the candidates within ``radius_m`` of it for
    ``duration_s`` of simulation time. Holds at most ``max_entries`` (the oldest go first)."""

    def __init__(self, params: ProgressParams, max_entries: int = 1000) -> None:
        self.radius_m = params.blacklist_radius_m
        self.duration_s = params.blacklist_duration_s
        self._entries: deque[GivenUpTarget] = deque(maxlen=max_entries)

    def add(self, given_up: GivenUpTarget) -> None:
        """Remember a target given up."""
        self._entries.append(given_up)

    def active(self, stamp_s: float) -> list[GivenUpTarget]:
        """The entries still in force at ``stamp_s`` [s]."""
        return [e for e in self._entries if stamp_s - e.stamp_s < self.duration_s]

    def excludes(self, positions: np.ndarray, stamp_s: float) -> np.ndarray:
        """For map-frame positions (K, 2) [m]: whether each lies within the radius of an
        entry in force, shape (K,)."""
        points = np.asarray(positions, dtype=float).reshape(-1, 2)
        active = self.active(stamp_s)
        if not active or len(points) == 0:
            return np.zeros(len(points), dtype=bool)
        centres = np.array([e.position for e in active])
        distance = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=-1)
        return np.any(distance <= self.radius_m, axis=1)

    def allowed(self, candidates: Sequence[Frontier], stamp_s: float) -> list[Frontier]:
        """The candidates not excluded at ``stamp_s``, in their order."""
        if not candidates:
            return []
        excluded = self.excludes(np.array([c.position for c in candidates]), stamp_s)
        return [c for c, out in zip(candidates, excluded) if not out]


class RecoveryTurn:
    """Turning on the spot away from the direction in which a robot was blocked."""

    def __init__(self, blocked_heading_rad: float) -> None:
        """Args: the robot's estimated heading [rad, map frame] when it was blocked."""
        self.blocked_heading_rad = float(blocked_heading_rad)

    def done(self, heading_rad: float) -> bool:
        """True once the heading [rad] points (nearly) opposite to the blocked one."""
        turned = abs(float(wrap_angle(heading_rad - self.blocked_heading_rad)))
        return turned >= np.pi - _REVERSED_TOLERANCE_RAD
