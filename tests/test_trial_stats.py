"""Tests of the statistics across trials: t table, CIs, curves on a distance grid, bands."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.evaluation.trial_stats import (band, curve_on_grid, distance_grid,
                                                 mean_ci, paired_difference, t_critical_95)


def test_t_critical_values_match_the_table_and_fall_back_to_normal():
    values = t_critical_95([0, 1, 2, 9, 30, 31, 1000])
    assert math.isnan(values[0])
    np.testing.assert_allclose(values[1:], [12.706, 4.303, 2.262, 2.042, 1.96, 1.96])
    assert np.all(np.diff(t_critical_95(np.arange(1, 40))) <= 0.0)


def test_mean_ci_of_known_samples_ignores_nan():
    result = mean_ci([1.0, 2.0, np.nan, 3.0, 4.0])
    assert result.n == 4
    assert result.mean == pytest.approx(2.5)
    # s = sqrt(5/3), t(3) = 3.182
    assert result.ci95 == pytest.approx(3.182 * math.sqrt(5.0 / 3.0) / 2.0)


def test_mean_ci_degenerate_cases_and_json_form():
    single = mean_ci([7.0])
    assert single.mean == 7.0 and math.isnan(single.ci95)
    assert single.to_dict() == {"mean": 7.0, "ci95": None, "n": 1}
    empty = mean_ci([np.nan])
    assert empty.n == 0 and math.isnan(empty.mean)


def test_ci_covers_the_true_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(3)
    samples = rng.normal(5.0, 2.0, size=(2000, 8))
    covered = [abs(mean_ci(row).mean - 5.0) <= mean_ci(row).ci95 for row in samples]
    assert 0.93 <= np.mean(covered) <= 0.97


def test_paired_difference_uses_common_seeds_only():
    a = {0: 1.0, 1: 2.0, 2: 4.0, 5: 100.0}
    b = {0: 0.5, 1: 1.0, 2: 3.0, 7: -100.0}
    result = paired_difference(a, b)
    assert result.n == 3
    assert result.mean == pytest.approx((0.5 + 1.0 + 1.0) / 3.0)


def test_curve_on_grid_interpolates_holds_the_last_value_and_skips_waiting():
    distance = [0.0, 10.0, 10.0, 20.0]
    values = [np.nan, 1.0, 2.0, 4.0]  # at 10 m the robots waited; the later sample counts
    grid = np.array([0.0, 5.0, 10.0, 15.0, 20.0, 30.0])
    out = curve_on_grid(distance, values, grid)
    assert math.isnan(out[0]) and math.isnan(out[1])
    np.testing.assert_allclose(out[2:], [2.0, 3.0, 4.0, 4.0])


def test_curve_on_grid_rejects_bad_input():
    assert np.all(np.isnan(curve_on_grid([0.0, 1.0], [np.nan, np.nan], [0.0, 1.0])))
    with pytest.raises(ValueError):
        curve_on_grid([0.0, 2.0, 1.0], [1.0, 2.0, 3.0], [0.0])
    with pytest.raises(ValueError):
        curve_on_grid([0.0, 1.0], [1.0], [0.0])


def test_band_averages_trials_per_grid_point():
    grid = distance_grid(20.0, 3)
    np.testing.assert_allclose(grid, [0.0, 10.0, 20.0])
    curves = np.array([[1.0, 2.0, np.nan], [3.0, 4.0, 5.0]])
    result = band(curves, grid)
    np.testing.assert_allclose(result.mean, [2.0, 3.0, 5.0])
    np.testing.assert_array_equal(result.count, [2, 2, 1])
    half = 12.706 * math.sqrt(2.0) / math.sqrt(2.0)
    np.testing.assert_allclose(result.upper[:2] - result.mean[:2], [half, half])
    assert math.isnan(result.lower[2])
    with pytest.raises(ValueError):
        band(curves, distance_grid(20.0, 4))
