"""Algorithm 1 (EM step): virtual paths and measurements, and the fast low-rank
propagation against the direct re-solve oracle."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from em_exploration_ros.core.geometry import range_bearing
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.em_oracle import propagate_oracle
from em_exploration_ros.core.planning.em_scenario import (ScenarioBuilder, TeamSnapshot,
                                                          VirtualNoise, graph_with_virtual,
                                                          virtual_waypoints)
from em_exploration_ros.core.planning.em_step import (DENSE_HUB_MAX_DIM, DecisionFactorization,
                                                      _backward_scan, _sparse_selected_inverse)
from em_exploration_ros.core.records.readings import OdometryReading
from em_exploration_ros.core.slam.synthetic_team import exact_team_slam
from em_exploration_ros.core.slam.team_slam import (OdometryAccumulator, TeamSlam, is_landmark_key,
                                                    pose_key)
from em_exploration_ros.core.world.sensors import odometry_covariance_per_step

PARAMS = ExplorationParams()
#: Block-relative agreement required between the fast path and the oracle. Both solve
#: the same linear problem; the 1e-6 rad prior of the gauge limits either to ~1e-10.
ORACLE_TOLERANCE = 1e-9


def straight(start: tuple[float, float, float], count: int, step: float = 2.0,
             turn: float = 0.0) -> np.ndarray:
    """``count`` keyframe poses (K, 3) driving ``step`` metres per keyframe, turning
    ``turn`` radians before each step."""
    poses = [np.array(start, dtype=float)]
    for _ in range(count - 1):
        pose = poses[-1].copy()
        pose[2] += turn
        pose[:2] += step * np.array([np.cos(pose[2]), np.sin(pose[2])])
        poses.append(pose)
    return np.array(poses)


def team_slam(trajectories: list[np.ndarray], landmarks: dict[int, np.ndarray],
              odometry_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.01),
              meetings: tuple[int, ...] = (), robot_id: int = 0,
              params: ExplorationParams = PARAMS) -> TeamSlam:
    """A TeamSlam fed with exact measurements of scripted simultaneous trajectories;
    teammates read each other at keyframe 0 and at the indices in ``meetings``; odometry
    carries the given per-keyframe sigmas, so the uncertainty grows along paths."""
    return exact_team_slam(trajectories, landmarks, np.diag(np.square(odometry_sigmas)),
                           params, meetings, robot_id)


def _block_error(fast: np.ndarray, oracle: np.ndarray) -> float:
    """Largest relative (Frobenius) difference between corresponding 3x3 blocks."""
    if len(oracle) == 0:
        return 0.0
    return float(np.max(np.linalg.norm(fast - oracle, axis=(1, 2))
                        / np.linalg.norm(oracle, axis=(1, 2))))


@pytest.fixture(scope="module")
def team() -> dict:
    """Three robots leaving x = 10 m eastwards; robot 0 saw landmark 0 at the start and
    drove 48 m straight on; robot 1 curves north, robot 2 south."""
    trajectories = [straight((10.0, 50.0, 0.0), 25), straight((10.0, 53.0, 0.0), 25, turn=0.06),
                    straight((10.0, 47.0, 0.0), 25, turn=-0.06)]
    landmarks = {0: np.array([14.0, 55.0]), 1: np.array([40.0, 75.0]),
                 2: np.array([60.0, 50.0])}
    slam = team_slam(trajectories, landmarks)
    snapshot = TeamSnapshot.from_slam(slam, 0)
    noise = VirtualNoise(slam.noise, PARAMS.sensors, PARAMS.motion)
    targets = {1: trajectories[1][-1][:2] + np.array([5.0, 8.0]),
               2: trajectories[2][-1][:2] + np.array([10.0, -5.0])}
    builder = ScenarioBuilder(snapshot, targets, noise, 2.0, PARAMS.sensors.sonar_max_range_m)
    return dict(slam=slam, snapshot=snapshot, builder=builder, targets=targets,
                trajectories=trajectories)


def test_virtual_waypoints_are_evenly_spaced_and_end_at_the_target() -> None:
    waypoints = virtual_waypoints([0.0, 0.0, 1.0], [5.0, 0.0], 2.0)
    np.testing.assert_allclose(waypoints, [[5 / 3, 0, 0], [10 / 3, 0, 0], [5, 0, 0]], atol=1e-12)
    diagonal = virtual_waypoints([1.0, 1.0, 0.0], [7.0, 9.0], 2.0)
    assert len(diagonal) == 5
    np.testing.assert_allclose(diagonal[-1, :2], [7.0, 9.0])
    np.testing.assert_allclose(diagonal[:, 2], np.arctan2(8.0, 6.0))
    assert virtual_waypoints([1.0, 1.0, 0.0], None, 2.0).shape == (0, 3)
    assert virtual_waypoints([1.0, 1.0, 0.0], [1.0, 1.0], 2.0).shape == (0, 3)


@pytest.mark.parametrize("length_m", [2.0, 3.45])
def test_virtual_odometry_noise_matches_the_slam_keyframe_model(length_m: float) -> None:
    # The SLAM accumulates per-step odometry noise over the steps of a keyframe; a virtual
    # odometry over length_m gets the same covariance for as many 0.2 m steps.
    slam = TeamSlam(0, 1, PARAMS.slam, np.zeros(3))
    noise = VirtualNoise(slam.noise, PARAMS.sensors, PARAMS.motion)
    steps = round(length_m / (PARAMS.motion.speed_mps * PARAMS.motion.time_step_s))
    step = length_m / steps
    accumulator = OdometryAccumulator()
    for _ in range(steps):
        accumulator.add(OdometryReading(np.array([step, 0.0, 0.0]),
                                        odometry_covariance_per_step(step, False, PARAMS.sensors)))
    delta, covariance = accumulator.take()
    root, longer = noise.odometry([delta, [2 * steps * step, 0.0, 0.0]])
    expected = slam.noise.odometry(delta, covariance).information()
    np.testing.assert_allclose(root.T @ root, expected, rtol=1e-9)
    # Twice the steps: twice the heading variance, more than twice the lateral variance
    # (heading errors act through a growing lever arm).
    # Each factor's covariance also holds the SLAM's floor once (slam.covariance_floor_sigma).
    floor = PARAMS.slam.covariance_floor_sigma ** 2
    short_cov = np.linalg.inv(root.T @ root) - floor * np.eye(3)
    long_cov = np.linalg.inv(longer.T @ longer) - floor * np.eye(3)
    assert long_cov[2, 2] == pytest.approx(2 * short_cov[2, 2], rel=1e-6)
    assert long_cov[0, 0] == pytest.approx(2 * short_cov[0, 0], rel=1e-6)
    assert long_cov[1, 1] > 2.05 * short_cov[1, 1]


def test_scenario_paths_measurements_and_keys(team: dict) -> None:
    builder, snapshot, targets = team["builder"], team["snapshot"], team["targets"]
    # Back west to landmark 0, seen at the start: a landmark loop closure.
    scenario = builder.build(np.array([20.0, 55.0]))
    own = scenario.next
    assert np.all(own.waypoint_robots == 0)
    np.testing.assert_allclose(own.waypoints[-1, :2], [20.0, 55.0])
    assert own.waypoint_keys[0] == pose_key(0, 25)
    assert np.all(np.diff(own.waypoint_keys) == 1)
    assert len(own.odometry.key1) == len(own.waypoint_keys)
    assert own.odometry.key1[0] == snapshot.start_keys[0]
    seen = own.landmark_observations
    assert set(seen.landmark_key.tolist()) == {snapshot.landmark_keys[0], snapshot.landmark_keys[2]}
    distance = np.hypot(*(seen.point - seen.pose[:, :2]).T)
    assert np.all(distance <= 7.5)
    np.testing.assert_allclose(seen.range, distance)
    predicted = scenario.predicted
    for robot in (1, 2):
        path = predicted.waypoints[predicted.waypoint_robots == robot]
        np.testing.assert_allclose(path[-1, :2], targets[robot])
    assert snapshot.start_keys[0] in scenario.boundary_keys
    assert len(own.robot_observations.key1) == 0


def test_rendezvous_candidate_creates_inter_robot_readings(team: dict) -> None:
    builder, targets = team["builder"], team["targets"]
    scenario = builder.build(targets[1])
    readings = scenario.next.robot_observations
    assert len(readings.key1) > 0
    last_alpha = scenario.next.waypoint_keys[-1]
    last_partner = scenario.predicted.waypoint_keys[scenario.predicted.waypoint_robots == 1][-1]
    assert (last_alpha, last_partner) in set(zip(readings.key1.tolist(), readings.key2.tolist()))
    assert last_partner in scenario.boundary_keys
    np.testing.assert_allclose(readings.sqrt_information[0],
                               np.diag(1 / np.array(PARAMS.slam.virtual_robot_obs_sigmas)))


@pytest.mark.parametrize("dense_hub_max_dim", [DENSE_HUB_MAX_DIM, 0], ids=["hub", "sparse"])
@pytest.mark.parametrize("with_history,with_predicted", [(True, False), (False, True)])
def test_fast_path_equals_the_oracle(team: dict, with_history: bool,
                                     with_predicted: bool, dense_hub_max_dim: int) -> None:
    builder, snapshot = team["builder"], team["snapshot"]
    candidates = [np.array([20.0, 55.0]),            # landmark loop closure
                  team["targets"][1],                 # rendezvous with robot 1
                  np.array([65.0, 44.0]),             # exploration past landmark 2
                  team["trajectories"][0][-1][:2]]    # stay: no own waypoint
    scenarios = [builder.build(c) for c in candidates]
    boundary = sorted(set().union(*(s.boundary_keys for s in scenarios)))
    factorization = DecisionFactorization(snapshot, builder.predicted, boundary,
                                          with_history, with_predicted, dense_hub_max_dim)
    assert factorization.sparse == (dense_hub_max_dim == 0)
    # All candidates in one batch (paths of different lengths, one of none) and each
    # alone give the oracle's covariances.
    alone = [factorization.propagate(scenario) for scenario in scenarios]
    for scenario, fast, single in zip(scenarios, factorization.propagate_all(scenarios), alone):
        for part in ("history_covariances", "predicted_covariances", "next_covariances"):
            np.testing.assert_allclose(getattr(fast, part), getattr(single, part),
                                       rtol=1e-12, atol=1e-15)
        oracle = propagate_oracle(snapshot, scenario)
        assert _block_error(fast.next_covariances, oracle.next_covariances) < ORACLE_TOLERANCE
        if with_history:
            assert _block_error(fast.history_covariances,
                                oracle.history_covariances) < ORACLE_TOLERANCE
        else:
            assert fast.history_covariances.shape == (0, 3, 3)
        if with_predicted:
            assert _block_error(fast.predicted_covariances,
                                oracle.predicted_covariances) < ORACLE_TOLERANCE


@pytest.mark.parametrize("dense_hub_max_dim", [DENSE_HUB_MAX_DIM, 0], ids=["hub", "sparse"])
def test_history_marginals_and_cross_covariances_are_blocks_of_the_dense_inverse(
        dense_hub_max_dim: int) -> None:
    """Meetings link alpha's poses through the teammates' eliminated paths, so the history
    splits into chain poses (recursion) and hub poses (dense block); both give the blocks
    of the inverse of the whole linearized information matrix, and so does the sparse
    selected inversion that replaces them when the hub is large."""
    trajectories = [straight((10.0, 50.0, 0.0), 25), straight((10.0, 53.0, 0.0), 25),
                    straight((10.0, 47.0, 0.0), 25, turn=-0.02)]
    landmarks = {0: np.array([14.0, 55.0]), 1: np.array([40.0, 58.0])}
    slam = team_slam(trajectories, landmarks, meetings=(8, 16))
    snapshot = TeamSnapshot.from_slam(slam, 0)
    builder = ScenarioBuilder(snapshot, {1: np.array([70.0, 60.0]), 2: np.array([70.0, 40.0])},
                              VirtualNoise(slam.noise, PARAMS.sensors, PARAMS.motion), 2.0,
                              PARAMS.sensors.sonar_max_range_m)
    scenarios = [builder.build(np.array([20.0, 55.0])), builder.build(np.array([62.0, 30.0]))]
    boundary = sorted(set().union(*(s.boundary_keys for s in scenarios)))
    factorization = DecisionFactorization(snapshot, builder.predicted, boundary,
                                          dense_hub_max_dim=dense_hub_max_dim)
    assert factorization.sparse == (dense_hub_max_dim == 0)
    graph, values = graph_with_virtual(snapshot, builder.predicted)
    linear = graph.linearize(values)
    keys = sorted(set(linear.keyVector()))
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    information, _ = linear.hessian(ordering)
    covariance = np.linalg.inv(information)
    dims = [2 if is_landmark_key(key) else 3 for key in keys]
    start = dict(zip(keys, np.cumsum([0] + dims[:-1]).tolist()))

    def columns(key_list: list[int]) -> np.ndarray:
        return np.concatenate([np.arange(start[k], start[k] + dims[keys.index(k)])
                               for k in key_list])

    chain = factorization._chain_keys(factorization._marginalize_untracked(linear))
    meeting_poses = {pose_key(0, 8), pose_key(0, 16)}
    assert meeting_poses <= set(snapshot.history_keys) - set(chain)  # hub poses
    assert len(chain) > len(snapshot.history_keys) // 2                # chain poses
    boundary_columns = columns(list(factorization.boundary_keys))
    expected_boundary = covariance[np.ix_(boundary_columns, boundary_columns)]
    assert np.linalg.norm(factorization.boundary_covariance - expected_boundary) \
        < ORACLE_TOLERANCE * np.linalg.norm(expected_boundary)
    for index, key in enumerate(snapshot.history_keys):
        own = columns([key])
        expected = covariance[np.ix_(own, own)]
        assert np.linalg.norm(factorization.tracked_covariances[index] - expected) \
            < ORACLE_TOLERANCE * np.linalg.norm(expected)
        cross = covariance[np.ix_(own, boundary_columns)]
        assert np.linalg.norm(factorization.tracked_cross[index] - cross) \
            < ORACLE_TOLERANCE * np.linalg.norm(expected)


@pytest.mark.parametrize("sandwich", [False, True])
def test_backward_scan_solves_the_recursion_it_stands_for(sandwich: bool) -> None:
    """Recursive doubling gives what the step-by-step recursion gives, also across zero
    gains (the ends of chain segments) and for lengths that are not powers of two."""
    rng = np.random.default_rng(3)
    for count in (1, 2, 7, 40):
        gains = 0.5 * rng.normal(size=(count, 3, 3))
        gains[rng.random(count) < 0.2] = 0.0
        terms = rng.normal(size=(count, 3, 3 if sandwich else 5))
        expected, later = np.zeros_like(terms), np.zeros(terms.shape[1:])
        for k in range(count - 1, -1, -1):
            reached = gains[k] @ later @ gains[k].T if sandwich else gains[k] @ later
            later = expected[k] = terms[k] + reached
        np.testing.assert_allclose(_backward_scan(gains, terms, sandwich), expected,
                                   rtol=1e-12, atol=1e-12)


def test_loop_closure_shrinks_the_history_and_exploration_does_not(team: dict) -> None:
    builder, snapshot = team["builder"], team["snapshot"]
    revisit = builder.build(np.array([20.0, 55.0]))
    explore = builder.build(np.array([62.0, 38.0]))
    boundary = sorted(set(revisit.boundary_keys) | set(explore.boundary_keys))
    factorization = DecisionFactorization(snapshot, builder.predicted, boundary)
    before = factorization.tracked_covariances
    after_revisit = factorization.propagate(revisit).history_covariances
    after_explore = factorization.propagate(explore).history_covariances
    # One landmark leaves the rotation about it free, so the closure removes about a
    # quarter of the latest pose's uncertainty here; exploring removes nothing.
    latest = -1
    assert np.trace(after_revisit[latest]) < 0.8 * np.trace(before[latest])
    assert np.trace(after_explore[latest]) > 0.99 * np.trace(before[latest])
    assert np.sum(np.trace(after_revisit, axis1=1, axis2=2)) < 0.9 * np.sum(
        np.trace(before, axis1=1, axis2=2))
    # Measurements only add information: no covariance grows.
    for after in (after_revisit, after_explore):
        assert np.all(np.linalg.eigvalsh(before - after) > -1e-12)
    # The means do not move: virtual readings equal their predictions.
    reading = revisit.next.landmark_observations
    distance, bearing = range_bearing(reading.pose, reading.point)
    np.testing.assert_allclose(reading.range, distance)
    np.testing.assert_allclose(reading.bearing, bearing)


def test_boundary_must_cover_the_scenario(team: dict) -> None:
    builder, snapshot = team["builder"], team["snapshot"]
    scenario = builder.build(np.array([20.0, 55.0]))
    factorization = DecisionFactorization(snapshot, builder.predicted,
                                          [snapshot.start_keys[0]])
    with pytest.raises(ValueError, match="outside the boundary"):
        factorization.propagate(scenario)


def _expected_readings(timelines: list[tuple[np.ndarray, np.ndarray]],
                       pairs: list[tuple[int, int]], reach_m: float) -> list[tuple[int, int]]:
    """Inter-robot readings by their definition, one step at a time: timelines (keys,
    poses) with the latest graph pose first; a robot past its end waits there."""
    readings = []
    for a, b in pairs:
        (keys_a, poses_a), (keys_b, poses_b) = timelines[a], timelines[b]
        for k in range(1, max(len(keys_a), len(keys_b))):
            i, j = min(k, len(keys_a) - 1), min(k, len(keys_b) - 1)
            if (i or j) and np.hypot(*(poses_b[j, :2] - poses_a[i, :2])) <= reach_m:
                readings.append((int(keys_a[i]), int(keys_b[j])))
    return readings


def test_scenarios_built_together_equal_scenarios_built_alone_and_the_definition() -> None:
    # Four robots leaving together: 1 and 2 will cross each other's way, 3 stays idle.
    trajectories = [straight((10.0, 50.0, 0.0), 6), straight((12.0, 53.0, 0.3), 6),
                    straight((12.0, 47.0, -0.3), 6), straight((11.0, 51.0, 0.0), 6, step=0.5)]
    slam = team_slam(trajectories, {0: np.array([14.0, 55.0]), 1: np.array([26.0, 50.0])})
    snapshot = TeamSnapshot.from_slam(slam, 0)
    noise = VirtualNoise(slam.noise, PARAMS.sensors, PARAMS.motion)
    reach = PARAMS.sensors.sonar_max_range_m
    mate_targets = {1: np.array([30.0, 40.0]), 2: np.array([30.0, 60.0]), 3: None}
    builder = ScenarioBuilder(snapshot, mate_targets, noise, 2.0, reach)
    start = snapshot.start_poses[0]
    candidates = np.array([[40.0, 60.0], start[:2], [12.0, 52.0], [80.0, 20.0]])
    together = builder.build_all(candidates)
    alone = [builder.build(c) for c in candidates]
    for one, other in zip(together, alone):
        assert one.boundary_keys == other.boundary_keys
        for name in ("waypoint_keys", "waypoint_robots", "waypoints"):
            np.testing.assert_array_equal(getattr(one.next, name), getattr(other.next, name))
        for group in ("odometry", "robot_observations", "landmark_observations"):
            for field, value in vars(getattr(one.next, group)).items():
                np.testing.assert_array_equal(value, getattr(getattr(other.next, group), field))
    assert len(together[1].next.waypoint_keys) == 0  # the candidate at the robot itself

    def timeline(robot: int, target) -> tuple[np.ndarray, np.ndarray]:
        waypoints = virtual_waypoints(snapshot.start_poses[robot], target, 2.0)
        keys = [snapshot.start_keys[robot]] + [pose_key(robot, snapshot.next_index[robot] + k)
                                               for k in range(len(waypoints))]
        return np.array(keys), np.vstack([snapshot.start_poses[robot][None], waypoints])

    mates = [timeline(r, mate_targets[r]) for r in (1, 2, 3)]
    predicted = builder.predicted.robot_observations
    expected = _expected_readings(mates, [(0, 1), (0, 2), (1, 2)], reach)
    assert list(zip(predicted.key1.tolist(), predicted.key2.tolist())) == expected
    assert expected  # robots 1 and 2 cross
    for candidate, scenario in zip(candidates, together):
        own = [timeline(0, candidate)] + mates
        expected = _expected_readings(own, [(0, 1), (0, 2), (0, 3)], reach)
        readings = scenario.next.robot_observations
        assert list(zip(readings.key1.tolist(), readings.key2.tolist())) == expected
    assert len(together[2].next.robot_observations.key1) > 0  # passes the idle robot 3


def test_sparse_selected_inverse_of_a_pose_without_parents() -> None:
    """A tracked pose whose part of the graph never reaches the boundary is eliminated
    without parents: its marginal is its own, its cross-covariance with the boundary zero,
    as in the dense inverse."""
    rng = np.random.default_rng(3)
    alone, anchor, linked = pose_key(0, 0), pose_key(1, 0), pose_key(1, 1)
    unit = gtsam.noiseModel.Unit.Create(3)

    def block() -> np.ndarray:
        return np.eye(3) + 0.3 * rng.standard_normal((3, 3))

    linear = gtsam.GaussianFactorGraph()
    linear.add(gtsam.JacobianFactor(alone, block(), np.zeros(3), unit))
    linear.add(gtsam.JacobianFactor(anchor, block(), np.zeros(3), unit))
    linear.add(gtsam.JacobianFactor(anchor, block(), linked, block(), np.zeros(3), unit))
    boundary_covariance, marginals, cross = _sparse_selected_inverse(
        linear, [alone, linked], [anchor])
    keys = [alone, anchor, linked]
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    covariance = np.linalg.inv(linear.hessian(ordering)[0])
    np.testing.assert_allclose(boundary_covariance, covariance[3:6, 3:6], rtol=1e-10)
    np.testing.assert_allclose(marginals[0], covariance[0:3, 0:3], rtol=1e-10)
    np.testing.assert_allclose(marginals[1], covariance[6:9, 6:9], rtol=1e-10)
    np.testing.assert_array_equal(cross[0], np.zeros((3, 3)))
    np.testing.assert_allclose(cross[1], covariance[6:9, 3:6], rtol=1e-10, atol=1e-12)
