"""What the observer's session (``evaluator_session.EvaluatorSession``) asks its driver to
do, and what it reads in a robot's motion command.

em-evaluator (``nodes/evaluator_node.py`` with ``nodes/evaluator_outputs.py``) publishes the
metrics, asks for missed team updates, keeps the summary so far on disk and, at the end,
writes the summary and the map and exits; em-sim (``team_runner.TeamRunner``) reports the
metrics as progress and ignores the rest. Besides these, the session returns
``effects.LogLine`` and ``effects.Dropped``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Union

from em_exploration_ros.core.evaluation.evaluator import TeamMetrics
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, MeetingEntry, RunSummary
from em_exploration_ros.core.records.team_data import MissingRange
from em_exploration_ros.core.sessions.effects import Dropped, LogLine


@dataclass(frozen=True)
class PublishMetrics:
    """Publish one evaluation: the team metrics and the decisions counted until them."""

    metrics: TeamMetrics
    decisions: int


@dataclass(frozen=True)
class RequestUpdates:
    """Ask robots again for the team updates of these gaps (as robots do)."""

    gaps: tuple[MissingRange, ...]


@dataclass(frozen=True)
class Finished:
    """The run ended: write ``summary`` and the map (``EvaluatorSession.map_layers``),
    then exit with ``exit_code``."""

    summary: RunSummary
    exit_code: int


@dataclass(frozen=True)
class KeepSoFar:
    """Replace the summary file with ``summary``, the run so far, whose stop reason starts
    with ``evaluator_session.EVALUATOR_LOST_PREFIX`` (the final summary replaces it; it
    stays when the evaluator dies before the run ended). Replaced atomically: a process
    killed while it writes leaves the previous one."""

    summary: RunSummary


Effect = Union[Dropped, PublishMetrics, RequestUpdates, Finished, KeepSoFar, LogLine]


@dataclass(frozen=True)
class CommandReport:
    """What the observer reads in a robot's answer to step ``step`` (its MotionCommand).

    ``stamp_ns``: the answer's stamp [ns sim time]; ``team_sequence``: the last team update
    the robot published; ``blocked_s``: the simulation time [s] its odometry showed it
    blocked so far; ``given_up_count``: targets given up so far (this process);
    ``given_up`` and ``meetings``: those given up and the meetings it requested that added an
    inter-robot factor, at this step; ``slam_recoveries``: its SLAM updates re-solved in
    batch so far.
    """

    robot_id: int
    step: int
    stamp_ns: int
    finished: bool
    team_sequence: int
    blocked_s: float
    given_up_count: int
    given_up: tuple[GivenUpEntry, ...] = ()
    meetings: tuple[MeetingEntry, ...] = ()
    slam_recoveries: int = 0
