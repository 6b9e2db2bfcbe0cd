"""What a planner gets and returns: the interface of the built-in planners and of plugins.

A planner chooses one robot's next target among its candidates (``PlanningContext``) and
returns a ``Decision``. It is made by a ``PlannerFactory`` from the run's parameters and
found by name in the entry-point group ``em_exploration_ros.planners``
(``core.planner_registry``, docs/plugins.md). Every position is in the team ``map`` frame
[m], every pose ``(x [m], y [m], theta [rad])``; the utilities are costs (lower is better).

A planner's choice must depend on its context and parameters only (no clock, no unseeded
randomness): em-sim and the ROS team in lockstep then choose the same targets.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Mapping, Protocol, Sequence

import numpy as np

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.slam.team_slam import TeamSlam
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid


@dataclass(frozen=True)
class PlanningContext:
    """Everything a planner may use for one decision of robot ``robot_id``.

    ``slam``: the robot's own team SLAM (its estimate of every robot's trajectory and of the
    landmarks; virtual paths start at every robot's latest keyframe in it); ``grid``: the
    team occupancy grid (the robot's virtual map: the inter-robot map's probability of being
    observed, and the cell layout); ``candidates``: the targets to choose among (at least
    one), each a ``Frontier`` with its ``position`` (2,) [m], its ``kind``
    (``FrontierType``: exploration, revisiting or rendezvous) and, for a rendezvous, its
    ``partner_id``; ``robot_pose``: (3,) current map-frame pose (``U_D``); ``teammates``:
    ``{id: (position (2,), current target (2,) or None)}``; ``target_history``: ``{robot id:
    targets (2,) in chronological order}`` (alpha's own entry is ignored);
    ``explored_ratio`` in [0, 1].
    """

    robot_id: int
    slam: TeamSlam
    grid: OccupancyGrid
    candidates: Sequence[Frontier]
    robot_pose: np.ndarray
    teammates: Mapping[int, tuple[np.ndarray, np.ndarray | None]]
    target_history: Mapping[int, Sequence[np.ndarray]]
    explored_ratio: float


@dataclass(frozen=True)
class CandidateUtility:
    """Utility terms of one candidate; ``nan`` for a term the planner does not use.
    ``u_m``: map uncertainty [m^2] (or the planner's own uncertainty measure), ``u_t``: task
    allocation (unitless), ``u_d``: distance [m], ``total``: the weighted sum minimized."""

    frontier: Frontier
    u_m: float
    u_t: float
    u_d: float
    total: float


@dataclass(frozen=True)
class Decision:
    """The chosen target, every candidate's utilities (candidate order) and
    ``choose_time_s``, the wall time of ``Planner.choose`` alone [s] (the robot's whole
    decision, map rebuild included, is ``DecisionRecord.planning_time_s``)."""

    target: Frontier
    utilities: list[CandidateUtility]
    choose_time_s: float


class Planner(Protocol):
    """A target-selection rule.

    ``name``: the name it is registered under (summaries and logs show it). ``choose`` gets
    the context of one decision and returns the chosen candidate (one of
    ``context.candidates``) with every candidate's utility terms; :func:`decide` builds
    that from per-candidate arrays. A planner that raises ``RuntimeError`` or
    ``numpy.linalg.LinAlgError`` (a numerical failure) is replaced for that decision by the
    nearest frontier rule (the summary's ``planner_failures``); any other exception is a
    bug and ends the robot's run."""

    name: str

    def choose(self, context: PlanningContext) -> Decision:
        """Choose among ``context.candidates`` (at least one)."""


class PlannerFactory(Protocol):
    """What a planner's entry point names: a callable (a class, or a function) that makes
    the planner from the run's parameters (``params.planner`` holds the built-in planners'
    weights; a plugin may read any group, and keep its own settings in its package)."""

    def __call__(self, params: ExplorationParams) -> Planner:
        """The planner for a run with ``params``."""


def decide(context: PlanningContext, u_m: np.ndarray, u_t: np.ndarray, u_d: np.ndarray,
           total: np.ndarray, started: float) -> Decision:
    """The argmin of ``total`` (C,) (first candidate on ties) with every candidate's terms
    ``u_m``, ``u_t``, ``u_d`` (C,), and the time since ``started`` (``time.perf_counter()``
    at the start of ``choose``) as ``choose_time_s``."""
    if len(context.candidates) == 0:
        raise ValueError("no candidate target to choose from")
    utilities = [CandidateUtility(c, float(m), float(t), float(d), float(s))
                 for c, m, t, d, s in zip(context.candidates, u_m, u_t, u_d, total)]
    best = int(np.argmin(total))
    return Decision(context.candidates[best], utilities, time.perf_counter() - started)
