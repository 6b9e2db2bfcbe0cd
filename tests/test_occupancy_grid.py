"""Tests of the occupancy part of the virtual map."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.virtual_map.occupancy import (GridGeometry, OccupancyGrid,
                                                           observation_counts, observation_pairs)
from em_exploration_ros.core.params import MapParams


def _sigmoid(log_odds: float) -> float:
    return 1.0 / (1.0 + math.exp(-log_odds))


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@pytest.fixture
def tiny() -> OccupancyGrid:
    """10 m x 6 m, 2 m cells -> 3 rows (y) x 5 cols (x); sonar range 2.5 m."""
    return OccupancyGrid(10.0, 6.0, MapParams(cell_size_m=2.0), sonar_max_range_m=2.5)


def test_geometry_index_convention() -> None:
    geometry = GridGeometry(10.0, 6.0, 2.0)
    assert geometry.shape == (3, 5)
    # Row grows along y, column along x; row 0 at y = 0.
    np.testing.assert_array_equal(geometry.world_to_cell([[7.4, 3.2], [0.0, 0.0], [9.99, 5.99]]),
                                  [[1, 3], [0, 0], [2, 4]])
    np.testing.assert_allclose(geometry.cell_center([1, 3]), [7.0, 3.0])
    centers = geometry.cell_centers()
    assert centers.shape == (3, 5, 2)
    np.testing.assert_allclose(centers[2, 0], [1.0, 5.0])
    np.testing.assert_array_equal(geometry.in_grid([[-1, 0], [0, 5], [2, 4]]), [False, False, True])
    np.testing.assert_allclose(geometry.distance_to_edge()[1], [1.0, 3.0, 3.0, 3.0, 1.0])


def test_geometry_partial_last_cell() -> None:
    assert GridGeometry(5.0, 4.0, 2.0).shape == (2, 3)


def test_single_pose_hand_computed(tiny: OccupancyGrid) -> None:
    # Pose at the centre of cell (1, 2); within 2.5 m lie the centres of the "plus" of 5 cells.
    tiny.rebuild(np.array([[5.0, 3.0, 0.3]]), np.array([[7.4, 3.2]]))
    expected = np.full((3, 5), 0.5)
    expected[1, 1:4] = 0.3
    expected[0, 2] = expected[2, 2] = 0.3
    expected[1, 3] = 0.7  # the landmark's cell is observed occupied
    np.testing.assert_allclose(tiny.probability(), expected)
    np.testing.assert_array_equal(tiny.observation_count(), (expected != 0.5).astype(int))
    assert tiny.explored_ratio() == pytest.approx(5 / 15)
    np.testing.assert_array_equal(tiny.explored_mask(), expected != 0.5)
    np.testing.assert_array_equal(tiny.occupied_mask(), expected == 0.7)


def test_repeated_observations_accumulate_and_clamp(tiny: OccupancyGrid) -> None:
    three = np.tile([5.0, 3.0, 0.0], (3, 1))
    tiny.rebuild(three, np.array([[7.4, 3.2]]))
    assert tiny.probability()[1, 2] == pytest.approx(_sigmoid(3 * _logit(0.3)))
    assert tiny.probability()[1, 3] == pytest.approx(_sigmoid(3 * _logit(0.7)))
    four = np.tile([5.0, 3.0, 0.0], (4, 1))
    tiny.rebuild(four, np.array([[7.4, 3.2]]))
    assert tiny.probability()[1, 2] == pytest.approx(0.05)
    assert tiny.probability()[1, 3] == pytest.approx(0.95)
    assert tiny.log_odds.min() == pytest.approx(_logit(0.05))
    with pytest.raises(ValueError):
        tiny.log_odds[0, 0] = 1.0


def test_unobserved_landmark_cell_is_occupied_and_outside_landmarks_ignored(
        tiny: OccupancyGrid) -> None:
    tiny.rebuild(np.array([[5.0, 3.0, 0.0]]), np.array([[1.0, 5.0], [-3.0, 2.0], [50.0, 1.0]]))
    probability = tiny.probability()
    assert probability[2, 0] == pytest.approx(0.7)
    assert np.count_nonzero(probability > 0.5) == 1


def test_rebuild_starts_from_scratch(tiny: OccupancyGrid) -> None:
    tiny.rebuild(np.array([[1.0, 1.0, 0.0], [9.0, 5.0, 0.0]]), np.zeros((0, 2)))
    first = tiny.explored_ratio()
    tiny.rebuild(np.array([[1.0, 1.0, 0.0]]), np.zeros((0, 2)))
    assert tiny.explored_ratio() < first
    assert tiny.probability()[2, 4] == 0.5
    tiny.rebuild(np.zeros((0, 3)), np.zeros((0, 2)))
    assert tiny.explored_ratio() == 0.0
    np.testing.assert_allclose(tiny.probability(), 0.5)


def test_counts_match_brute_force() -> None:
    rng = np.random.default_rng(7)
    geometry = GridGeometry(40.0, 30.0, 1.5)
    poses = np.column_stack([rng.uniform(-5.0, 45.0, (300, 2)), rng.uniform(-3.0, 3.0, 300)])
    counts = observation_counts(geometry, poses, 4.2)
    centers = geometry.cell_centers()
    distance = np.linalg.norm(centers[:, :, None, :] - poses[None, None, :, :2], axis=-1)
    np.testing.assert_array_equal(counts, np.sum(distance <= 4.2, axis=2))
    pose_index, flat_cell = observation_pairs(geometry, poses, 4.2)
    assert np.all(np.diff(pose_index) >= 0)
    rows, cols = np.divmod(flat_cell, geometry.cols)
    np.testing.assert_array_equal(distance[rows, cols, pose_index] <= 4.2, True)


def test_cells_observed_by_two_waypoints() -> None:
    geometry = GridGeometry(20.0, 20.0, 2.0)
    waypoints = np.array([[3.0, 3.0, 0.0], [5.0, 3.0, 0.0]])
    mask = observation_counts(geometry, waypoints, 2.0) > 0
    assert mask.shape == (10, 10)
    np.testing.assert_array_equal(np.argwhere(mask),
                                  [[0, 1], [0, 2], [1, 0], [1, 1], [1, 2], [1, 3], [2, 1], [2, 2]])
    assert not observation_counts(geometry, np.zeros((0, 3)), 2.0).any()


def test_invalid_parameters_rejected() -> None:
    with pytest.raises(ValueError):
        OccupancyGrid(10.0, 10.0, MapParams(prob_free=0.0), 7.5)
    with pytest.raises(ValueError):
        OccupancyGrid(10.0, 10.0, MapParams(prob_min=0.6), 7.5)
    with pytest.raises(ValueError):
        OccupancyGrid(10.0, 10.0, MapParams(), 0.0)
