"""Tests of frontier cells and candidate targets."""
import dataclasses

import numpy as np
import pytest

from em_exploration_ros.core.params import FrontierParams, MapParams
from em_exploration_ros.core.planning.frontiers import (Frontier, candidate_targets,
                                                        exploration_frontiers, frontier_cells,
                                                        rendezvous_frontiers, revisiting_frontiers,
                                                        segment_point_distances)
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid

NO_LANDMARKS = np.zeros((0, 2))


def _disc_grid(pose_xy: tuple[float, float], landmarks: np.ndarray = NO_LANDMARKS) -> OccupancyGrid:
    """30 m x 30 m, 2 m cells, one pose observing a 7.5 m disc."""
    grid = OccupancyGrid(30.0, 30.0, MapParams(cell_size_m=2.0), sonar_max_range_m=7.5)
    grid.rebuild(np.array([[*pose_xy, 0.0]]), landmarks)
    return grid


def _sorted_rows(points: np.ndarray) -> list[tuple[float, float]]:
    return sorted(map(tuple, np.round(points, 9).tolist()))


def test_frontier_cells_of_one_disc() -> None:
    # Pose at the centre of cell (7, 7): the disc is rows +-3 x cols +-2, rows +-2/+-1/0 x
    # cols +-3. Only the 8 diagonal "step" cells have fewer than 3 explored neighbours.
    cells = frontier_cells(_disc_grid((15.0, 15.0)), FrontierParams())
    expected = [(15.0 + 2.0 * dc, 15.0 + 2.0 * dr)
                for dr, dc in [(3, 2), (3, -2), (-3, 2), (-3, -2),
                               (2, 3), (2, -3), (-2, 3), (-2, -3)]]
    assert _sorted_rows(cells) == sorted(expected)
    # Row-major order: lowest y first.
    assert cells[0][1] == pytest.approx(9.0)
    # The literal "fewer than 2 explored neighbours" leaves no frontier on a disc.
    strict = FrontierParams(explored_neighbors_below=2)
    assert frontier_cells(_disc_grid((15.0, 15.0)), strict).shape == (0, 2)


def test_frontier_cells_exclude_boundary_and_occupied() -> None:
    near_edge = _disc_grid((3.0, 15.0))
    with_boundary = frontier_cells(near_edge, FrontierParams(boundary_distance_m=4.0))
    without_boundary = frontier_cells(near_edge, FrontierParams(boundary_distance_m=0.0))
    assert len(without_boundary) > len(with_boundary) > 0
    assert np.all(with_boundary >= 4.0) and np.all(with_boundary <= 26.0)
    assert np.any(without_boundary[:, 0] < 4.0)
    # A landmark in a frontier cell makes it occupied: not a frontier any more.
    occupied = _disc_grid((15.0, 15.0), landmarks=np.array([[19.2, 21.1]]))
    cells = frontier_cells(occupied, FrontierParams())
    assert (19.0, 21.0) not in _sorted_rows(cells)
    assert len(cells) == 7


def test_exploration_frontiers() -> None:
    cells = np.array([[30.0, 0.0], [3.0, 0.0], [0.0, 8.0], [0.0, -15.0]])
    robot = np.array([0.0, 0.0])
    params = FrontierParams()
    near = exploration_frontiers(cells, robot, explored_ratio=0.5, params=params)
    assert [tuple(f.position) for f in near] == [(3.0, 0.0), (0.0, 8.0)]
    assert all(f.kind == FrontierType.EXPLORATION and f.partner_id is None for f in near)
    every = exploration_frontiers(cells, robot, explored_ratio=0.1, params=params)
    assert [tuple(f.position) for f in every] == [(3.0, 0.0), (0.0, 8.0), (0.0, -15.0),
                                                  (30.0, 0.0)]
    far = exploration_frontiers(cells, np.array([100.0, 0.0]), 0.5, params)
    assert [tuple(f.position) for f in far] == [(30.0, 0.0)]
    assert exploration_frontiers(np.zeros((0, 2)), robot, 0.5, params) == []


def test_exploration_frontiers_tie_break_keeps_row_major_order() -> None:
    cells = np.array([[5.0, 1.0], [5.0, 9.0], [1.0, 5.0], [9.0, 5.0]])
    chosen = exploration_frontiers(cells, np.array([5.0, 5.0]), 0.5, FrontierParams())
    np.testing.assert_allclose([f.position for f in chosen],
                               [[5.0, 1.0], [5.0, 9.0], [1.0, 5.0], [9.0, 5.0]])


def test_segment_point_distances() -> None:
    shift = np.array([3.0, -7.0])
    distances = segment_point_distances(shift, np.array([[10.0, 0.0], [0.0, 0.0]]) + shift,
                                        np.array([[5.0, 3.0], [-4.0, 3.0], [12.0, 0.0]]) + shift)
    np.testing.assert_allclose(distances, [[3.0, 5.0, 2.0], [np.hypot(5, 3), 5.0, 12.0]])


def test_revisiting_frontiers() -> None:
    landmarks = np.array([[50.0, 50.0]])
    robot = np.array([20.0, 50.0])
    cells = np.array([[55.0, 50.0],    # 5 m from the landmark
                      [90.0, 52.0],    # path from the robot passes the landmark at 2 m
                      [80.0, 56.0],    # path passes at 4 m, nearer to the robot
                      [20.0, 10.0]])   # path stays 30 m away
    params = FrontierParams(revisit_radius_m=10.0, min_revisiting=3)
    found = revisiting_frontiers(cells, landmarks, robot, params)
    assert [tuple(f.position) for f in found] == [(55.0, 50.0), (80.0, 56.0), (90.0, 52.0)]
    assert all(f.kind == FrontierType.REVISITING for f in found)
    only_near = revisiting_frontiers(cells, landmarks, robot,
                                     dataclasses.replace(params, min_revisiting=1))
    assert [tuple(f.position) for f in only_near] == [(55.0, 50.0)]
    two = revisiting_frontiers(cells, landmarks, robot,
                               dataclasses.replace(params, min_revisiting=2))
    assert [tuple(f.position) for f in two] == [(55.0, 50.0), (80.0, 56.0)]
    assert revisiting_frontiers(cells, NO_LANDMARKS, robot, params) == []


def test_rendezvous_frontiers() -> None:
    teammates = {
        3: (np.array([30.0, 0.0]), np.array([20.0, 0.0])),   # 20 m from us, 10 m from it
        1: (np.array([0.0, 9.0]), np.array([5.0, 0.0])),     # within 10 m of us: skipped
        2: (np.array([0.0, 30.0]), None),                    # no target yet
        0: (np.array([0.0, 0.0]), np.array([40.0, 0.0])),    # ourselves
        4: (np.array([0.0, -40.0]), np.array([0.0, -15.0])),  # 15 m from us, 25 m from it
    }
    found = rendezvous_frontiers(0, np.array([0.0, 0.0]), teammates, FrontierParams())
    assert [f.partner_id for f in found] == [3, 4]
    assert all(f.kind == FrontierType.RENDEZVOUS for f in found)
    np.testing.assert_allclose(found[0].position, [20.0, 0.0])
    # The paper's U_D is the distance alone; the reference code's waiting penalty is an option.
    assert [f.waiting_penalty_m for f in found] == [0.0, 0.0]
    with_penalty = rendezvous_frontiers(0, np.array([0.0, 0.0]), teammates,
                                        FrontierParams(rendezvous_waiting_penalty=True))
    assert [f.waiting_penalty_m for f in with_penalty] == pytest.approx([10.0, 10.0])


def test_candidate_targets_dedup_cap_and_rendezvous_kept() -> None:
    robot = np.array([50.0, 50.0])
    cells = np.array([[50.0 + d, 50.0] for d in (2.0, 4.0, 6.0, 8.0)])
    landmarks = np.array([[58.0, 52.0]])
    teammates = {1: (np.array([90.0, 50.0]), np.array([80.0, 50.0]))}
    params = FrontierParams(max_candidates=3, min_revisiting=0)
    targets = candidate_targets(cells, 0, robot, 0.5, landmarks, teammates, params)
    assert len(targets) == 3
    assert [f.kind for f in targets] == [FrontierType.REVISITING, FrontierType.REVISITING,
                                         FrontierType.RENDEZVOUS]
    np.testing.assert_allclose([f.position for f in targets], [[52, 50], [54, 50], [80, 50]])
    roomy = candidate_targets(cells, 0, robot, 0.5, landmarks, teammates,
                              dataclasses.replace(params, max_candidates=40))
    assert len(roomy) == 5  # 4 cells, each once, plus the rendezvous
    distances = [np.linalg.norm(f.position - robot) for f in roomy]
    assert distances == sorted(distances)
    lonely = candidate_targets(cells, 0, robot, 0.5, NO_LANDMARKS, {}, params)
    assert [f.kind for f in lonely] == [FrontierType.EXPLORATION] * 3


def test_frontier_is_immutable() -> None:
    frontier = Frontier([1.0, 2.0], 2, partner_id=4, waiting_penalty_m=1.5)
    assert frontier.kind is FrontierType.RENDEZVOUS
    with pytest.raises(ValueError):
        frontier.position[0] = 3.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        frontier.kind = FrontierType.EXPLORATION  # type: ignore[misc]
    assert [int(k) for k in FrontierType] == [0, 1, 2]
