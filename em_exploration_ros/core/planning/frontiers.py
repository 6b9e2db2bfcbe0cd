"""Frontier cells and the three kinds of candidate targets (paper sec. III-C / IV).

* exploration frontiers: frontier cells near the robot (all of them early in the mission),
* revisiting frontiers: frontier cells near known landmarks, to close loops,
* rendezvous frontiers: teammates' current targets, to meet them and close inter-robot loops.

Who waits for whom once a rendezvous is chosen is ``rendezvous.RendezvousBook``. Positions
are in the team ``map`` frame [m]; distances are straight-line.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from em_exploration_ros.core.geometry import read_only_point
from em_exploration_ros.core.params import FrontierParams
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid

#: Positions closer than this are the same target when de-duplicating [m].
_SAME_POSITION_M = 1e-6


@dataclass(frozen=True, eq=False)
class Frontier:
    """One candidate target.

    Attributes:
        position: (2,) map-frame position [m] (read-only).
        kind: frontier type.
        partner_id: the teammate to meet (RENDEZVOUS only), else None.
        waiting_penalty_m: RENDEZVOUS only, with ``rendezvous_waiting_penalty`` (the
            reference code's option): expected waiting expressed as distance [m],
            ``|d_self - d_teammate|`` at equal speeds; 0 otherwise.
    """

    position: np.ndarray
    kind: FrontierType
    partner_id: int | None = None
    waiting_penalty_m: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", read_only_point(self.position))
        object.__setattr__(self, "kind", FrontierType(self.kind))


def frontier_cells(grid: OccupancyGrid, params: FrontierParams) -> np.ndarray:
    """Centres (K, 2) [m] of the frontier cells of the grid, in row-major cell order.

    A frontier cell is an explored, not occupied cell with fewer than
    ``params.explored_neighbors_below`` explored 4-neighbours (cells beyond the map edge
    count as unexplored) whose centre lies at least ``params.boundary_distance_m`` from
    every edge of the map. Occupied cells hold a landmark and cannot be driven to.
    """
    explored = grid.explored_mask()
    padded = np.pad(explored, 1, constant_values=False).astype(np.int8)
    explored_neighbors = (padded[:-2, 1:-1] + padded[2:, 1:-1]
                          + padded[1:-1, :-2] + padded[1:-1, 2:])
    is_frontier = (explored & ~grid.occupied_mask()
                   & (explored_neighbors < params.explored_neighbors_below)
                   & (grid.geometry.distance_to_edge() >= params.boundary_distance_m))
    return grid.geometry.cell_center(np.argwhere(is_frontier))


def _as_points(points: np.ndarray) -> np.ndarray:
    """Float array (N, 2) of map-frame points."""
    return np.asarray(points, dtype=float).reshape(-1, 2)


def _by_distance(points: np.ndarray, robot_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) sorted nearest first from ``robot_xy`` (stable), with their distances."""
    distances = np.linalg.norm(points - np.asarray(robot_xy, dtype=float)[:2], axis=1)
    order = np.argsort(distances, kind="stable")
    return points[order], distances[order]


def _frontiers_of(points: np.ndarray, kind: FrontierType) -> list[Frontier]:
    """One frontier of the given kind per row of ``points`` (N, 2)."""
    return [Frontier(point, kind) for point in points]


def exploration_frontiers(cells: np.ndarray, robot_xy: np.ndarray, explored_ratio: float,
                          params: FrontierParams) -> list[Frontier]:
    """Exploration candidates among frontier cells (K, 2) [m], nearest first.

    Those within ``exploration_radius_m`` of the robot position ``robot_xy`` (2,) [m], all
    of them while ``explored_ratio < all_frontiers_below_ratio``, and always the nearest.
    Ties in distance keep the row-major cell order.
    """
    points, distances = _by_distance(_as_points(cells), robot_xy)
    keep = distances <= params.exploration_radius_m
    if explored_ratio < params.all_frontiers_below_ratio:
        keep[:] = True
    keep[:1] = True
    return _frontiers_of(points[keep], FrontierType.EXPLORATION)


def segment_point_distances(start: np.ndarray, ends: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distances (K, M) [m] from points (M, 2) to the segments ``start`` (2,) -> ``ends`` (K, 2)."""
    start = np.asarray(start, dtype=float)[:2]
    direction = _as_points(ends) - start
    to_points = _as_points(points) - start
    length_sq = np.einsum("kd,kd->k", direction, direction)
    projection = to_points @ direction.T
    fraction = np.clip(projection.T / np.maximum(length_sq, 1e-18)[:, None], 0.0, 1.0)
    closest = fraction[:, :, None] * direction[:, None, :]
    return np.linalg.norm(closest - to_points[None, :, :], axis=2)


def revisiting_frontiers(cells: np.ndarray, landmarks: np.ndarray, robot_xy: np.ndarray,
                         params: FrontierParams) -> list[Frontier]:
    """Revisiting candidates among frontier cells (K, 2) [m], given known landmarks (M, 2).

    First the cells within ``revisit_radius_m`` of a landmark (nearest to the robot first).
    While fewer than ``min_revisiting`` were found, the nearest remaining cells whose
    straight path from ``robot_xy`` passes within ``revisit_radius_m`` of a landmark are
    added until ``min_revisiting`` is reached.
    """
    points, _ = _by_distance(_as_points(cells), robot_xy)
    landmarks = _as_points(landmarks)
    if len(points) == 0 or len(landmarks) == 0:
        return []
    to_landmarks = np.linalg.norm(points[:, None, :] - landmarks[None, :, :], axis=2)
    near = to_landmarks.min(axis=1) <= params.revisit_radius_m
    missing = params.min_revisiting - int(near.sum())
    if missing > 0:
        path_distance = segment_point_distances(robot_xy, points[~near], landmarks).min(axis=1)
        passing = np.flatnonzero(~near)[path_distance <= params.revisit_radius_m][:missing]
        near[passing] = True
    return _frontiers_of(points[near], FrontierType.REVISITING)


def rendezvous_frontiers(robot_id: int, robot_xy: np.ndarray,
                         teammates: Mapping[int, tuple[np.ndarray, np.ndarray | None]],
                         params: FrontierParams) -> list[Frontier]:
    """Rendezvous candidates: the current targets of teammates, in ascending teammate id.

    Args:
        robot_id: id of the deciding robot (skipped if it appears in ``teammates``).
        robot_xy: (2,) its position [m].
        teammates: ``{id: (current_xy (2,), current_target_xy (2,) or None)}`` [m].
        params: frontier parameters; a target counts only when the deciding robot is
            farther than ``rendezvous_min_distance_m`` from it.

    Callers leave out teammates that cannot meet (finished or lost). With
    ``params.rendezvous_waiting_penalty`` (not in the paper), each candidate carries the
    arrival-time difference at equal speeds, expressed as distance travelled by the
    deciding robot: ``|d_self - d_teammate|``.
    """
    robot_xy = np.asarray(robot_xy, dtype=float)[:2]
    found = []
    for teammate_id in sorted(teammates):
        teammate_xy, target = teammates[teammate_id]
        if teammate_id == robot_id or target is None:
            continue
        target = np.asarray(target, dtype=float)[:2]
        d_self = float(np.linalg.norm(target - robot_xy))
        if d_self <= params.rendezvous_min_distance_m:
            continue
        d_teammate = float(np.linalg.norm(target - np.asarray(teammate_xy, dtype=float)[:2]))
        penalty = abs(d_self - d_teammate) if params.rendezvous_waiting_penalty else 0.0
        found.append(Frontier(target, FrontierType.RENDEZVOUS, partner_id=teammate_id,
                              waiting_penalty_m=penalty))
    return found


def candidate_targets(cells: np.ndarray, robot_id: int, robot_xy: np.ndarray,
                      explored_ratio: float, landmarks: np.ndarray,
                      teammates: Mapping[int, tuple[np.ndarray, np.ndarray | None]],
                      params: FrontierParams) -> list[Frontier]:
    """All candidate targets of one decision, nearest first, at most ``max_candidates``.

    Combines rendezvous, revisiting and exploration frontiers (arguments as in those
    functions). A cell offered both as revisiting and as exploration frontier appears once,
    as REVISITING; a rendezvous is a distinct option (one per partner) even where it
    coincides with a frontier cell. Rendezvous candidates (at most one per teammate) are
    always kept; the remaining budget goes to the nearest frontier cells.
    """
    rendezvous = rendezvous_frontiers(robot_id, robot_xy, teammates, params)
    others = (revisiting_frontiers(cells, landmarks, robot_xy, params)
              + exploration_frontiers(cells, robot_xy, explored_ratio, params))
    unique: dict[tuple[float, float, int | None], Frontier] = {}
    for frontier in rendezvous + others:
        key = (*np.round(frontier.position / _SAME_POSITION_M).tolist(), frontier.partner_id)
        unique.setdefault(key, frontier)
    robot_xy = np.asarray(robot_xy, dtype=float)[:2]
    nearest_first = sorted(unique.values(),
                           key=lambda f: float(np.linalg.norm(f.position - robot_xy)))
    budget = params.max_candidates - sum(f.kind == FrontierType.RENDEZVOUS for f in nearest_first)
    kept = []
    for frontier in nearest_first:
        if frontier.kind == FrontierType.RENDEZVOUS or budget > 0:
            kept.append(frontier)
            budget -= frontier.kind != FrontierType.RENDEZVOUS
    return kept[:params.max_candidates]
