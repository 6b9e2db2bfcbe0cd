"""Target selection: the utilities U_M, U_T, U_D and the planners EM_2, EM_3, CE, BSP, NEAREST.

All positions are in the team ``map`` frame [m]. For a candidate target ``a`` of the
deciding robot alpha (every utility is a cost: lower is better):

* ``U_D``: Euclidean distance from alpha's pose to ``a`` [m] (plus a rendezvous
  candidate's waiting penalty when ``frontiers.rendezvous_waiting_penalty``, the reference
  code's option).
* ``U_T`` (task allocation, Eq. 11): ``sum h(|a - a_beta|)`` over the targets ``a_beta``
  of every teammate (all of them, the paper's set A; the last ``allocation_history`` when
  > 0, the reference code's 5), ``h(d) = 1 - d / d_max`` below ``d_max`` and 0 beyond
  (unitless). A rendezvous candidate's meeting point is its partner's current target; that
  target is left out of the candidate's own sum unless ``allocation_counts_meeting_point``.
* ``U_M`` (Algorithm 2, EM): the sum of ``trace(Sigma_v)`` [m^2] over the cells of the
  predicted local virtual map of alpha, built from alpha's optimized historical and new
  poses ``X_new_alpha*`` (Algorithm 1, :mod:`uncertainty_propagation`), counting only the
  cells whose probability of being observed exceeds ``q_min`` both in that local map and
  in the current inter-robot map (the team occupancy grid). ``utility_variant =
  'reference'`` sums over all cells instead (never-observed cells add the prior trace,
  2.88) and uses the reference implementation's weights (below).
* ``U_M_bsp`` (BSP): ``sum trace(sqrt(Sigma_x))`` over all robots' predicted waypoints
  ``X_predict* U X_next*`` (matrix square root; units mix m and rad as in the paper).

Planners (``PlannerParams``): EM_2 ``1 U_M + 0 U_T + 10 U_D``; EM_3 ``1 U_M + 20 (1 - r)
U_T + 10 U_D`` (``r``: explored ratio); CE ``1 U_D + 10 U_T``; BSP ``5 U_D + 1 U_M_bsp``;
NEAREST: the nearest exploration frontier (the nearest frontier rule; not the "Next
Frontier" method the paper cites). Reference EM weights: ``U_M + 100 max(1 - r, 0) U_T
+ 10 r U_D`` (``U_T`` weight kept 0 for EM_2).

What a planner gets and returns is in :mod:`planner_api`; each planner is registered by name
in the entry-point group ``em_exploration_ros.planners`` (setup.py), through which
:func:`make_planner` finds it and any installed plugin (docs/plugins.md).
"""
from __future__ import annotations

import logging
import time
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from em_exploration_ros.core.params import ExplorationParams, PlannerParams
from em_exploration_ros.core.planner_registry import planner_entry_points
from em_exploration_ros.core.planning.em_scenario import (ScenarioBuilder, TeamSnapshot,
                                                          VirtualNoise, VirtualScenario)
from em_exploration_ros.core.planning.em_step import DecisionFactorization
from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.planning.planner_api import (Decision, Planner, PlannerFactory,
                                                          PlanningContext, decide)
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.virtual_map.cell_uncertainty import (CellObservations,
                                                                  CovarianceIntersectionSums,
                                                                  observation_confidence)

FloatArray = NDArray[np.float64]

_LOG = logging.getLogger(__name__)

#: Relative covariance changes up to this are round-off (``history_change_tolerance``
#: at or below it is the exact U_M).
_ROUND_OFF = 1e-12


def distance_utility(robot_xy: np.ndarray, candidates: Sequence[Frontier]) -> FloatArray:
    """``U_D`` (C,) [m]: distance to each candidate plus its rendezvous waiting penalty (0
    unless ``frontiers.rendezvous_waiting_penalty``)."""
    positions = np.array([c.position for c in candidates]).reshape(-1, 2)
    penalty = np.array([c.waiting_penalty_m for c in candidates])
    return np.linalg.norm(positions - np.asarray(robot_xy, dtype=float)[:2], axis=1) + penalty


def allocation_utility(candidate_xy: np.ndarray, teammate_targets: np.ndarray,
                       d_max_m: float) -> FloatArray:
    """``U_T`` (C,): ``sum_j h(|a - a_j|)`` over teammate targets (T, 2) for candidates (C, 2)."""
    candidate_xy = np.asarray(candidate_xy, dtype=float).reshape(-1, 2)
    teammate_targets = np.asarray(teammate_targets, dtype=float).reshape(-1, 2)
    distance = np.linalg.norm(candidate_xy[:, None, :] - teammate_targets[None, :, :], axis=2)
    return np.sum(np.clip(1.0 - distance / d_max_m, 0.0, None), axis=1)


def trace_sqrt_sum(covariances: np.ndarray) -> float:
    """``sum_i trace(sqrt(Sigma_i))`` of symmetric PSD matrices ``(N, d, d)``: the sum of
    the square roots of their eigenvalues (negative round-off clipped to 0)."""
    covariances = np.asarray(covariances, dtype=float)
    if covariances.size == 0:
        return 0.0
    return float(np.sum(np.sqrt(np.clip(np.linalg.eigvalsh(covariances), 0.0, None))))


def teammate_allocation_utility(context: PlanningContext, params: PlannerParams) -> FloatArray:
    """``U_T`` (C,) of ``context.candidates`` over the teammates' target histories.

    Every teammate's targets count (its last ``params.allocation_history`` when > 0). A
    rendezvous candidate's own sum skips its partner's current (latest) target, the meeting
    point itself, unless ``params.allocation_counts_meeting_point``.
    """
    positions = np.array([c.position for c in context.candidates]).reshape(-1, 2)
    u_t = np.zeros(len(positions))
    count = params.allocation_history
    for robot, history in context.target_history.items():
        targets = np.array(list(history)[-count:] if count > 0 else list(history),
                           dtype=float).reshape(-1, 2)
        if robot == context.robot_id or len(targets) == 0:
            continue
        u_t += allocation_utility(positions, targets, params.allocation_d_max_m)
        if not params.allocation_counts_meeting_point:
            meets = np.array([c.partner_id == robot for c in context.candidates], dtype=bool)
            u_t[meets] -= allocation_utility(positions[meets], targets[-1:],
                                             params.allocation_d_max_m)
    return u_t


def _utility_terms(context: PlanningContext,
                   params: PlannerParams) -> tuple[FloatArray, FloatArray]:
    """``U_T`` (C,) and ``U_D`` (C,) of the candidates."""
    return (teammate_allocation_utility(context, params),
            distance_utility(context.robot_pose, context.candidates))


class NearestFrontierPlanner:
    """NEAREST: the nearest exploration candidate (the nearest candidate if there is none)."""

    name = "NEAREST"

    def choose(self, context: PlanningContext) -> Decision:
        started = time.perf_counter()
        u_d = distance_utility(context.robot_pose, context.candidates)
        exploring = np.array([c.kind == FrontierType.EXPLORATION for c in context.candidates])
        total = np.where(exploring, u_d, np.inf) if exploring.any() else u_d
        nan = np.full(len(u_d), np.nan)
        return decide(context, nan, nan, u_d, total, started)


class CoordinatedPlanner:
    """CE (Burgard et al.): ``lambda_0 U_D + lambda_1 U_T``."""

    name = "CE"

    def __init__(self, params: PlannerParams) -> None:
        self.params = params

    def choose(self, context: PlanningContext) -> Decision:
        started = time.perf_counter()
        u_t, u_d = _utility_terms(context, self.params)
        weight_d, weight_t = self.params.ce_lambdas
        return decide(context, np.full(len(u_d), np.nan), u_t, u_d,
                       weight_d * u_d + weight_t * u_t, started)


class _PropagationPlanner:
    """Shared setup of the planners that run Algorithm 1 for every candidate."""

    def __init__(self, params: ExplorationParams) -> None:
        self.params = params

    def _scenarios(self, context: PlanningContext, with_history: bool
                   ) -> tuple[TeamSnapshot, list[VirtualScenario], DecisionFactorization] | None:
        """Snapshot, one scenario per candidate and the decision's factorization (alpha's
        history tracked for EM, the predicted waypoints otherwise); None while the deciding
        robot has no pose in the graph."""
        if context.slam.latest_index(context.robot_id) is None:
            _LOG.warning("robot %d has no SLAM pose yet; uncertainty utility skipped",
                         context.robot_id)
            return None
        snapshot = TeamSnapshot.from_slam(context.slam, context.robot_id)
        noise = VirtualNoise(context.slam.noise, self.params.sensors, self.params.motion)
        targets = {robot: target for robot, (_, target) in context.teammates.items()}
        builder = ScenarioBuilder(snapshot, targets, noise,
                                  self.params.planner.virtual_waypoint_spacing_m,
                                  self.params.sensors.sonar_max_range_m)
        scenarios = builder.build_all(np.array([c.position for c in context.candidates]))
        boundary = sorted(set().union(*(s.boundary_keys for s in scenarios)))
        factorization = DecisionFactorization(snapshot, builder.predicted, boundary,
                                              with_history=with_history,
                                              with_predicted=not with_history)
        return snapshot, scenarios, factorization


class BspPlanner(_PropagationPlanner):
    """BSP (Indelman): ``lambda_0 U_D + lambda_1 sum trace(sqrt(Sigma_x))`` over the
    predicted waypoints of every robot."""

    name = "BSP"

    def choose(self, context: PlanningContext) -> Decision:
        started = time.perf_counter()
        u_t, u_d = _utility_terms(context, self.params.planner)
        prepared = self._scenarios(context, with_history=False)
        if prepared is None:
            u_m = np.zeros(len(u_d))
        else:
            _, scenarios, factorization = prepared
            results = factorization.propagate_all(scenarios)
            u_m = np.array([trace_sqrt_sum(r.predicted_covariances)
                            + trace_sqrt_sum(r.next_covariances) for r in results])
        weight_d, weight_m = self.params.planner.bsp_lambdas
        return decide(context, u_m, np.full(len(u_d), np.nan), u_d,
                       weight_d * u_d + weight_m * u_m, started)


class EmPlanner(_PropagationPlanner):
    """EM_2 / EM_3: ``lambda_0 U_M + lambda_1 U_T + lambda_2 U_D`` with ``U_M`` by
    Algorithm 2 on the EM-propagated (Algorithm 1) covariances."""

    def __init__(self, params: ExplorationParams, name: str) -> None:
        super().__init__(params)
        if name not in ("EM_2", "EM_3"):
            raise ValueError(f"unknown EM planner {name!r}")
        self.name = name

    def weights(self, explored_ratio: float) -> tuple[float, float, float]:
        """``(lambda_0, lambda_1, lambda_2)`` at the given explored ratio."""
        planner = self.params.planner
        lambdas = planner.em2_lambdas if self.name == "EM_2" else planner.em3_lambdas
        if planner.utility_variant == "reference":
            weight_t = 100.0 * max(1.0 - explored_ratio, 0.0) if lambdas[1] else 0.0
            return 1.0, weight_t, 10.0 * explored_ratio
        weight_t = lambdas[1] * (1.0 - explored_ratio) if self.name == "EM_3" else lambdas[1]
        return lambdas[0], weight_t, lambdas[2]

    def choose(self, context: PlanningContext) -> Decision:
        started = time.perf_counter()
        u_t, u_d = _utility_terms(context, self.params.planner)
        u_m = self.map_uncertainty(context)
        weight_m, weight_t, weight_d = self.weights(context.explored_ratio)
        return decide(context, u_m, u_t, u_d,
                       weight_m * u_m + weight_t * u_t + weight_d * u_d, started)

    def map_uncertainty(self, context: PlanningContext) -> FloatArray:
        """``U_M`` (C,) [m^2] of every candidate (Algorithm 2)."""
        prepared = self._scenarios(context, with_history=True)
        if prepared is None:
            return np.zeros(len(context.candidates))
        snapshot, scenarios, factorization = prepared
        grid, planner, sensors = context.grid, self.params.planner, self.params.sensors
        reference = planner.utility_variant == "reference"
        # The cells U_M sums over: all of them (reference), or those the team has observed
        # (paper; whether alpha's own counts make a cell local is decided per candidate).
        # Pairs of other cells are never built and the sums hold only these cells, in
        # map order, so U_M is the same to the last bit as with whole-map sums.
        team_probability = grid.probability().ravel()
        counted = (np.ones(len(team_probability), dtype=bool) if reference else
                   np.maximum(team_probability, 1.0 - team_probability) > planner.q_min)
        num_cells = int(np.count_nonzero(counted))
        slots = np.full(len(counted), -1, dtype=np.int64)
        slots[counted] = np.arange(num_cells)
        history = CellObservations.from_poses(grid.geometry, snapshot.history_poses, sensors,
                                              "body", slots)
        history_counts = np.bincount(history.flat_cell, minlength=num_cells)
        current = factorization.tracked_covariances
        current_sums = history.intersection_sums(current, num_cells)
        current_traces = np.trace(current, axis1=1, axis2=2)
        new_poses = CellObservations.from_poses(
            grid.geometry, np.vstack([s.next.waypoints for s in scenarios]), sensors, "body",
            slots)
        results = factorization.propagate_all(scenarios)
        # Every candidate's own waypoints in one pass: set c holds candidate c's.
        candidate_of_pose = np.repeat(np.arange(len(scenarios)),
                                      [len(s.next.waypoints) for s in scenarios])
        new_sums = new_poses.grouped_intersection_sums(
            np.concatenate([r.next_covariances for r in results]), candidate_of_pose,
            len(scenarios), num_cells)
        history_sums = CovarianceIntersectionSums.stack([
            _history_sums(history, current, current_sums, current_traces,
                          result.history_covariances, num_cells,
                          planner.history_change_tolerance) for result in results])
        sums = history_sums + new_sums
        traces = sums.covariance_traces()
        if reference:
            prior_trace = 2.0 * self.params.map.virtual_landmark_prior_sigma_m ** 2
            unobserved = np.count_nonzero(~sums.observed, axis=1)
            return np.array([np.sum(row) for row in traces]) + prior_trace * unobserved
        counts = history_counts + new_poses.grouped_counts(candidate_of_pose, len(scenarios),
                                                           num_cells)
        local = observation_confidence(counts, self.params.map) > planner.q_min
        return np.array([np.sum(row[mask]) for row, mask in zip(traces, local)])


def _history_sums(history: CellObservations, current: FloatArray,
                  current_sums: CovarianceIntersectionSums, current_traces: FloatArray,
                  propagated: FloatArray, num_cells: int,
                  tolerance: float) -> CovarianceIntersectionSums:
    """Covariance-intersection sums of alpha's history poses with their ``propagated``
    covariances (K, 3, 3), given those of the ``current`` ones.

    Poses whose trace shrinks by at most ``tolerance`` (a fraction) keep their current
    contribution. Candidates without a loop closure leave every pose unchanged; otherwise
    everything is recomputed when ``tolerance`` is round-off (the default, exact), and only
    the changed poses' contributions are replaced for a larger (approximating) tolerance.
    """
    reduction = current_traces - np.trace(propagated, axis1=1, axis2=2)
    changed = reduction > tolerance * current_traces
    if not np.any(changed):
        return current_sums
    if tolerance <= _ROUND_OFF or np.all(changed):
        return history.intersection_sums(propagated, num_cells)
    subset = history.of_poses(changed)
    return (current_sums - subset.intersection_sums(current, num_cells)
            + subset.intersection_sums(propagated, num_cells))


def make_planner(params: ExplorationParams, name: str | None = None) -> Planner:
    """The planner called ``name`` (default ``params.planner.name``), made by the factory its
    entry point names (``core.planner_registry``): a built-in one (EM_2, EM_3, CE, BSP,
    NEAREST) or an installed plugin's. ``ValueError`` for a name no installed planner has
    (listing the installed ones) or a plugin that cannot be loaded."""
    name = params.planner.name if name is None else name
    entry_points = planner_entry_points()
    if name not in entry_points:
        installed = ", ".join(entry_points) or "none (pip install -e . registers the built-in ones)"
        raise ValueError(f"unknown planner {name!r}; installed: {installed}")
    try:
        factory: PlannerFactory = entry_points[name].load()
    except Exception as error:  # a plugin's import can fail in any way
        raise ValueError(f"planner {name!r}: cannot load {entry_points[name].value} "
                         f"({type(error).__name__}: {error})") from error
    return factory(params)


def em2_planner(params: ExplorationParams) -> EmPlanner:
    """EM_2's factory (its entry point)."""
    return EmPlanner(params, "EM_2")


def em3_planner(params: ExplorationParams) -> EmPlanner:
    """EM_3's factory (its entry point)."""
    return EmPlanner(params, "EM_3")


def ce_planner(params: ExplorationParams) -> CoordinatedPlanner:
    """CE's factory (its entry point)."""
    return CoordinatedPlanner(params.planner)


def bsp_planner(params: ExplorationParams) -> BspPlanner:
    """BSP's factory (its entry point)."""
    return BspPlanner(params)


def nearest_planner(params: ExplorationParams) -> NearestFrontierPlanner:
    """NEAREST's factory (its entry point; it has no parameters)."""
    del params
    return NearestFrontierPlanner()
