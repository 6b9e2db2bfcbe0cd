"""Evaluation metrics of the paper, plotted against the distance travelled.

Robot localization RMSE over the optimized trajectories, landmark position RMSE and the
distance travelled. The explored ratio comes from the occupancy grid and is only stored
here. Poses are ``(x [m], y [m], theta [rad])`` in one common frame (map = world in
simulation); heading differences are wrapped to (-pi, pi].
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.geometry import wrap_angle
from em_exploration_ros.core.sim.world import World

FloatArray = NDArray[np.float64]


def _paired_poses(estimated: ArrayLike, truth: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Both pose arrays as ``(K, 3)`` floats; ValueError unless shapes match."""
    estimated = np.asarray(estimated, dtype=float).reshape(-1, 3)
    truth = np.asarray(truth, dtype=float).reshape(-1, 3)
    if estimated.shape != truth.shape:
        raise ValueError(
            f"estimated {estimated.shape} and truth {truth.shape} poses differ in shape")
    return estimated, truth


def localization_rmse(estimated: ArrayLike, truth: ArrayLike) -> float:
    """Position RMSE [m] between estimated and true poses ``(K, 3)``, row by row.

    Pass the optimized trajectories of all robots concatenated. NaN for ``K = 0``.
    """
    estimated, truth = _paired_poses(estimated, truth)
    if estimated.shape[0] == 0:
        return float("nan")
    squared = np.sum((estimated[:, :2] - truth[:, :2]) ** 2, axis=1)
    return float(np.sqrt(np.mean(squared)))


def heading_rmse(estimated: ArrayLike, truth: ArrayLike) -> float:
    """Heading RMSE [rad] between estimated and true poses ``(K, 3)`` with wrapped
    differences. NaN for ``K = 0``."""
    estimated, truth = _paired_poses(estimated, truth)
    if estimated.shape[0] == 0:
        return float("nan")
    return float(np.sqrt(np.mean(wrap_angle(estimated[:, 2] - truth[:, 2]) ** 2)))


def landmark_rmse(estimates: Mapping[int, ArrayLike], truth: World) -> float:
    """Position RMSE [m] of the estimated landmarks ``{landmark id: (x, y)}`` against the
    world's landmarks; NaN if nothing is estimated. Unknown ids raise ``KeyError``."""
    if not estimates:
        return float("nan")
    row_of_id = {int(landmark_id): row for row, landmark_id in enumerate(truth.landmark_ids)}
    unknown = sorted(set(map(int, estimates)) - set(row_of_id))
    if unknown:
        raise KeyError(f"landmark ids not in the world: {unknown}")
    rows = [row_of_id[int(landmark_id)] for landmark_id in estimates]
    estimated = np.array([np.asarray(p, dtype=float).reshape(2) for p in estimates.values()])
    errors = estimated - truth.landmarks[rows]
    return float(np.sqrt(np.mean(np.sum(errors ** 2, axis=1))))


def path_length(poses: ArrayLike) -> float:
    """Length [m] of the polyline through the positions of poses ``(K, 3)``; 0 if K < 2."""
    xy = np.asarray(poses, dtype=float).reshape(-1, 3)[:, :2]
    return float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)))


@dataclass(frozen=True)
class MetricSample:
    """The metrics at one moment: team distance travelled [m], localization RMSE [m],
    landmark RMSE [m] (NaN if none estimated) and explored ratio [0, 1]."""

    distance_m: float
    loc_rmse_m: float
    landmark_rmse_m: float
    explored_ratio: float


class MetricHistory:
    """Samples appended during a run, returned as arrays for plotting against distance."""

    def __init__(self) -> None:
        """An empty history."""
        self._samples: list[MetricSample] = []

    def append(self, sample: MetricSample) -> None:
        """Record one sample."""
        self._samples.append(sample)

    def __len__(self) -> int:
        """Number of samples."""
        return len(self._samples)

    def as_arrays(self) -> dict[str, FloatArray]:
        """``{field name of MetricSample: (S,) float array}`` in the order appended."""
        return {f.name: np.array([getattr(s, f.name) for s in self._samples], dtype=float)
                for f in fields(MetricSample)}
