"""The second picture of a run: its metrics over simulation time, from the summary alone.

Three panels sharing the time axis (simulation time [s]), drawn from the summary's
``history`` samples (``RunSummary.to_dict`` data, as written to JSON):

- the team's explored ratio;
- robot localization RMSE and landmark RMSE [m];
- each robot's position uncertainty [m] (``robot_pose_sigma_m``: the square root of the
  trace of the position block of its latest keyframe's marginal covariance), when the
  writer recorded it; otherwise the panel says so.

Every requested meeting that gave an inter-robot factor (the summary's ``meetings``, from
the robots' answers in both drivers) is marked in every panel by a vertical line at its time,
named in the legend as such: a rendezvous that timed out can still end in a meeting, so the
count may differ from the map's rendezvous met. A null (NaN) value leaves a gap.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from em_exploration_ros.core.evaluation.map_render import robot_colour

#: Colour and style of the rendezvous marks.
MEETING_STYLE = {"color": "0.35", "linestyle": ":", "linewidth": 1.0}


def _column(samples: list[Mapping[str, Any]], key: str) -> np.ndarray:
    """One history key over the samples as floats, null as NaN."""
    return np.array([np.nan if s.get(key) is None else float(s[key]) for s in samples])


def _pose_sigmas(samples: list[Mapping[str, Any]]) -> np.ndarray:
    """(samples, robots) position uncertainty [m], NaN where not recorded."""
    rows = [s.get("robot_pose_sigma_m") or [] for s in samples]
    robots = max((len(row) for row in rows), default=0)
    table = np.full((len(rows), robots), np.nan)
    for i, row in enumerate(rows):
        table[i, :len(row)] = [np.nan if v is None else float(v) for v in row]
    return table


def _mark_meetings(panels: list[Axes], summary: Mapping[str, Any]) -> int:
    """Vertical lines at the meetings' times; returns how many."""
    times = sorted(float(m["stamp_s"]) for m in summary.get("meetings") or ()
                   if m.get("stamp_s") is not None)
    for axes in panels:
        for stamp in times:
            axes.axvline(stamp, zorder=0, **MEETING_STYLE)
    return len(times)


def timeline_figure(summary: Mapping[str, Any]) -> Figure:
    """The figure of ``summary`` (see the module docstring); its three axes in order."""
    samples = list(summary.get("history") or ())
    time_s = _column(samples, "sim_time_s")
    figure = Figure(figsize=(9.0, 8.0))
    FigureCanvasAgg(figure)
    explored, rmse, sigma = figure.subplots(3, 1, sharex=True)
    explored.plot(time_s, _column(samples, "explored_ratio"), color="tab:green",
                  label="explored ratio")
    explored.set_ylabel("explored ratio")
    explored.set_ylim(0.0, 1.0)
    rmse.plot(time_s, _column(samples, "loc_rmse_m"), color="black", label="robot RMSE")
    rmse.plot(time_s, _column(samples, "landmark_rmse_m"), color="tab:purple",
              linestyle="--", label="landmark RMSE")
    rmse.set_ylabel("RMSE [m]")
    sigmas = _pose_sigmas(samples)
    for robot in range(sigmas.shape[1]):
        sigma.plot(time_s, sigmas[:, robot], color=robot_colour(robot, sigmas.shape[1]),
                   label=f"robot {robot}")
    if not np.isfinite(sigmas).any():
        sigma.text(0.5, 0.5, "position uncertainty not recorded in this summary",
                   transform=sigma.transAxes, ha="center", va="center", color="0.4")
    sigma.set_ylabel("position sigma [m]")
    sigma.set_xlabel("simulation time [s]")
    meetings = _mark_meetings([explored, rmse, sigma], summary)
    mark = ([Line2D([], [], label=f"meeting: inter-robot factor ({meetings})",
                    **MEETING_STYLE)]
            if meetings else [])
    for axes in (explored, rmse, sigma):
        handles, _ = axes.get_legend_handles_labels()
        if handles:
            axes.legend(handles=handles + mark, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                        fontsize=8, frameon=False)
        axes.grid(alpha=0.3)
    explored.set_title(f"{summary.get('planner', '')}, {summary.get('num_robots', '?')} robots, "
                       f"seed {summary.get('seed', '?')}: {summary.get('stop_reason', '')}",
                       fontsize=10)
    figure.tight_layout()
    return figure


def render_timeline(summary: Mapping[str, Any], path: str | Path, dpi: int = 110) -> Path:
    """Draw the timeline of ``summary`` (``RunSummary.to_dict`` data) into a PNG at ``path``
    (parent folders created); returns the path."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    timeline_figure(summary).savefig(target, dpi=dpi)
    return target
