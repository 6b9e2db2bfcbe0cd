"""What the world's session (``world_session.WorldSession``) asks its driver to do.

The ROS world node (``nodes/world_node.py``, with ``nodes/world_outputs.py`` and
``nodes/team_relay.py``) turns each effect into a publication or a timer; em-sim
(``team_runner.TeamRunner``) hands a step's sensor frames to its robots, the deliveries to
their receivers and the truth of the scans to its observer, and ignores the rest. A delivery
is ``core.links.link_model.Delivery`` itself (a record or request for robot ``receiver``,
its payload as the world heard it).
Besides these, a session returns ``effects.LogLine``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from em_exploration_ros.core.links.link_model import UpdateDeliveryCounts
from em_exploration_ros.core.records.readings import LandmarkReading
from em_exploration_ros.core.sessions.effects import Dropped as Dropped  # every session's
from em_exploration_ros.core.world.simulation import SensorFrame


@dataclass(frozen=True, slots=True)
class PublishClock:
    """Publish /clock: the simulation time ``stamp_s`` [s] of the current step."""

    stamp_s: float


@dataclass(frozen=True, slots=True)
class PublishSensors:
    """Publish robot ``robot``'s sensor messages of a step (SonarScan and odometry from
    ``frame``, body and REP-105 odom frames), the same effect again for a re-send.
    ``team_sequences``: the barrier, each robot's last record at the previous step (lockstep;
    empty in real time). ``delivered``: in relay mode, the records and requests delivered to
    the robot so far (None without the relay)."""

    robot: int
    frame: SensorFrame
    team_sequences: tuple[int, ...]
    delivered: tuple[int, int] | None


@dataclass(frozen=True, slots=True)
class PublishTruth:
    """Publish the ground truth of the step at ``stamp_s`` [s]: every robot's true pose
    ``(x [m], y [m], theta [rad])`` in the ``world`` frame, by robot id."""

    stamp_s: float
    poses: tuple[np.ndarray, ...]


@dataclass(frozen=True, slots=True)
class PublishSonarTruth:
    """Truth side only (for the evaluator; no robot reads it): where each landmark reading
    of robot ``robot``'s scan at keyframe step ``step`` (simulation time ``stamp_s`` [s])
    came from: ``sources``, in the order of ``readings`` (the scan's, body frame), a
    landmark id or ``sensors.CLUTTER``."""

    robot: int
    step: int
    stamp_s: float
    readings: tuple[LandmarkReading, ...]
    sources: tuple[int, ...]


@dataclass(frozen=True)
class PublishLinkCounts:
    """Relay mode: publish the on-time / late / never counts of the team updates before
    ``step`` (for the evaluator's summary)."""

    step: int
    counts: UpdateDeliveryCounts


@dataclass(frozen=True)
class PublishStatus:
    """Publish /world/status: the current ``step`` at ``stamp_s`` [s], whether stepping is
    over for good (``stepping_over``: the end of the stepping) and why."""

    step: int
    stamp_s: float
    stepping_over: bool
    reason: str


@dataclass(frozen=True)
class StartTicking:
    """Real-time mode: call ``WorldSession.tick`` every ``period_s`` wall seconds."""

    period_s: float


