"""Simulated sensors: exactness without noise, seeded independent streams, noise statistics."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.geometry import between, range_bearing, wrap_angle
from em_exploration_ros.core.params import BOUND_95_TO_SIGMA, MotionParams, SensorParams
from em_exploration_ros.core.world.sensors import SensorSimulator, odometry_covariance_per_step
from em_exploration_ros.core.world.world import World

MOTION = MotionParams()
NOISY = SensorParams()
EXACT = SensorParams(noise_enabled=False)
DRAWS = 20000


def _world() -> World:
    """Three landmarks with unsorted ids and three robots, hand placed."""
    return World(width_m=50.0, height_m=50.0,
                 landmarks=np.array([[20.0, 20.0], [10.0, 10.0], [17.5, 14.0]]),
                 landmark_ids=np.array([7, 3, 5]), landmark_radius_m=1.0, robot_radius_m=0.8,
                 start_poses=np.array([[10.0, 14.0, 0.3], [13.0, 14.0, -2.0], [30.0, 30.0, 1.0]]))


def _simulator(params: SensorParams = NOISY, seed: int = 0) -> SensorSimulator:
    return SensorSimulator(_world(), params, MOTION, np.random.SeedSequence(seed))


def _check_gaussian(samples: np.ndarray, covariance: np.ndarray) -> None:
    """Zero mean, covariance within sampling tolerance, mean NEES = dimension, and 2.5% of
    the draws beyond each side of the 95% bound (the noise is not clipped)."""
    n, dim = samples.shape
    sigma = np.sqrt(np.diag(covariance))
    assert np.all(np.abs(samples.mean(axis=0)) < 4.0 * sigma / math.sqrt(n))
    sample_cov = np.cov(samples, rowvar=False)
    np.testing.assert_allclose(np.diag(sample_cov), np.diag(covariance), rtol=0.05)
    correlation = sample_cov / np.outer(sigma, sigma)
    assert np.all(np.abs(correlation[~np.eye(dim, dtype=bool)]) < 0.03)
    nees = np.einsum("ni,ij,nj->n", samples, np.linalg.inv(covariance), samples)
    assert abs(nees.mean() - dim) < 4.0 * math.sqrt(2.0 * dim / n)
    bound = BOUND_95_TO_SIGMA * sigma
    for tail in (np.mean(samples > bound, axis=0), np.mean(samples < -bound, axis=0)):
        np.testing.assert_allclose(tail, 0.025, atol=0.005)


def test_noise_free_sonar_is_exact_and_sorted_by_id() -> None:
    sim = _simulator(EXACT)
    pose = np.array([10.0, 14.0, 0.3])  # landmark 3 at 4 m, 5 at exactly 7.5 m, 7 too far
    readings = sim.sonar(0, pose)
    assert [r.landmark_id for r in readings] == [3, 5]
    ranges, bearings = range_bearing(pose, _world().landmarks)
    assert readings[0].range_m == ranges[1] and readings[0].bearing_rad == bearings[1]
    assert readings[1].range_m == ranges[2] and readings[1].bearing_rad == bearings[2]
    assert readings[0].range_variance == pytest.approx((0.002 / 1.96) ** 2)
    assert readings[0].bearing_variance == pytest.approx((math.radians(0.5) / 1.96) ** 2)
    assert sim.sonar(0, np.array([40.0, 40.0, 0.0])) == []


def test_noise_free_teammates_are_exact_and_filtered() -> None:
    sim = _simulator(EXACT)
    poses = _world().start_poses
    readings = sim.teammates(0, poses)
    assert [r.robot_id for r in readings] == [1]
    np.testing.assert_array_equal(readings[0].relative_pose, between(poses[0], poses[1]))
    np.testing.assert_allclose(np.diag(readings[0].covariance), [
        (0.002 / 1.96) ** 2, (0.002 / 1.96) ** 2, (math.radians(0.2) / 1.96) ** 2])
    assert sim.teammates(0, poses, active=[True, False, True]) == []
    assert sim.teammates(2, poses) == []


def test_noise_free_odometry_is_exact() -> None:
    sim = _simulator(EXACT)
    previous, current = np.array([3.0, 4.0, 2.9]), np.array([2.81, 4.07, -3.0])
    reading = sim.odometry(1, previous, current)
    np.testing.assert_array_equal(reading.delta, between(previous, current))
    step = float(np.hypot(*reading.delta[:2]))
    np.testing.assert_array_equal(reading.covariance,
                                  odometry_covariance_per_step(step, True, EXACT))
    assert reading.covariance[2, 2] > 0.0 and reading.covariance[0, 0] > 0.0


def test_still_robot_reads_exactly_zero_and_pure_turn_only_heading_noise() -> None:
    sim = _simulator(NOISY)
    pose = np.array([3.0, 4.0, 1.0])
    still = sim.odometry(0, pose, pose)
    np.testing.assert_array_equal(still.delta, np.zeros(3))
    np.testing.assert_array_equal(still.covariance, np.zeros((3, 3)))
    turned = sim.odometry(0, pose, pose + [0.0, 0.0, 0.2])
    np.testing.assert_array_equal(turned.delta[:2], [0.0, 0.0])
    assert turned.delta[2] != 0.2
    np.testing.assert_allclose(turned.covariance, np.diag(
        [0.0, 0.0, (math.radians(0.5) / 1.96) ** 2 / 10]))


def test_odometry_covariance_accumulates_to_the_paper_bounds_per_interval() -> None:
    steps = NOISY.odometry_interval_steps
    full = odometry_covariance_per_step(0.2, True, NOISY) * steps  # 2 m per interval
    np.testing.assert_allclose(np.sqrt(np.diag(full)) * BOUND_95_TO_SIGMA,
                               [0.05, 0.05, math.radians(0.5)])
    short = odometry_covariance_per_step(0.05, False, NOISY) * steps  # 0.5 m per interval
    np.testing.assert_allclose(np.sqrt(np.diag(short)) * BOUND_95_TO_SIGMA,
                               [0.025, 0.025, math.radians(0.5)])
    still = odometry_covariance_per_step(0.0, False, NOISY)
    np.testing.assert_array_equal(still, np.zeros((3, 3)))


def test_same_seed_same_draws_and_streams_independent_of_call_order() -> None:
    poses = _world().start_poses
    moved = poses + [0.2, 0.0, 0.1]
    first, second = _simulator(seed=3), _simulator(seed=3)
    # first: robot 0 then robot 1; second: robot 1 several times before robot 0.
    r0_first = [first.odometry(0, poses[0], moved[0]).delta for _ in range(3)]
    r1_first = [first.odometry(1, poses[1], moved[1]).delta for _ in range(3)]
    r1_second = [second.odometry(1, poses[1], moved[1]).delta for _ in range(3)]
    second.sonar(1, poses[1])
    second.teammates(1, poses)
    r0_second = [second.odometry(0, poses[0], moved[0]).delta for _ in range(3)]
    np.testing.assert_array_equal(r0_first, r0_second)
    np.testing.assert_array_equal(r1_first, r1_second)
    assert not np.array_equal(r0_first[0] - between(poses[0], moved[0]),
                              r1_first[0] - between(poses[1], moved[1]))
    # Sonar and teammate streams are separate from odometry: interleaving changes nothing.
    third, fourth = _simulator(seed=3), _simulator(seed=3)
    third.odometry(0, poses[0], moved[0])
    assert third.sonar(0, poses[0]) == fourth.sonar(0, poses[0])
    different = _simulator(seed=4)
    assert different.sonar(0, poses[0]) != _simulator(seed=3).sonar(0, poses[0])


def test_seed_sequence_is_not_modified() -> None:
    seed_sequence = np.random.SeedSequence(9)
    SensorSimulator(_world(), NOISY, MOTION, seed_sequence)
    assert seed_sequence.n_children_spawned == 0


def test_odometry_noise_matches_stated_covariance() -> None:
    sim = _simulator(seed=5)
    previous = np.array([10.0, 10.0, 2.5])
    current = previous + [0.2 * math.cos(2.6), 0.2 * math.sin(2.6), 0.1]
    true_delta = between(previous, current)
    readings = [sim.odometry(0, previous, current) for _ in range(DRAWS)]
    errors = np.array([r.delta for r in readings]) - true_delta
    errors[:, 2] = wrap_angle(errors[:, 2])
    _check_gaussian(errors, readings[0].covariance)
    np.testing.assert_array_equal(readings[0].covariance,
                                  odometry_covariance_per_step(0.2, True, NOISY))


def test_sonar_noise_matches_stated_variances() -> None:
    sim = _simulator(seed=6)
    pose = np.array([13.0, 14.0, -2.0])
    true_range, true_bearing = range_bearing(pose, _world().landmarks[1])
    samples = np.array([[r.range_m - true_range, wrap_angle(r.bearing_rad - true_bearing)]
                        for r in (sim.sonar(1, pose)[0] for _ in range(DRAWS))])
    reading = sim.sonar(1, pose)[0]
    assert reading.landmark_id == 3
    _check_gaussian(samples, np.diag([reading.range_variance, reading.bearing_variance]))


def test_teammate_noise_matches_stated_covariance() -> None:
    sim = _simulator(seed=7)
    poses = _world().start_poses
    truth = between(poses[1], poses[0])
    readings = [sim.teammates(1, poses)[0] for _ in range(DRAWS)]
    errors = np.array([r.relative_pose for r in readings]) - truth
    errors[:, 2] = wrap_angle(errors[:, 2])
    _check_gaussian(errors, readings[0].covariance)


def test_invalid_robot_id_raises() -> None:
    with pytest.raises(ValueError, match="robot_id"):
        _simulator().sonar(3, np.zeros(3))
