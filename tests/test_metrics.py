"""Metrics on hand-computed examples."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.evaluation.metrics import landmark_rmse, localization_rmse
from em_exploration_ros.core.sim.world import World


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
