"""Estimation errors of the paper's evaluation: robot localization RMSE over the optimized
trajectories and landmark position RMSE.

Poses are ``(x [m], y [m], theta [rad])`` and landmarks ``(x [m], y [m])`` in one common
frame (map = world in simulation). The distance travelled and the explored ratio, the
other metrics of the paper, are computed by ``evaluator.TeamEvaluator``.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.world.world import World

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


def nearest_landmark_rmse(points: ArrayLike, truth: World) -> float:
    """Position RMSE [m] of estimated landmarks ``(K, 2)`` that name no world landmark
    (``sensors.landmark_ids`` false), each against the nearest true landmark; NaN if
    nothing is estimated (or the world has no landmark)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if points.shape[0] == 0 or truth.landmarks.shape[0] == 0:
        return float("nan")
    distances = np.linalg.norm(points[:, None, :] - truth.landmarks[None, :, :], axis=2)
    return float(np.sqrt(np.mean(distances.min(axis=1) ** 2)))
