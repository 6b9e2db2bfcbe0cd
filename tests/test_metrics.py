"""Metrics on hand-computed examples."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator, stamp_key, stamp_keys
from em_exploration_ros.core.evaluation.metrics import landmark_rmse, localization_rmse
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.world.world import World


def _world() -> World:
    return World(width_m=10.0, height_m=10.0, landmarks=np.array([[1.0, 1.0], [5.0, 5.0],
                                                                   [8.0, 2.0]]),
                 landmark_ids=np.array([4, 9, 2]), landmark_radius_m=1.0, robot_radius_m=0.8,
                 start_poses=np.zeros((1, 3)))


def test_localization_rmse_hand_example() -> None:
    truth = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.5]])
    estimated = np.array([[3.0, 4.0, 2.0], [1.0, 1.0, 0.5]])
    assert localization_rmse(estimated, truth) == pytest.approx(math.sqrt(25.0 / 2.0))
    assert localization_rmse(truth, truth) == 0.0
    assert math.isnan(localization_rmse(np.zeros((0, 3)), np.zeros((0, 3))))
    with pytest.raises(ValueError):
        localization_rmse(estimated, truth[:1])


def test_landmark_rmse_matches_by_id() -> None:
    world = _world()
    estimates = {9: np.array([5.0, 8.0]), 4: [1.0, 1.0]}
    assert landmark_rmse(estimates, world) == pytest.approx(math.sqrt(9.0 / 2.0))
    assert landmark_rmse({2: (8.0, 3.0)}, world) == pytest.approx(1.0)
    assert math.isnan(landmark_rmse({}, world))
    with pytest.raises(KeyError, match="5"):
        landmark_rmse({5: [0.0, 0.0]}, world)


def test_stamp_keys_equal_stamp_key_one_by_one() -> None:
    stamps = np.concatenate([np.arange(0, 5000) * 0.2,
                             np.random.default_rng(2).uniform(0, 1e4, 2000),
                             [0.0000005, 0.0000015, 0.0000025, 1e-9]])  # halves to even
    np.testing.assert_array_equal(stamp_keys(stamps), [stamp_key(float(s)) for s in stamps])


def test_team_evaluator_matches_estimates_to_the_truth_by_stamp() -> None:
    params = ExplorationParams()
    evaluator = TeamEvaluator(_world(), params)
    # Robot 0's truth arrives out of order and its stamp 0.4 is recorded twice (the last wins).
    for stamp, pose in ((0.2, [1.0, 0.0, 0.0]), (0.0, [0.0, 0.0, 0.0]),
                        (0.4, [9.0, 9.0, 0.0]), (0.4, [2.0, 0.0, 0.0])):
        evaluator.record_truth(0, stamp, np.array(pose))
    evaluator.record_truth(1, 0.2, np.array([5.0, 5.0, 0.0]))
    trajectories = {
        0: (np.array([0.0, 0.2 + 1e-12, 0.4, 0.6]),  # 0.6 has no truth yet
            np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [2.0, 2.0, 0.0], [7.0, 7.0, 0.0]])),
        1: (np.array([0.2]), np.array([[5.0, 2.0, 0.0]])),
        2: (np.zeros(0), np.zeros((0, 3)))}
    metrics = evaluator.evaluate(0.6, trajectories, {})
    # Matched: robot 0 at 0.0 (error 1), 0.2 (0), 0.4 (2); robot 1 at 0.2 (3).
    assert metrics.loc_rmse_m == pytest.approx(math.sqrt((1 + 0 + 4 + 9) / 4))
    np.testing.assert_array_equal(evaluator.true_trajectory(0)[:, 0], [0.0, 1.0, 2.0])
    assert evaluator.true_trajectory(2).shape == (0, 3)
    nothing = evaluator.evaluate(0.6, {2: (np.zeros(0), np.zeros((0, 3)))}, {})
    assert math.isnan(nothing.loc_rmse_m)
