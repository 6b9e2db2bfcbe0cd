"""What a robot's session (``robot_session.RobotSession``) asks its driver to do.

The ROS robot node (``nodes/robot_node.py``) turns each effect into a publication, a journal
write or its exit; em-sim (``team_runner.TeamRunner``) performs the ones that matter in one
process (the command to the world, the frames onto the links) and ignores the rest. Besides
these, a session returns ``effects.LogLine`` and ``effects.Dropped`` (an input dropped).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from em_exploration_ros.core.agent.robot_agent import MeetingEffect
from em_exploration_ros.core.links.link_model import Frame
from em_exploration_ros.core.planning.progress import GivenUpTarget
from em_exploration_ros.core.records.team_data import TeamUpdate


class Journal(Enum):
    """A robot's two journals: its own stream, and the teammates' records it applied."""

    OWN = "own"
    TEAM = "team"


@dataclass(frozen=True)
class CommandReply:
    """The MotionCommand answering one step: the twist (``linear_x`` [m/s], ``angular_z``
    [rad/s]) for the next step, the sequence number of the robot's last record, what it has
    sent on the team topics in all (``team_messages`` records, ``team_requests`` requests),
    whether it finished, its blocked time [s] and the targets given up (all so far:
    ``given_up_count``; those of this step: ``given_up``), its SLAM updates re-solved in
    batch so far and the meetings it measured since its previous reply (``MeetingEffect``).
    ``stamp``: (sec, nanosec) of the scan it answers."""

    robot_id: int
    step: int
    stamp: tuple[int, int]
    linear_x: float
    angular_z: float
    team_sequence: int
    team_messages: int
    team_requests: int
    finished: bool
    blocked_s: float
    given_up_count: int
    given_up: tuple[GivenUpTarget, ...]
    slam_recoveries: int = 0
    meetings: tuple[MeetingEffect, ...] = ()


@dataclass(frozen=True)
class PublishCorrespondences:
    """The teammates' landmarks the robot tied to its own while answering ``step`` (at
    ``stamp``, (sec, nanosec) of the scan): ``pairs`` of team-graph landmark ids (own,
    teammate's), for the evaluator's association counts (teammates do not read them)."""

    step: int
    stamp: tuple[int, int]
    pairs: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class SendCommand:
    """Publish the command of a step (``again``: the world sent the step again)."""

    reply: CommandReply
    again: bool = False


@dataclass(frozen=True)
class PublishUpdate:
    """Publish a record of this robot's stream on its update topic; ``what`` names it in a
    line about a failed publish."""

    record: TeamUpdate
    what: str


@dataclass(frozen=True)
class PublishRequest:
    """Ask robot ``owner`` for records ``first_sequence..last_sequence`` of its stream (0 as
    the last: up to its latest; ``owner`` this robot: its own stream, after a restart)."""

    owner: int
    first_sequence: int
    last_sequence: int


@dataclass(frozen=True)
class SendFrame:
    """Relay mode and em-sim: offer a frame to the links (``LinkSender``): a gap request
    (payload ``MissingRange``) or a record of this robot's stream (payload ``TeamUpdate``)."""

    frame: Frame


@dataclass(frozen=True)
class PublishHistory:
    """Re-send a restarted teammate's records, as this robot holds them."""

    requester: int
    records: tuple[TeamUpdate, ...]


@dataclass(frozen=True)
class StartJournal:
    """Begin a journal with ``records``; ``fresh``: at the mission's start."""

    journal: Journal
    records: tuple[TeamUpdate, ...]
    fresh: bool


@dataclass(frozen=True)
class AppendJournal:
    """Journal one more record."""

    journal: Journal
    record: TeamUpdate


@dataclass(frozen=True)
class ReadJournals:
    """After a restart: read both journals back and hand them to
    ``RobotSession.journals_read``."""


@dataclass(frozen=True)
class PublishTransforms:
    """/tf of a step (map -> odom -> base_link) from the agent's estimate and the dead
    reckoning ``odom_pose`` (x [m], y [m], yaw [rad], odom frame); ``stamp_s``: sim time."""

    stamp_s: float
    odom_pose: np.ndarray


@dataclass(frozen=True)
class KeyframeEstimate:
    """The robot's estimate of its latest keyframe: the keyframe's time ``stamp_s`` [s sim
    time], its pose (x [m], y [m], theta [rad]) and marginal covariance (3, 3) (additive
    x, y, theta errors), both in the map frame."""

    stamp_s: float
    pose: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class PublishEstimates:
    """The estimated path and landmarks, at a keyframe step (``stamp_s``: sim time), and
    the latest keyframe's pose with its covariance (None while the robot has no estimate of
    its own pose)."""

    stamp_s: float
    latest: KeyframeEstimate | None = None


@dataclass(frozen=True)
class PublishDecision:
    """The target, virtual map and markers of a new decision (``stamp_s``: sim time)."""

    stamp_s: float


@dataclass(frozen=True)
class Exit:
    """End the process with ``code``."""

    code: int
