"""World <-> robot conversions: commands, odometry poses and covariances survive the wire."""
import numpy as np

from em_exploration_ros.core.geometry import compose
from em_exploration_ros.core.records.wire_model import (DeadReckoningDifferencer,
                                                        DeadReckoningIntegrator, command_to_twist,
                                                        increment_covariance_to_twist,
                                                        twist_to_command,
                                                        twist_to_increment_covariance)


def test_command_round_trip():
    turn, forward = twist_to_command(*command_to_twist(0.2, 0.2, 0.2), 0.2)
    assert np.isclose(turn, 0.2, atol=1e-15) and np.isclose(forward, 0.2, atol=1e-15)


def test_covariance_round_trip_and_layout():
    covariance = np.array([[4e-4, 1e-5, 2e-6], [1e-5, 3e-4, 0.0], [2e-6, 0.0, 1e-5]])
    twist = increment_covariance_to_twist(covariance, 0.2)
    assert twist.shape == (6, 6) and np.isclose(twist[5, 5], covariance[2, 2] / 0.2**2, rtol=1e-15)
    assert np.all(twist[2:5, :] == 0.0)
    np.testing.assert_allclose(twist_to_increment_covariance(twist.ravel(), 0.2), covariance,
                               rtol=1e-12)


def test_dead_reckoning_recovers_increments():
    rng = np.random.default_rng(0)
    integrator, differencer = DeadReckoningIntegrator(), DeadReckoningDifferencer()
    assert differencer.increment(integrator.pose) is None
    for _ in range(100):
        increment = np.array([rng.uniform(0, 0.2), rng.normal(0, 0.01), rng.normal(0, 0.2)])
        recovered = differencer.increment(integrator.add(increment))
        np.testing.assert_allclose(recovered, increment, atol=1e-12)


def test_dead_reckoning_covariance_matches_sampled_noise():
    """The propagated covariance of the odometry pose equals the spread of many noisy runs."""
    rng = np.random.default_rng(1)
    steps, runs = 60, 4000
    step_covariance = np.diag([2e-4, 2e-4, 4e-5])
    truth = [np.array([0.2, 0.0, 0.02])] * steps  # ends at 1.2 rad, far from the wrap at pi
    integrator = DeadReckoningIntegrator()
    for increment in truth:
        integrator.add(increment, step_covariance)
    noise = rng.multivariate_normal(np.zeros(3), step_covariance, size=(steps, runs))
    finals = np.zeros((runs, 3))
    for k, increment in enumerate(truth):  # every run at once (compose is vectorized)
        finals = compose(finals, increment + noise[k])
    sampled = np.cov(finals.T)
    np.testing.assert_allclose(integrator.covariance, sampled, rtol=0.1, atol=2e-4)
    assert np.all(DeadReckoningIntegrator().covariance == 0.0)
