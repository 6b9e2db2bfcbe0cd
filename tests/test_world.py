"""World generation constraints and reproducibility, kinematics, collisions."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.params import MotionParams, SensorParams, WorldParams
from em_exploration_ros.core.world.world import (World, advance_robot, collides,
                                                 derive_seed_sequence, generate_world,
                                                 run_seed_sequences, start_region, step_pose)

MOTION = MotionParams()


def _pairwise(points: np.ndarray) -> np.ndarray:
    """Distances between distinct pairs of points (upper triangle)."""
    dist = np.linalg.norm(points[:, None] - points[None], axis=-1)
    return dist[np.triu_indices(len(points), k=1)]


def _world_with_landmarks(landmarks: list[list[float]]) -> World:
    return World(width_m=20.0, height_m=20.0, landmarks=np.array(landmarks, dtype=float),
                 landmark_ids=np.arange(len(landmarks)), landmark_radius_m=1.0,
                 robot_radius_m=0.8, start_poses=np.array([[2.0, 2.0, 0.0]]))


def test_same_seed_same_world_different_seed_different_world() -> None:
    params, sensors = WorldParams(), SensorParams()
    first = generate_world(params, sensors, np.random.SeedSequence(7))
    second = generate_world(params, sensors, np.random.SeedSequence(7))
    other = generate_world(params, sensors, np.random.SeedSequence(8))
    np.testing.assert_array_equal(first.landmarks, second.landmarks)
    np.testing.assert_array_equal(first.start_poses, second.start_poses)
    np.testing.assert_array_equal(first.landmark_ids, second.landmark_ids)
    assert not np.array_equal(first.landmarks, other.landmarks)
    with pytest.raises(ValueError):
        first.landmarks[0, 0] = 1.0


def test_seed_sequences_match_spawn_and_do_not_mutate_parent() -> None:
    parent = np.random.SeedSequence(11)
    derived = derive_seed_sequence(parent, 1, 2)
    assert parent.n_children_spawned == 0
    spawned = np.random.SeedSequence(11).spawn(2)[1].spawn(3)[2]
    np.testing.assert_array_equal(derived.generate_state(4), spawned.generate_state(4))
    world_a, sensor_a = run_seed_sequences(5)
    world_b, _ = run_seed_sequences(5)
    np.testing.assert_array_equal(world_a.generate_state(4), world_b.generate_state(4))
    assert not np.array_equal(world_a.generate_state(4), sensor_a.generate_state(4))


@pytest.mark.parametrize("params", [
    WorldParams(),
    WorldParams(width_m=200.0, height_m=200.0),
    WorldParams(width_m=150.0, height_m=150.0, num_robots=5, num_landmarks=40),
], ids=["small", "large", "five_robots"])
def test_generated_worlds_satisfy_constraints_over_50_seeds(params: WorldParams) -> None:
    sensors = SensorParams()
    size = np.array([params.width_m, params.height_m])
    low = size * np.array([params.start_region_x_fraction[0], params.start_region_y_fraction[0]])
    high = size * np.array([params.start_region_x_fraction[1], params.start_region_y_fraction[1]])
    for seed in range(50):
        world = generate_world(params, sensors, np.random.SeedSequence(seed))
        starts, landmarks = world.start_poses, world.landmarks
        assert starts.shape == (params.num_robots, 3)
        assert landmarks.shape == (params.num_landmarks, 2)
        np.testing.assert_array_equal(world.landmark_ids, np.arange(params.num_landmarks))
        assert np.all(_pairwise(landmarks) >= params.landmark_min_separation_m)
        assert np.all(landmarks >= params.landmark_edge_margin_m)
        assert np.all(landmarks <= size - params.landmark_edge_margin_m)
        to_start = np.linalg.norm(landmarks[:, None] - starts[None, :, :2], axis=-1)
        assert np.all(to_start >= params.landmark_clearance_from_start_m)
        assert np.all((starts[:, :2] >= low) & (starts[:, :2] <= high))
        separations = _pairwise(starts[:, :2])
        assert np.all(separations >= params.start_min_separation_m)
        assert np.all(separations <= params.start_max_separation_m)
        assert np.all(separations < sensors.sonar_max_range_m)
        assert np.all((starts[:, 2] > -np.pi) & (starts[:, 2] <= np.pi))
        assert not np.any(collides(world, starts[:, :2]))


@pytest.mark.parametrize("size_m", [100.0, 200.0])
def test_twelve_robots_start_in_a_grown_region_each_sensing_the_robots_placed_before(
        size_m: float) -> None:
    params = WorldParams(width_m=size_m, height_m=size_m, num_robots=12)
    sensors = SensorParams()
    low, high = start_region(params)
    default_low, default_high = start_region(WorldParams(width_m=size_m, height_m=size_m))
    np.testing.assert_allclose(high - low, (default_high - default_low) * math.sqrt(12 / 5))
    np.testing.assert_allclose(low + high, default_low + default_high)
    group = params.start_group_robots
    for seed in range(20):
        starts = generate_world(params, sensors, np.random.SeedSequence(seed)).start_poses[:, :2]
        assert np.all((starts >= low) & (starts <= high))
        assert np.all(_pairwise(starts) >= params.start_min_separation_m)
        distance = np.linalg.norm(starts[:, None] - starts[None], axis=-1)
        for robot in range(1, 12):
            before = distance[robot, max(0, robot - group + 1):robot]
            assert np.all(before <= params.start_max_separation_m)
        # The sensing graph at the start is connected: every robot reaches robot 0's anchor.
        reached, frontier = {0}, [0]
        while frontier:
            robot = frontier.pop()
            for other in np.flatnonzero(distance[robot] < sensors.sonar_max_range_m):
                if int(other) not in reached:
                    reached.add(int(other))
                    frontier.append(int(other))
        assert reached == set(range(12))


def test_start_region_is_the_configured_box_up_to_one_group_and_stays_in_the_map() -> None:
    low, high = start_region(WorldParams(num_robots=5))
    np.testing.assert_allclose(low, [10.0, 45.0])
    np.testing.assert_allclose(high, [20.0, 55.0])
    low, high = start_region(WorldParams(num_robots=26, start_group_robots=2,
                                         start_region_x_fraction=(0.0, 0.1)))
    assert np.all(low >= 0.0) and np.all(high <= 100.0) and low[0] == 0.0


def test_start_headings_are_spread_over_the_circle() -> None:
    headings = np.concatenate([
        generate_world(WorldParams(), SensorParams(), np.random.SeedSequence(s)).start_poses[:, 2]
        for s in range(50)])
    counts, _ = np.histogram(headings, bins=4, range=(-np.pi, np.pi))
    assert np.all(counts > 20)


def test_start_separation_is_capped_below_sonar_range() -> None:
    params = WorldParams(start_min_separation_m=4.0, start_max_separation_m=30.0)
    sensors = SensorParams(sonar_max_range_m=5.0)
    for seed in range(10):
        world = generate_world(params, sensors, np.random.SeedSequence(seed))
        separations = _pairwise(world.start_poses[:, :2])
        assert np.all((separations >= 4.0) & (separations < 5.0))


@pytest.mark.parametrize("params, sensors, message", [
    (WorldParams(num_landmarks=200), SensorParams(), "landmarks"),
    (WorldParams(width_m=40.0, height_m=40.0, num_landmarks=20), SensorParams(), "landmarks"),
    (WorldParams(num_robots=20, start_group_robots=20), SensorParams(), "robots"),
    (WorldParams(start_min_separation_m=8.0, start_max_separation_m=9.0), SensorParams(),
     "sonar_max_range_m"),
    (WorldParams(start_region_x_fraction=(0.3, 0.2)), SensorParams(), "start region"),
], ids=["landmarks_over_packing_bound", "landmarks_jammed", "too_many_robots",
        "separation_beyond_sonar", "empty_start_region"])
def test_impossible_worlds_raise_clear_value_error(params: WorldParams, sensors: SensorParams,
                                                   message: str) -> None:
    with pytest.raises(ValueError, match=message):
        generate_world(params, sensors, np.random.SeedSequence(0))


def test_step_pose_clips_turn_and_keeps_speed() -> None:
    step = MOTION.speed_mps * MOTION.time_step_s
    pose = np.array([1.0, 2.0, 0.0])
    turned = step_pose(pose, 1.0, step, MOTION)
    assert turned[2] == pytest.approx(math.radians(15.0))
    np.testing.assert_allclose(turned[:2], pose[:2] + step * np.array(
        [math.cos(math.radians(15.0)), math.sin(math.radians(15.0))]), atol=1e-12)
    right = step_pose(pose, -1.0, step, MOTION)
    assert right[2] == pytest.approx(-math.radians(15.0))
    small = step_pose(pose, 0.1, step, MOTION)
    assert small[2] == pytest.approx(0.1)
    too_far = step_pose(pose, 0.0, 5.0, MOTION)
    np.testing.assert_allclose(too_far, [1.0 + step, 2.0, 0.0], atol=1e-12)
    reverse = step_pose(pose, 0.0, -1.0, MOTION)
    np.testing.assert_allclose(reverse, pose)


def test_step_pose_wraps_heading_and_broadcasts() -> None:
    near_pi = step_pose(np.array([0.0, 0.0, math.pi - 0.1]), 0.2, 0.2, MOTION)
    assert near_pi[2] == pytest.approx(-math.pi + 0.1)
    poses = np.zeros((4, 3))
    turns = np.array([-1.0, -0.1, 0.1, 1.0])
    moved = step_pose(poses, turns, 0.2, MOTION)
    assert moved.shape == (4, 3)
    np.testing.assert_allclose(np.linalg.norm(moved[:, :2], axis=1), 0.2)
    np.testing.assert_allclose(moved[:, 2], np.clip(turns, -math.radians(15), math.radians(15)))


def test_collides_uses_both_radii_and_map_bounds() -> None:
    world = _world_with_landmarks([[10.0, 10.0]])
    points = np.array([[11.79, 10.0], [11.81, 10.0], [10.0, 8.5], [-0.01, 5.0], [5.0, 20.01],
                       [20.0, 20.0]])
    np.testing.assert_array_equal(collides(world, points),
                                  [True, False, True, True, True, False])
    assert collides(world, points.reshape(2, 3, 2)).shape == (2, 3)
    empty = _world_with_landmarks([])
    np.testing.assert_array_equal(collides(empty, points), [False, False, False, True, True, False])


def test_advance_robot_blocked_by_landmark_turns_but_does_not_translate() -> None:
    world = _world_with_landmarks([[10.0, 10.0]])
    pose = np.array([8.1, 10.0, 0.0])
    new_pose, blocked = advance_robot(world, pose, 0.05, 0.2, MOTION)
    assert blocked
    np.testing.assert_allclose(new_pose, [8.1, 10.0, 0.05])
    free, free_blocked = advance_robot(world, np.array([5.0, 5.0, 0.0]), 0.05, 0.2, MOTION)
    assert not free_blocked
    np.testing.assert_allclose(free, step_pose(np.array([5.0, 5.0, 0.0]), 0.05, 0.2, MOTION))
    edge, edge_blocked = advance_robot(world, np.array([19.9, 5.0, 0.0]), 0.0, 0.2, MOTION)
    assert edge_blocked
    np.testing.assert_allclose(edge, [19.9, 5.0, 0.0])
