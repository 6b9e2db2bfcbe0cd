"""Plots and the Markdown table of the planner comparison, from the files em-bench writes.

Inputs, in the benchmark's output folder: ``results.csv`` (columns ``CSV_COLUMNS``, one row
per trial and metrics sample, missing values empty) and ``summary.json`` (see bench.py).
Outputs there: per setting the paper's three plots, ``<setting>_loc_rmse.png``,
``<setting>_landmark_rmse.png`` and ``<setting>_explored_ratio.png`` (mean and 95%
confidence band per planner against the team's distance travelled, see
core/evaluation/trial_stats.py), and ``results.md`` (final values with 95% CIs and paired
differences). Matplotlib draws through its Agg renderer only (no display, no pyplot state).
"""
from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from em_exploration_ros.core.evaluation.trial_stats import band, curve_on_grid, distance_grid

#: Columns of results.csv.
CSV_COLUMNS = ("setting", "planner", "seed", "distance_m", "explored_ratio", "loc_rmse_m",
               "landmark_rmse_m", "sim_time_s")
#: Plotted metrics: CSV column, file suffix, title, y-axis label.
PLOTS = (("loc_rmse_m", "loc_rmse", "Robot localization RMSE", "localization RMSE [m]"),
         ("landmark_rmse_m", "landmark_rmse", "Landmark position RMSE", "landmark RMSE [m]"),
         ("explored_ratio", "explored_ratio", "Explored ratio", "explored ratio [-]"))
#: Points of the common distance grid of a setting.
GRID_POINTS = 201
#: One colour per planner, the same in every plot.
PLANNER_COLORS = {"EM_2": "tab:blue", "EM_3": "tab:green", "CE": "tab:orange",
                  "BSP": "tab:red", "NEAREST": "tab:gray"}
#: Final values in the Markdown table: summary key, column title, decimals.
TABLE_COLUMNS = (("explored_ratio", "explored ratio", 3), ("distance_m", "distance [m]", 0),
                 ("loc_rmse_m", "robot loc. RMSE [m]", 3),
                 ("landmark_rmse_m", "landmark RMSE [m]", 3))
PAIRED_TITLES = {"loc_rmse_m": ("robot loc. RMSE [m]", 3),
                 "landmark_rmse_m": ("landmark RMSE [m]", 3), "distance_m": ("distance [m]", 0)}


@dataclass(frozen=True)
class TrialCurve:
    """One trial's metrics against the team's distance travelled [m]."""

    seed: int
    distance_m: np.ndarray
    metrics: Mapping[str, np.ndarray]


def read_curves(csv_path: Path) -> dict[str, dict[str, list[TrialCurve]]]:
    """``{setting: {planner: [curves by seed]}}`` from results.csv (empty values are NaN)."""
    columns: dict[tuple[str, str, int], list[list[float]]] = defaultdict(list)
    with csv_path.open(newline="", encoding="utf-8") as stream:
        reader = csv.reader(stream)
        header = next(reader, None)
        if header is None or tuple(header) != CSV_COLUMNS:
            raise ValueError(f"{csv_path}: header {header} is not {list(CSV_COLUMNS)}")
        for row in reader:
            if len(row) != len(CSV_COLUMNS):
                raise ValueError(f"{csv_path}: line {reader.line_num} has {len(row)} values, "
                                 f"not {len(CSV_COLUMNS)}")
            try:
                columns[row[0], row[1], int(row[2])].append(
                    [float(value) if value else np.nan for value in row[3:]])
            except ValueError as error:
                raise ValueError(f"{csv_path}: line {reader.line_num}: {error}") from None
    curves: dict[str, dict[str, list[TrialCurve]]] = defaultdict(lambda: defaultdict(list))
    for (setting, planner, seed), rows in sorted(columns.items()):
        table = np.asarray(rows, dtype=float)
        metrics = {name: table[:, i + 1] for i, name in enumerate(CSV_COLUMNS[4:])}
        curves[setting][planner].append(TrialCurve(seed, table[:, 0], metrics))
    return curves


def plot_metric(curves: Mapping[str, Sequence[TrialCurve]], metric: str, title: str,
                y_label: str, path: Path) -> None:
    """Mean and 95% band of ``metric`` per planner against distance travelled, as PNG."""
    # Imported here: the benchmark's worker processes import this module but never draw.
    from matplotlib.figure import Figure  # pylint: disable=import-outside-toplevel

    longest = max(float(np.nanmax(c.distance_m)) for trials in curves.values() for c in trials)
    grid = distance_grid(longest, GRID_POINTS)
    figure = Figure(figsize=(6.4, 4.4), dpi=110)
    axes = figure.add_subplot()
    for planner, trials in curves.items():
        on_grid = np.array([curve_on_grid(c.distance_m, c.metrics[metric], grid) for c in trials])
        stats = band(on_grid, grid)
        color = PLANNER_COLORS.get(planner)
        axes.plot(grid, stats.mean, color=color, label=f"{planner} (n={len(trials)})")
        axes.fill_between(grid, stats.lower, stats.upper, color=color, alpha=0.2, linewidth=0)
    axes.set_xlabel("distance travelled by the team [m]")
    axes.set_ylabel(y_label)
    axes.set_title(title, fontsize=10)
    axes.set_xlim(0.0, grid[-1] if grid[-1] > 0 else 1.0)
    axes.grid(alpha=0.3)
    axes.legend(loc="best", fontsize=9)
    figure.tight_layout()
    figure.savefig(path, format="png")


def setting_caption(info: Mapping[str, Any], trial_counts: Sequence[int]) -> str:
    """E.g. ``100 m x 100 m, cell 2 m, 3 robots, 20 landmarks, 20 trials per planner``."""
    width, height = info["map_size_m"]
    low, high = min(trial_counts, default=0), max(trial_counts, default=0)
    trials = f"{low}" if low == high else f"{low}-{high}"
    return (f"{width:g} m x {height:g} m, cell {info['cell_size_m']:g} m, "
            f"{info['num_robots']} robots, {info['num_landmarks']} landmarks, "
            f"{trials} trials per planner")


def _with_ci(stat: Mapping[str, Any], decimals: int) -> str:
    if stat["mean"] is None:
        return "n/a"
    if stat["ci95"] is None:
        return f"{stat['mean']:.{decimals}f}"
    return f"{stat['mean']:.{decimals}f} ± {stat['ci95']:.{decimals}f}"


def _activity_row(planner: str, activity: Mapping[str, Any] | None) -> str:
    """One row of the decisions-and-rendezvous table (n/a for results made before it)."""
    if not activity:
        return f"| {planner} |" + " n/a |" * 9
    kinds, meetings = activity["decisions_by_type"], activity["rendezvous"]
    cells = [kinds.get(k, 0) for k in ("exploration", "revisiting", "rendezvous")]
    cells += [activity["planner_failures"]]
    cells += [meetings[k] for k in ("requested", "met", "timed_out", "open")]
    cells += [activity.get("slam_recoveries", "n/a")]
    return f"| {planner} | " + " | ".join(str(c) for c in cells) + " |"


def results_markdown(summary: Mapping[str, Any], plots: Mapping[str, Sequence[Path]]) -> str:
    """results.md: per setting, final values (mean ± 95% CI half width), paired
    differences over common seeds and the plots (``plots``: setting -> PNG paths)."""
    lines = ["# Planner comparison", "",
             "Made by `em-bench planners` (re-make with `em-bench plot --out <folder>`). "
             "Values are the mean ± the half width of the two-sided 95% confidence interval "
             "(Student t) over trials, at the end of each trial (explored-ratio target or "
             "distance/step limit). Trials with the same seed share the world.", ""]
    for setting, info in summary["settings"].items():
        planners = info["planners"]
        caption = setting_caption(info, [p["trials_done"] for p in planners.values()])
        lines += [f"## {setting}: {caption}", "",
                  "| planner | trials done (failed) | reached target "
                  + "".join(f"| {title} " for _, title, _ in TABLE_COLUMNS)
                  + "| wall per trial [s] |",
                  "|---" * (4 + len(TABLE_COLUMNS)) + "|"]
        for name, entry in planners.items():
            wall = entry["wall_s_mean"]
            lines.append(
                f"| {name} | {entry['trials_done']} ({entry['trials_failed']}) "
                f"| {entry['reached_explored_target']} "
                + "".join(f"| {_with_ci(entry['final'][key], digits)} "
                          for key, _, digits in TABLE_COLUMNS)
                + f"| {'n/a' if wall is None else f'{wall:.1f}'} |")
        lines += ["", "Decisions, rendezvous and SLAM updates re-solved in batch (every "
                  "robot's), summed over the finished trials:", "",
                  "| planner | exploration | revisiting | rendezvous | planner failed "
                  "(nearest frontier) | rendezvous requested | met | timed out | open "
                  "| SLAM re-solves |",
                  "|---" * 10 + "|"]
        for name, entry in planners.items():
            lines.append(_activity_row(name, entry.get("activity")))
        versions = "; ".join(f"{name}: {', '.join(entry['code_versions']) or 'n/a'}"
                             for name, entry in planners.items())
        platforms = setting_values(info, "math_platforms")
        lines += ["", f"Reached target: trials that ended at explored ratio "
                  f"{info['until_explored']:g}. Code version (git describe) of the finished "
                  f"trials: {versions}. Their numerical kernels: "
                  f"{' | '.join(platforms) or 'n/a'}.", ""]
        if info["paired_differences"]:
            metrics = list(dict.fromkeys(d["metric"] for d in info["paired_differences"]))
            lines += ["Paired differences A − B of the final values over common seeds "
                      "(negative: A lower):", "",
                      "| A − B | " + " | ".join(PAIRED_TITLES[m][0] for m in metrics) + " |",
                      "|---" * (1 + len(metrics)) + "|"]
            pairs: dict[tuple[str, str], dict[str, Any]] = defaultdict(dict)
            for diff in info["paired_differences"]:
                pairs[diff["a"], diff["b"]][diff["metric"]] = diff
            for (a, b), by_metric in pairs.items():
                lines.append(f"| {a} − {b} | " + " | ".join(
                    _with_ci(by_metric[m], PAIRED_TITLES[m][1]) for m in metrics) + " |")
            lines.append("")
        failures = [(name, f) for name, entry in planners.items() for f in entry["failures"]]
        if failures:
            lines += ["Failed trials:", ""]
            lines += [f"- {name} seed {f['seed']}: `{f['error']}`" for name, f in failures]
            lines.append("")
        lines += [f"![{path.stem}]({path.name})" for path in plots.get(setting, ())]
        lines.append("")
    return "\n".join(lines)


def setting_values(info: Mapping[str, Any], field: str) -> list[str]:
    """The distinct values, sorted, of a per-planner list ``field`` of one setting's
    summary (``code_versions``, ``math_platforms``) over all its planners."""
    return sorted({value for entry in info["planners"].values()
                   for value in entry.get(field, [])})


def summary_problem(summary: Any) -> str | None:
    """What in ``summary`` (summary.json's data) is not as bench.summarize writes it and
    :func:`results_markdown` reads it, or None. Fields added to the summary over time
    (``activity``, ``math_platforms``) may be missing; ``code_versions`` may not."""
    if not isinstance(summary, dict) or not isinstance(summary.get("settings"), dict):
        return "no settings"
    for setting, info in summary["settings"].items():
        problem = _setting_problem(info)
        if problem is not None:
            return f"setting {setting}: {problem}"
    return None


def _setting_problem(info: Any) -> str | None:
    if not isinstance(info, dict):
        return "not an object"
    size = info.get("map_size_m")
    if not (isinstance(size, list) and len(size) == 2 and all(is_number(v) for v in size)):
        return "map_size_m is not two numbers"
    for key in ("cell_size_m", "until_explored", "num_robots", "num_landmarks"):
        if not is_number(info.get(key)):
            return f"{key} is not a number"
    if not isinstance(info.get("planners"), dict):
        return "no planners"
    for name, entry in info["planners"].items():
        problem = _planner_problem(entry)
        if problem is not None:
            return f"planner {name}: {problem}"
    return _paired_problem(info.get("paired_differences"))


def _planner_problem(entry: Any) -> str | None:
    if not isinstance(entry, dict):
        return "not an object"
    for key in ("trials_done", "trials_failed", "reached_explored_target"):
        if not is_number(entry.get(key)):
            return f"{key} is not a number"
    if "wall_s_mean" not in entry or not (entry["wall_s_mean"] is None
                                          or is_number(entry["wall_s_mean"])):
        return "wall_s_mean is not a number or null"
    final = entry.get("final")
    if not isinstance(final, dict) or not all(_is_mean_ci(final.get(key))
                                              for key, _, _ in TABLE_COLUMNS):
        return "final lacks a mean and CI of " + ", ".join(key for key, _, _ in TABLE_COLUMNS)
    for key, default in (("code_versions", None), ("math_platforms", [])):
        if not _is_list_of(entry.get(key, default), str):
            return f"{key} is not a list of strings"
    failures = entry.get("failures")
    if not _is_list_of(failures, dict) or not all("seed" in f and "error" in f
                                                  for f in failures):
        return "failures is not a list of seeds and errors"
    activity = entry.get("activity")
    if activity and not (
            isinstance(activity, dict) and isinstance(activity.get("decisions_by_type"), dict)
            and isinstance(activity.get("rendezvous"), dict)
            and all(key in activity["rendezvous"]
                    for key in ("requested", "met", "timed_out", "open"))
            and "planner_failures" in activity):
        return "activity lacks decisions_by_type, rendezvous or planner_failures"
    return None


def _paired_problem(differences: Any) -> str | None:
    if not _is_list_of(differences, dict):
        return "paired_differences is not a list of objects"
    pairs: dict[tuple[str, str], set[str]] = defaultdict(set)
    for diff in differences:
        if not isinstance(diff.get("metric"), str) or diff["metric"] not in PAIRED_TITLES:
            return f"a paired difference's metric is not one of {sorted(PAIRED_TITLES)}"
        if not (_is_mean_ci(diff) and isinstance(diff.get("a"), str)
                and isinstance(diff.get("b"), str)):
            return "a paired difference lacks its planners, mean or CI"
        pairs[diff["a"], diff["b"]].add(diff["metric"])
    metrics = {diff["metric"] for diff in differences}
    if any(found != metrics for found in pairs.values()):
        return "paired_differences do not give every metric for every pair"
    return None


def is_number(value: Any) -> bool:
    """A JSON number: an int or float, not a boolean."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_mean_ci(value: Any) -> bool:
    return isinstance(value, dict) and all(
        key in value and (value[key] is None or is_number(value[key]))
        for key in ("mean", "ci95"))


def _is_list_of(value: Any, kind: type) -> bool:
    return isinstance(value, list) and all(isinstance(item, kind) for item in value)


def make_all(out_dir: Path, plot: Callable[..., None] = plot_metric) -> list[Path]:
    """All plots and results.md from ``out_dir``'s results.csv and summary.json; ``plot``
    draws each PNG (arguments as ``plot_metric``'s).

    Returns the PNG paths written. FileNotFoundError if an input is missing, ValueError
    naming what is wrong if one is not as em-bench writes it (``summary_problem``,
    ``read_curves``).
    """
    summary_path = out_dir / "summary.json"
    summary = json.loads(summary_path.read_text(encoding="utf-8"))
    problem = summary_problem(summary)
    if problem is not None:
        raise ValueError(f"{summary_path}: {problem}")
    curves = read_curves(out_dir / "results.csv")
    plots: dict[str, list[Path]] = {}
    for setting, info in summary["settings"].items():
        by_planner = {name: curves[setting][name] for name in info["planners"]
                      if name in curves.get(setting, {})}
        if not by_planner:
            continue
        caption = setting_caption(info, [len(trials) for trials in by_planner.values()])
        plots[setting] = []
        for metric, suffix, title, y_label in PLOTS:
            path = out_dir / f"{setting}_{suffix}.png"
            plot(by_planner, metric, f"{title}\n{caption}", y_label, path)
            plots[setting].append(path)
    (out_dir / "results.md").write_text(results_markdown(summary, plots), encoding="utf-8")
    return [path for paths in plots.values() for path in paths]
