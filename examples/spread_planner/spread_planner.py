"""SPREAD, an example planner plugin of em_exploration_ros (docs/plugins.md).

The nearest candidate, kept away from the teammates: each candidate costs its distance U_D
[m] plus ``SPREAD_WEIGHT_M`` for every teammate whose current target lies within
``CROWD_RADIUS_M`` of it (its U_T here: a count). Registered in pyproject.toml under the
entry-point group ``em_exploration_ros.planners`` as ``SPREAD = spread_planner:SpreadPlanner``.
"""
from __future__ import annotations

import time

import numpy as np

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.planner_api import Decision, PlanningContext, decide
from em_exploration_ros.core.planning.planners import distance_utility

#: A teammate's current target this close to a candidate crowds it [m].
CROWD_RADIUS_M = 15.0
#: Cost of each crowding teammate, in metres of travel.
SPREAD_WEIGHT_M = 20.0


class SpreadPlanner:
    """The planner; the class is its own factory (it takes the run's parameters)."""

    name = "SPREAD"

    def __init__(self, params: ExplorationParams) -> None:
        self.params = params  # unused here: a planner may read any parameter group

    def choose(self, context: PlanningContext) -> Decision:
        """The candidate of least ``U_D + SPREAD_WEIGHT_M * crowding``."""
        started = time.perf_counter()
        positions = np.array([c.position for c in context.candidates]).reshape(-1, 2)
        u_d = distance_utility(context.robot_pose, context.candidates)
        targets = np.array([target for _, target in context.teammates.values()
                            if target is not None], dtype=float).reshape(-1, 2)
        distance = np.linalg.norm(positions[:, None, :] - targets[None, :, :], axis=2)
        crowding = np.count_nonzero(distance < CROWD_RADIUS_M, axis=1).astype(float)
        unused = np.full(len(u_d), np.nan)  # no map-uncertainty term
        return decide(context, unused, crowding, u_d, u_d + SPREAD_WEIGHT_M * crowding,
                      started)
