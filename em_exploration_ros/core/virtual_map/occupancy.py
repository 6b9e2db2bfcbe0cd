"""Occupancy part of the virtual map: log-odds per cell, explored area and explored ratio.

The grid covers the mission rectangle ``[0, width] x [0, height]`` of the team ``map``
frame (the world frame in simulation), split into square cells of ``cell_size_m``.

Index convention (same as ``nav_msgs/OccupancyGrid``): arrays are ``(rows, cols)``; the row
index grows along map y and the column index along map x; cell ``(row, col)`` covers
``x in [col * s, (col + 1) * s)`` and ``y in [row * s, (row + 1) * s)``, so row 0 lies at
y = 0 (the bottom edge). Its centre is ``((col + 0.5) * s, (row + 0.5) * s)``. When the
size is not a multiple of ``s`` the last row/column extends past the edge. A flat index is
``row * cols + col`` (row-major).

A cell is observed by a robot pose when the cell centre lies within the sonar range of
the pose position (the sonar sees all around the robot). The map is rebuilt from scratch
from the latest SLAM estimates, since every SLAM update may move every pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from em_exploration_ros.core.params import MapParams

#: Upper bound on the number of (pose, cell) candidates held in memory at once.
_CANDIDATES_PER_CHUNK = 1 << 20


@dataclass(frozen=True)
class GridGeometry:
    """Cell layout of the mission rectangle in the map frame (see the module docstring)."""

    width_m: float
    height_m: float
    cell_size_m: float

    def __post_init__(self) -> None:
        if self.width_m <= 0.0 or self.height_m <= 0.0 or self.cell_size_m <= 0.0:
            raise ValueError("grid width, height and cell size must be positive, got "
                             f"{self.width_m}, {self.height_m}, {self.cell_size_m}")

    @property
    def rows(self) -> int:
        """Number of rows (along map y)."""
        return max(1, math.ceil(self.height_m / self.cell_size_m - 1e-9))

    @property
    def cols(self) -> int:
        """Number of columns (along map x)."""
        return max(1, math.ceil(self.width_m / self.cell_size_m - 1e-9))

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return self.rows, self.cols

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """Integer ``(row, col)`` of the cells containing map-frame points ``xy`` (..., 2) [m].

        Points outside the rectangle give indices outside the grid; see ``in_grid``.
        """
        xy = np.asarray(xy, dtype=float)
        col_row = np.floor(xy / self.cell_size_m).astype(np.int64)
        return col_row[..., ::-1]

    def in_grid(self, cells: np.ndarray) -> np.ndarray:
        """Boolean mask (...) of ``(row, col)`` indices (..., 2) that lie inside the grid."""
        cells = np.asarray(cells)
        return ((cells[..., 0] >= 0) & (cells[..., 0] < self.rows)
                & (cells[..., 1] >= 0) & (cells[..., 1] < self.cols))

    def cell_center(self, cells: np.ndarray) -> np.ndarray:
        """Map-frame centres ``(x, y)`` [m] (..., 2) of ``(row, col)`` indices (..., 2)."""
        cells = np.asarray(cells, dtype=float)
        return (cells[..., ::-1] + 0.5) * self.cell_size_m

    def cell_centers(self) -> np.ndarray:
        """Centres ``(x, y)`` [m] of every cell, shape ``(rows, cols, 2)``."""
        rows, cols = np.indices(self.shape)
        return self.cell_center(np.stack([rows, cols], axis=-1))

    def distance_to_edge(self) -> np.ndarray:
        """Distance [m] from each cell centre to the nearest edge of the rectangle, (rows, cols)."""
        centers = self.cell_centers()
        return np.minimum.reduce([centers[..., 0], self.width_m - centers[..., 0],
                                  centers[..., 1], self.height_m - centers[..., 1]])


def _disc_offsets(cell_size_m: float, max_range_m: float) -> np.ndarray:
    """``(row, col)`` offsets (O, 2) of every cell that a disc of the given radius can reach.

    The disc centre lies anywhere in the origin cell, so one extra cell of margin is kept.
    """
    reach = math.ceil(max_range_m / cell_size_m) + 1
    span = np.arange(-reach, reach + 1)
    d_row, d_col = np.meshgrid(span, span, indexing="ij")
    # Nearest possible distance between a point of the origin cell and the offset cell centre.
    gap = np.maximum(np.abs(np.stack([d_row, d_col], axis=-1)) - 0.5, 0.0) * cell_size_m
    keep = np.hypot(gap[..., 0], gap[..., 1]) <= max_range_m
    return np.stack([d_row[keep], d_col[keep]], axis=-1)


def observation_pairs(geometry: GridGeometry, poses: np.ndarray,
                      max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Every (pose, cell) pair such that the cell centre lies within range of the pose.

    Args:
        geometry: the grid layout.
        poses: (K, 3) or (K, 2) map-frame robot poses ``(x [m], y [m], theta [rad])``;
            only the position is used.
        max_range_m: sensing radius [m].

    Returns:
        ``(pose_index, flat_cell)``: two int64 arrays of equal length, in ascending pose
        order; ``flat_cell = row * cols + col``. A pose outside the grid still observes the
        grid cells within range.
    """
    xy = np.asarray(poses, dtype=float)
    if xy.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    xy = xy.reshape(-1, xy.shape[-1])[:, :2]
    offsets = _disc_offsets(geometry.cell_size_m, max_range_m)
    chunk = max(1, _CANDIDATES_PER_CHUNK // len(offsets))
    pose_parts, cell_parts = [], []
    size = geometry.cell_size_m
    for start in range(0, len(xy), chunk):
        block = xy[start:start + chunk]
        base = geometry.world_to_cell(block)
        rows = base[:, 0:1] + offsets[None, :, 0]
        cols = base[:, 1:2] + offsets[None, :, 1]
        d_x = (cols + 0.5) * size - block[:, 0:1]
        d_y = (rows + 0.5) * size - block[:, 1:2]
        seen = ((d_x * d_x + d_y * d_y <= max_range_m ** 2)
                & (rows >= 0) & (rows < geometry.rows) & (cols >= 0) & (cols < geometry.cols))
        pose_parts.append(np.nonzero(seen)[0] + start)
        cell_parts.append(rows[seen] * geometry.cols + cols[seen])
    return np.concatenate(pose_parts), np.concatenate(cell_parts)


def observation_counts(geometry: GridGeometry, poses: np.ndarray, max_range_m: float) -> np.ndarray:
    """Number of poses (K, 3) whose sensing disc of radius ``max_range_m`` [m] covers each
    cell centre; int64 array ``(rows, cols)``."""
    _, flat_cell = observation_pairs(geometry, poses, max_range_m)
    counts = np.bincount(flat_cell, minlength=geometry.rows * geometry.cols)
    return counts.reshape(geometry.shape)


def _logit(probability: float) -> float:
    """Log-odds of a probability in (0, 1)."""
    return math.log(probability / (1.0 - probability))


class OccupancyGrid:
    """Log-odds occupancy of the mission rectangle, rebuilt from the team's SLAM estimate.

    Each observing pose adds ``logit(prob_free)`` to a free cell; a cell containing an
    estimated landmark instead gets ``logit(prob_occupied)`` per observing pose (at least
    one, since its landmark was sensed). A cell therefore only ever receives increments of
    one sign, so clamping the result to ``[logit(prob_min), logit(prob_max)]`` equals
    clamping after every increment. Unobserved cells keep log-odds 0 (probability 0.5).
    """

    def __init__(self, width_m: float, height_m: float, map_params: MapParams,
                 sonar_max_range_m: float) -> None:
        """Args: map rectangle size [m], map parameters, sonar range [m] (observation disc)."""
        probabilities = (map_params.prob_free, map_params.prob_occupied,
                         map_params.prob_min, map_params.prob_max)
        if not all(0.0 < p < 1.0 for p in probabilities):
            raise ValueError(f"occupancy probabilities must lie in (0, 1), got {probabilities}")
        if not map_params.prob_min < 0.5 < map_params.prob_max:
            raise ValueError("prob_min < 0.5 < prob_max is required")
        if sonar_max_range_m <= 0.0:
            raise ValueError(f"sonar range must be positive, got {sonar_max_range_m}")
        self.geometry = GridGeometry(width_m, height_m, map_params.cell_size_m)
        self.params = map_params
        self.sonar_max_range_m = float(sonar_max_range_m)
        self._log_odds = np.zeros(self.geometry.shape)
        self._counts = np.zeros(self.geometry.shape, dtype=np.int64)

    def rebuild(self, poses: np.ndarray, landmarks: np.ndarray) -> None:
        """Recompute the map from scratch.

        Args:
            poses: (K, 3) estimated map-frame keyframe poses of the whole team.
            landmarks: (M, 2) estimated map-frame landmark positions [m]; those outside
                the rectangle are ignored.
        """
        geometry = self.geometry
        counts = observation_counts(geometry, poses, self.sonar_max_range_m)
        landmark_cells = geometry.world_to_cell(np.asarray(landmarks, dtype=float).reshape(-1, 2))
        landmark_cells = landmark_cells[geometry.in_grid(landmark_cells)]
        occupied = np.zeros(geometry.shape, dtype=bool)
        occupied[landmark_cells[:, 0], landmark_cells[:, 1]] = True
        log_odds = counts * _logit(self.params.prob_free)
        log_odds[occupied] = np.maximum(counts[occupied], 1) * _logit(self.params.prob_occupied)
        self._log_odds = np.clip(log_odds, _logit(self.params.prob_min),
                                 _logit(self.params.prob_max))
        self._counts = counts

    @property
    def log_odds(self) -> np.ndarray:
        """Read-only (rows, cols) log-odds of occupancy."""
        view = self._log_odds.view()
        view.flags.writeable = False
        return view

    def observation_count(self) -> np.ndarray:
        """Number of team poses (rows, cols) whose sonar disc covers each cell centre."""
        return self._counts.copy()

    def probability(self) -> np.ndarray:
        """Occupancy probability (rows, cols) in ``[prob_min, prob_max]``; 0.5 = unknown."""
        return 1.0 / (1.0 + np.exp(-self._log_odds))

    def explored_mask(self) -> np.ndarray:
        """Cells (rows, cols) known free (below ``explored_free_below``) or occupied (above
        ``explored_occupied_above``)."""
        probability = self.probability()
        return ((probability < self.params.explored_free_below)
                | (probability > self.params.explored_occupied_above))

    def occupied_mask(self) -> np.ndarray:
        """Cells (rows, cols) known occupied (probability above ``explored_occupied_above``)."""
        return self.probability() > self.params.explored_occupied_above

    def explored_ratio(self) -> float:
        """Fraction of all cells that are explored, in [0, 1]."""
        return float(np.mean(self.explored_mask()))
