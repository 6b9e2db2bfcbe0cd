"""Statistics across repeated exploration trials: means and 95% confidence intervals.

A trial's metrics are sampled against the team's distance travelled [m]; different trials
are sampled at different distances and end at different distances. ``curve_on_grid`` puts
one trial's curve on a common distance grid and ``band`` averages the trials on it.

Conventions:

- Confidence intervals are two-sided 95% intervals of the mean, ``mean +- t * s / sqrt(n)``
  with ``s`` the sample standard deviation (ddof 1) and ``t`` the Student-t critical value
  for ``n - 1`` degrees of freedom. The t values for 1..30 degrees of freedom are tabulated
  below; from 31 on the normal value 1.96 is used (the t value for 30 is 2.042, for 60
  2.000, so the interval is then at most ~4% too narrow). One sample has no interval (NaN).
- NaN samples are missing values (e.g. a landmark RMSE before any landmark was seen) and
  are ignored.
- A trial that ended before a grid distance keeps its final value there (the exploration
  is over, its map and estimates stay as they were); before its first finite sample it is
  missing. The mean at every distance therefore covers all trials that had started
  reporting that metric.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Two-sided 95% Student-t critical values, index = degrees of freedom (index 0 unused).
_T_95 = (np.nan, 12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
         2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
         2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)
#: Two-sided 95% normal critical value, used above the table.
_Z_95 = 1.96


def t_critical_95(dof: ArrayLike) -> FloatArray:
    """Two-sided 95% critical value for ``dof`` degrees of freedom (NaN for dof < 1)."""
    dof = np.asarray(dof, dtype=int)
    table = np.asarray(_T_95)
    out = np.where(dof >= len(table), _Z_95, table[np.clip(dof, 0, len(table) - 1)])
    return np.where(dof < 1, np.nan, out)


@dataclass(frozen=True)
class MeanCI:
    """Mean of some samples and the half width of its 95% confidence interval."""

    mean: float
    ci95: float
    n: int

    def to_dict(self) -> dict[str, float | int | None]:
        """Plain data, NaN as None (for JSON)."""
        return {"mean": _finite_or_none(self.mean), "ci95": _finite_or_none(self.ci95),
                "n": self.n}


def mean_ci(values: ArrayLike) -> MeanCI:
    """Mean and 95% CI half width of ``values``, ignoring NaN (NaN mean if none left)."""
    mean, half, count = _column_stats(np.asarray(values, dtype=float).reshape(-1, 1))
    return MeanCI(float(mean[0]), float(half[0]), int(count[0]))


def paired_difference(a: Mapping[int, float], b: Mapping[int, float]) -> MeanCI:
    """Mean and 95% CI of ``a[seed] - b[seed]`` over the seeds both have finite values for.

    With the seed fixing the world, this compares two planners trial by trial (paired).
    """
    seeds = sorted(set(a) & set(b))
    diffs = np.array([a[s] - b[s] for s in seeds], dtype=float)
    return mean_ci(diffs)


def distance_grid(max_distance_m: float, points: int = 201) -> FloatArray:
    """``points`` evenly spaced distances [m] from 0 to ``max_distance_m``."""
    return np.linspace(0.0, max(float(max_distance_m), 0.0), points)


def curve_on_grid(distance_m: ArrayLike, values: ArrayLike, grid_m: ArrayLike) -> FloatArray:
    """One trial's metric, sampled at non-decreasing ``distance_m`` [m], on ``grid_m`` [m].

    Linear interpolation between finite samples; NaN before the first finite sample, the
    last finite value after the last one. Where the distance does not change (robots
    waiting) the last sample at that distance is used. All NaN if no sample is finite.
    """
    distance_m = np.asarray(distance_m, dtype=float)
    values = np.asarray(values, dtype=float)
    grid_m = np.asarray(grid_m, dtype=float)
    if distance_m.shape != values.shape:
        raise ValueError(f"distance {distance_m.shape} and values {values.shape} differ in shape")
    finite = np.isfinite(values) & np.isfinite(distance_m)
    distance_m, values = distance_m[finite], values[finite]
    if distance_m.size == 0:
        return np.full(grid_m.shape, np.nan)
    if np.any(np.diff(distance_m) < 0.0):
        raise ValueError("distance samples must be non-decreasing")
    # Last sample of each distinct distance: unique() on the reversed array finds it first.
    _, first_in_reversed = np.unique(distance_m[::-1], return_index=True)
    keep = distance_m.size - 1 - first_in_reversed
    return np.interp(grid_m, distance_m[keep], values[keep], left=np.nan, right=values[keep][-1])


@dataclass(frozen=True)
class Band:
    """Mean across trials and its 95% confidence band on a distance grid."""

    grid_m: FloatArray
    mean: FloatArray
    lower: FloatArray
    upper: FloatArray
    count: NDArray[np.int_]


def band(curves: ArrayLike, grid_m: ArrayLike) -> Band:
    """Mean and 95% band of ``curves`` ``(trials, grid points)`` (NaN = missing)."""
    curves = np.asarray(curves, dtype=float)
    grid_m = np.asarray(grid_m, dtype=float)
    if curves.ndim != 2 or curves.shape[1] != grid_m.size:
        raise ValueError(f"curves {curves.shape} do not match a grid of {grid_m.size} points")
    mean, half, count = _column_stats(curves)
    return Band(grid_m, mean, mean - half, mean + half, count)


def _column_stats(samples: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.int_]]:
    """Per column of ``samples`` (rows = trials): mean, 95% CI half width, finite count."""
    finite = np.isfinite(samples)
    count = finite.sum(axis=0)
    filled = np.where(finite, samples, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = filled.sum(axis=0) / count
        squares = np.where(finite, (samples - mean) ** 2, 0.0).sum(axis=0)
        std = np.sqrt(squares / (count - 1))
        half = t_critical_95(count - 1) * std / np.sqrt(count)
    mean = np.where(count > 0, mean, np.nan)
    return mean, np.where(count > 1, half, np.nan), count


def _finite_or_none(value: float) -> float | None:
    return value if np.isfinite(value) else None
