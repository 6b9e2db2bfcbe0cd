"""Utilities U_D, U_T, U_M (Algorithm 2), BSP's trace(sqrt) and the planners' choices in the
situations of the paper's figures."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_em_step import straight, team_slam

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.planning.planners import (EmPlanner, PlanningContext,
                                                       allocation_utility, distance_utility,
                                                       make_planner, trace_sqrt_sum)
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.slam.team_slam import TeamSlam
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid, observation_counts

PARAMS = ExplorationParams()
HIGH_NOISE = (0.1, 0.1, 0.02)      # per-keyframe odometry sigmas [m, m, rad]
LOW_NOISE = (0.002, 0.002, 0.0005)
#: Teammates idle near the start (low uncertainty), robot 1 at (10, 53), robot 2 at (10, 47).
TEAMMATES = [straight((12.0, 53.0, np.pi), 3, step=1.0), straight((12.0, 47.0, np.pi), 3, step=1.0)]
EXPLORE = Frontier(np.array([22.0, 77.0]), FrontierType.EXPLORATION)


def loop_path() -> np.ndarray:
    """Robot 0 (alpha): from (12, 50) 28 m east, 20 m north, then 18 m back west to
    (22, 70), heading west; 30 keyframes."""
    east = straight((12.0, 50.0, 0.0), 15)
    north = straight(tuple(east[-1] + [0.0, 0.0, np.pi / 2]), 11)[1:]
    west = straight(tuple(north[-1] + [0.0, 0.0, np.pi / 2]), 10)[1:]
    return np.vstack([east, north, west])


def context(odometry_sigmas: tuple[float, float, float], landmarks: dict[int, np.ndarray],
            candidates: list[Frontier], targets: dict[int, np.ndarray]) -> PlanningContext:
    """Robot 0's decision at the end of :func:`loop_path` with idle teammates."""
    trajectories = [loop_path()] + TEAMMATES
    slam = team_slam(trajectories, landmarks, odometry_sigmas=odometry_sigmas)
    grid = OccupancyGrid(100.0, 100.0, PARAMS.map, PARAMS.sensors.sonar_max_range_m)
    grid.rebuild(np.vstack([slam.trajectory(r)[1] for r in range(3)]),
                 np.array(list(landmarks.values())).reshape(-1, 2))
    teammates = {r: (slam.pose(r, slam.latest_index(r))[:2], targets.get(r)) for r in (1, 2)}
    history = {r: [targets[r]] for r in targets}
    return PlanningContext(0, slam, grid, candidates, slam.pose(0, slam.latest_index(0)),
                           teammates, history, grid.explored_ratio())


def rendezvous_with_robot_1(target: np.ndarray) -> Frontier:
    return Frontier(target, FrontierType.RENDEZVOUS, partner_id=1)


def test_distance_utility_adds_the_waiting_penalty() -> None:
    candidates = [Frontier(np.array([3.0, 4.0]), FrontierType.EXPLORATION),
                  Frontier(np.array([0.0, -2.0]), FrontierType.RENDEZVOUS, 1, 1.5)]
    np.testing.assert_allclose(distance_utility(np.array([0.0, 0.0, 1.0]), candidates),
                               [5.0, 3.5])


def test_allocation_utility_hand_values() -> None:
    targets = np.array([[0.0, 0.0], [15.0, 0.0], [30.0, 0.0], [45.0, 0.0]])
    np.testing.assert_allclose(allocation_utility(np.array([[0.0, 0.0], [100.0, 0.0]]),
                                                  targets, 30.0), [1.5, 0.0])


def test_allocation_uses_every_teammate_target_or_the_recent_ones() -> None:
    ctx = context(LOW_NOISE, {}, [EXPLORE], {})
    near, far = EXPLORE.position, EXPLORE.position + 100.0
    history = {0: [near] * 3, 1: [near] * 2 + [far] * 5, 2: [near]}
    ctx = dataclasses.replace(ctx, target_history=history)
    # Paper (set A of all historical targets): robot 1's two old targets count, own do not.
    assert make_planner(PARAMS, "CE").choose(ctx).utilities[0].u_t == pytest.approx(3.0)
    reference = PARAMS.replace(planner={"allocation_history": 5})
    assert make_planner(reference, "CE").choose(ctx).utilities[0].u_t == pytest.approx(1.0)


def test_task_allocation_changes_the_choice_between_two_candidates() -> None:
    # Two exploration frontiers 7 m and 8 m from robot 0; the teammates' earlier targets lie
    # 2-3 m from the nearer one. EM_2 (no U_T) takes the nearer, EM_3 the other.
    nearer = Frontier(np.array([22.0, 77.0]), FrontierType.EXPLORATION)
    other = Frontier(np.array([14.0, 70.0]), FrontierType.EXPLORATION)
    ctx = context(LOW_NOISE, {}, [nearer, other], {})
    teammate_targets = {1: [np.array([24.0, 79.0]), np.array([25.0, 78.0])],
                        2: [np.array([23.0, 80.0])]}
    ctx = dataclasses.replace(ctx, target_history=teammate_targets)
    em2 = make_planner(PARAMS, "EM_2").choose(ctx)
    em3 = make_planner(PARAMS, "EM_3").choose(ctx)
    assert em2.target is nearer and em3.target is other
    expected = [sum(max(0.0, 1.0 - np.hypot(*(c.position - t)) / 30.0)
                    for ts in teammate_targets.values() for t in ts) for c in (nearer, other)]
    np.testing.assert_allclose([u.u_t for u in em3.utilities], expected)
    u_nearer, u_other = em3.utilities
    weight_t = EmPlanner(PARAMS, "EM_3").weights(ctx.explored_ratio)[1]
    assert weight_t * (u_nearer.u_t - u_other.u_t) > (
        u_other.u_m - u_nearer.u_m + 10.0 * (u_other.u_d - u_nearer.u_d)) > 0.0


def test_trace_sqrt_sum_is_rotation_invariant() -> None:
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                         [0, 0, 1]])
    diagonal = np.diag([4.0, 9.0, 16.0])
    assert trace_sqrt_sum(np.array([diagonal, rotation @ diagonal @ rotation.T])) == \
        pytest.approx(18.0)
    assert trace_sqrt_sum(np.zeros((0, 3, 3))) == 0.0


def test_make_planner_names_and_weights() -> None:
    assert make_planner(PARAMS).name == PARAMS.planner.name == "EM_3"
    assert [make_planner(PARAMS, n).name for n in ("EM_2", "CE", "BSP", "NEAREST")] == \
        ["EM_2", "CE", "BSP", "NEAREST"]
    with pytest.raises(ValueError):
        make_planner(PARAMS, "GREEDY")
    em3 = EmPlanner(PARAMS, "EM_3")
    assert em3.weights(0.25) == pytest.approx((1.0, 15.0, 10.0))
    assert EmPlanner(PARAMS, "EM_2").weights(0.25) == pytest.approx((1.0, 0.0, 10.0))
    reference = PARAMS.replace(planner={"utility_variant": "reference"})
    assert EmPlanner(reference, "EM_3").weights(0.25) == pytest.approx((1.0, 75.0, 2.5))
    assert EmPlanner(reference, "EM_2").weights(0.25) == pytest.approx((1.0, 0.0, 2.5))


def test_nearest_frontier_ignores_other_kinds() -> None:
    revisit = Frontier(np.array([22.0, 67.0]), FrontierType.REVISITING)
    decision = make_planner(PARAMS, "NEAREST").choose(
        context(LOW_NOISE, {}, [revisit, EXPLORE], {}))
    assert decision.target is EXPLORE
    assert [u.frontier for u in decision.utilities] == [revisit, EXPLORE]
    assert decision.choose_time_s > 0.0


def test_high_uncertainty_and_a_known_landmark_make_em_revisit() -> None:
    # Landmark seen at the start, now 15 m away; its frontier is 8.6 m away, the
    # exploration frontier 7 m (paper: 'Five robots navigating a 150m x 150m environment').
    revisit = Frontier(np.array([17.0, 63.0]), FrontierType.REVISITING)
    ctx = context(HIGH_NOISE, {0: np.array([16.0, 56.0])}, [EXPLORE, revisit], {})
    for name in ("EM_2", "EM_3"):
        decision = make_planner(PARAMS, name).choose(ctx)
        assert decision.target is revisit
        u_explore, u_revisit = decision.utilities
        assert u_revisit.u_m < 0.6 * u_explore.u_m
    assert make_planner(PARAMS, "CE").choose(ctx).target is EXPLORE
    assert make_planner(PARAMS, "NEAREST").choose(ctx).target is EXPLORE


def test_high_uncertainty_without_landmarks_makes_em_rendezvous() -> None:
    # No landmark: only a rendezvous with the well-localized robot 1 at its target can
    # close a loop (paper: 'Three robots explore a 200m x 200m environment').
    meet = rendezvous_with_robot_1(np.array([26.0, 58.0]))
    targets = {1: meet.position, 2: np.array([8.0, 30.0])}
    ctx = context(HIGH_NOISE, {}, [EXPLORE, meet], targets)
    decision = make_planner(PARAMS, "EM_3").choose(ctx)
    assert decision.target is meet
    assert decision.utilities[1].u_m < 0.5 * decision.utilities[0].u_m
    # The meeting point is robot 1's current target: not duplicated work for a rendezvous
    # unless the literal reading of Eq. (11) is asked for.
    assert decision.utilities[1].u_t == pytest.approx(0.0)
    literal = PARAMS.replace(planner={"allocation_counts_meeting_point": True})
    assert make_planner(literal, "EM_3").choose(ctx).utilities[1].u_t == pytest.approx(1.0)
    assert make_planner(PARAMS, "CE").choose(ctx).target is EXPLORE


def test_low_uncertainty_makes_em_take_the_nearest_exploration_frontier() -> None:
    revisit = Frontier(np.array([17.0, 63.0]), FrontierType.REVISITING)
    meet = rendezvous_with_robot_1(np.array([26.0, 58.0]))
    ctx = context(LOW_NOISE, {0: np.array([16.0, 56.0])}, [meet, revisit, EXPLORE],
                  {1: meet.position})
    for name in ("EM_2", "EM_3", "BSP"):
        decision = make_planner(PARAMS, name).choose(ctx)
        assert decision.target is EXPLORE
        spread = np.ptp([u.u_m for u in decision.utilities])
        assert spread < 1.0


def test_u_m_counts_cells_explored_in_both_maps_or_all_cells_for_the_reference() -> None:
    stay = Frontier(np.array([22.0, 70.0]), FrontierType.EXPLORATION)   # no new waypoint
    ctx = context(LOW_NOISE, {}, [stay, EXPLORE], {})
    paper = EmPlanner(PARAMS, "EM_2").map_uncertainty(ctx)
    reference = EmPlanner(PARAMS.replace(planner={"utility_variant": "reference"}),
                          "EM_2").map_uncertainty(ctx)
    # New cells seen only on the way to the unexplored frontier do not count in the paper
    # variant; the reference counts 2.88 for every cell never seen by the robot.
    assert abs(paper[1] - paper[0]) < 0.05 * paper[0]
    geometry = ctx.grid.geometry
    history = ctx.slam.trajectory(0)[1]
    seen = observation_counts(geometry, history, 7.5) > 0
    assert reference[0] == pytest.approx(2.88 * np.count_nonzero(~seen) + paper[0], rel=0.02)
    path = np.array([[22.0, 70.0 + d, np.pi / 2] for d in (2.0, 4.0, 6.0, 7.0)])
    newly_seen = np.count_nonzero((observation_counts(geometry, path, 7.5) > 0) & ~seen)
    assert reference[0] - reference[1] > 2.88 * newly_seen - 5.0


def test_robot_without_a_pose_skips_the_uncertainty_utility() -> None:
    ctx = context(LOW_NOISE, {}, [EXPLORE], {})
    empty = TeamSlam(0, 3, PARAMS.slam, np.zeros(3))
    decision = make_planner(PARAMS, "EM_3").choose(dataclasses.replace(ctx, slam=empty))
    assert decision.target is EXPLORE
    assert decision.utilities[0].u_m == 0.0


def test_history_change_tolerance_approximates_u_m_and_zero_recomputes_everything() -> None:
    landmarks = {0: np.array([20.0, 56.0]), 1: np.array([30.0, 62.0])}
    revisit = Frontier(np.array([16.0, 54.0]), FrontierType.REVISITING)   # closes the loop
    ctx = context(HIGH_NOISE, landmarks, [revisit, EXPLORE], {})
    exact = EmPlanner(PARAMS, "EM_2").map_uncertainty(ctx)

    def with_tolerance(tolerance: float) -> np.ndarray:
        params = PARAMS.replace(planner={"history_change_tolerance": tolerance})
        return EmPlanner(params, "EM_2").map_uncertainty(ctx)

    np.testing.assert_allclose(with_tolerance(0.0), exact, rtol=1e-12)
    # The loop closure shrinks the history traces by 0 (anchor) to 96 %: with a 20 %
    # tolerance the two least changed poses keep their contribution, U_M rises slightly.
    approximate = with_tolerance(0.2)
    assert exact[0] < approximate[0] < 1.001 * exact[0]
    assert approximate[1] == exact[1]        # no loop closure: nothing to approximate
    assert with_tolerance(0.5)[0] > approximate[0]
    # Everything under the tolerance: every history pose keeps its current contribution.
    assert with_tolerance(1.0)[0] > 4.0 * exact[0]
