"""The re-solve oracle of Algorithm 1: the EM step's covariances computed the direct way.

Copies the team graph, adds every virtual factor and waypoint of a scenario
(``em_scenario``) and reads ``gtsam.Marginals``. Its cost grows with the history, so the
planners use ``em_step.DecisionFactorization``; this is the reference it is tested
against and the oracle column of ``em-bench latency``.
"""
from __future__ import annotations

from typing import Sequence

import gtsam
import numpy as np
from numpy.typing import NDArray

from em_exploration_ros.core.planning.em_scenario import (TeamSnapshot, VirtualScenario,
                                                          graph_with_virtual)
from em_exploration_ros.core.planning.em_step import PropagationResult

FloatArray = NDArray[np.float64]


def propagate_oracle(snapshot: TeamSnapshot, scenario: VirtualScenario) -> PropagationResult:
    """Algorithm 1 the direct way: copy the graph, add every virtual factor and waypoint,
    and read ``gtsam.Marginals`` (the test oracle; its cost grows with the history)."""
    marginals = gtsam.Marginals(*graph_with_virtual(snapshot, scenario.predicted, scenario.next))

    def covariances(keys: Sequence[int]) -> FloatArray:
        return np.array([marginals.marginalCovariance(int(k)) for k in keys]).reshape(-1, 3, 3)

    return PropagationResult(covariances(snapshot.history_keys),
                             covariances(scenario.predicted.waypoint_keys),
                             covariances(scenario.next.waypoint_keys))
