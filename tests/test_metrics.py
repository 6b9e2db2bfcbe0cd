"""Metrics on hand-computed examples, including heading wrap-around."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.evaluation.metrics import (MetricHistory, MetricSample, heading_rmse,
                                             landmark_rmse, localization_rmse, path_length)
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


def test_heading_rmse_wraps_angles() -> None:
    estimated = np.array([[0.0, 0.0, math.pi - 0.01]])
    truth = np.array([[5.0, 5.0, -math.pi + 0.01]])
    assert heading_rmse(estimated, truth) == pytest.approx(0.02)
    both = heading_rmse(np.array([[0, 0, 0.1], [0, 0, -3.1]]),
                        np.array([[0, 0, -0.2], [0, 0, 3.1]]))
    expected = math.sqrt((0.3 ** 2 + (2 * math.pi - 6.2) ** 2) / 2)
    assert both == pytest.approx(expected)


def test_landmark_rmse_matches_by_id() -> None:
    world = _world()
    estimates = {9: np.array([5.0, 8.0]), 4: [1.0, 1.0]}
    assert landmark_rmse(estimates, world) == pytest.approx(math.sqrt(9.0 / 2.0))
    assert landmark_rmse({2: (8.0, 3.0)}, world) == pytest.approx(1.0)
    assert math.isnan(landmark_rmse({}, world))
    with pytest.raises(KeyError, match="5"):
        landmark_rmse({5: [0.0, 0.0]}, world)


def test_path_length() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 1.0], [3.0, 4.0, 2.0], [3.0, 6.0, 0.0]])
    assert path_length(poses) == pytest.approx(7.0)
    assert path_length(poses[:1]) == 0.0
    assert path_length(np.zeros((0, 3))) == 0.0


def test_metric_history_returns_arrays_in_order() -> None:
    history = MetricHistory()
    assert len(history) == 0
    assert history.as_arrays()["distance_m"].shape == (0,)
    history.append(MetricSample(distance_m=0.0, loc_rmse_m=0.0, landmark_rmse_m=float("nan"),
                                explored_ratio=0.01))
    history.append(MetricSample(distance_m=12.5, loc_rmse_m=0.3, landmark_rmse_m=0.2,
                                explored_ratio=0.2))
    arrays = history.as_arrays()
    assert len(history) == 2
    assert set(arrays) == {"distance_m", "loc_rmse_m", "landmark_rmse_m", "explored_ratio"}
    np.testing.assert_array_equal(arrays["distance_m"], [0.0, 12.5])
    np.testing.assert_array_equal(arrays["loc_rmse_m"], [0.0, 0.3])
    assert math.isnan(arrays["landmark_rmse_m"][0]) and arrays["landmark_rmse_m"][1] == 0.2
    np.testing.assert_array_equal(arrays["explored_ratio"], [0.01, 0.2])
