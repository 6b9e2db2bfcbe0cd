"""Picture of a team's final map: a PNG drawn with matplotlib's Agg backend (no display).

Layers (:class:`map_layers.TeamMapLayers`), all in the mission rectangle
``[0, width] x [0, height]`` (the map frame, which is the world frame in simulation), metres:

- the explored area of the team virtual map (explored cells shaded);
- true landmarks (circles of their radius) and each robot's landmark estimates (crosses);
- each robot's true trajectory (solid) and estimated keyframe trajectory (dashed), one colour
  per robot, with its start marked;
- the targets each robot chose, marker shape by frontier type (exploration, revisiting,
  rendezvous) and colour by robot;
- each robot's virtual-map uncertainty ellipses (outlines) and its last frontier candidates
  (hollow markers, shape by type), colour by robot;
- requested rendezvous: a ring at the meeting point, solid black when the robots met,
  grey otherwise, labelled ``requester→partner``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.summary import TARGET_TYPES

#: Marker of each target type.
TARGET_MARKERS = {"exploration": "^", "revisiting": "s", "rendezvous": "*"}
#: Shade of explored cells (RGBA); unexplored cells are left transparent.
EXPLORED_RGBA = (0.80, 0.90, 0.80, 1.0)


def _robot_colour(robot: int) -> tuple[float, float, float, float]:
    return colormaps["tab10"](robot % 10)


def _draw_explored(axes, layers: TeamMapLayers) -> None:
    explored = np.asarray(layers.explored, dtype=bool)
    rows, cols = explored.shape
    shaded = np.ma.masked_where(~explored, np.ones(explored.shape))
    axes.imshow(shaded, origin="lower", cmap=ListedColormap([EXPLORED_RGBA]),
                extent=(0.0, cols * layers.cell_size_m, 0.0, rows * layers.cell_size_m),
                interpolation="nearest", zorder=0)


def _draw_landmarks(axes, layers: TeamMapLayers) -> None:
    radius = max(layers.landmark_radius_m, 0.2)
    for x, y in np.asarray(layers.true_landmarks, dtype=float).reshape(-1, 2):
        axes.add_patch(Circle((x, y), radius, facecolor="0.35", edgecolor="black", zorder=2))
    for robot, positions in sorted(layers.estimated_landmarks.items()):
        xy = np.asarray(positions, dtype=float).reshape(-1, 2)
        axes.plot(xy[:, 0], xy[:, 1], "x", color=_robot_colour(robot), markersize=6,
                  markeredgewidth=1.5, zorder=5)


def _draw_paths(axes, layers: TeamMapLayers) -> None:
    for robot, poses in sorted(layers.true_paths.items()):
        xy = np.asarray(poses, dtype=float).reshape(-1, 3)[:, :2]
        if len(xy):
            axes.plot(xy[:, 0], xy[:, 1], "-", color=_robot_colour(robot), linewidth=1.2,
                      zorder=3)
            axes.plot(xy[0, 0], xy[0, 1], "o", color=_robot_colour(robot), markersize=7,
                      markeredgecolor="black", zorder=6)
    for robot, poses in sorted(layers.estimated_paths.items()):
        xy = np.asarray(poses, dtype=float).reshape(-1, 3)[:, :2]
        axes.plot(xy[:, 0], xy[:, 1], "--", color=_robot_colour(robot), linewidth=1.0,
                  alpha=0.9, zorder=4)


def _draw_targets(axes, layers: TeamMapLayers) -> None:
    for robot, entries in sorted(layers.targets.items()):
        for kind in TARGET_TYPES:
            xy = np.array([(t.x, t.y) for t in entries if t.type == kind]).reshape(-1, 2)
            axes.plot(xy[:, 0], xy[:, 1], TARGET_MARKERS[kind], color=_robot_colour(robot),
                      markeredgecolor="black", markersize=8, linestyle="none", zorder=7)


def _draw_uncertainty(axes, layers: TeamMapLayers) -> None:
    for robot, ellipses in sorted(layers.uncertainty_ellipses.items()):
        if ellipses.count:
            axes.add_collection(EllipseCollection(
                ellipses.axes[:, 0], ellipses.axes[:, 1], np.degrees(ellipses.angles),
                units="xy", offsets=ellipses.centres, offset_transform=axes.transData,
                facecolors="none", edgecolors=[_robot_colour(robot)], linewidths=0.6,
                alpha=0.7, zorder=1))
    for robot, entries in sorted(layers.frontiers.items()):
        for kind in TARGET_TYPES:
            xy = np.array([(f.x, f.y) for f in entries if f.type == kind]).reshape(-1, 2)
            axes.plot(xy[:, 0], xy[:, 1], TARGET_MARKERS[kind], markerfacecolor="none",
                      markeredgecolor=_robot_colour(robot), markersize=5, linestyle="none",
                      zorder=6)


def _draw_rendezvous(axes, layers: TeamMapLayers) -> None:
    for meeting in layers.rendezvous:
        met = meeting.outcome == "met"
        axes.plot(meeting.x, meeting.y, "o", markersize=18, markerfacecolor="none",
                  markeredgecolor="black" if met else "0.5", markeredgewidth=2.0,
                  linestyle="none", zorder=8)
        axes.annotate(f"{meeting.requester_id}\u2192{meeting.partner_id}", (meeting.x, meeting.y),
                      xytext=(9, 9), textcoords="offset points", fontsize=8,
                      color="black" if met else "0.4", zorder=8)


def _legend(axes, robots: list[int], with_rendezvous: bool) -> None:
    handles = [Line2D([], [], color=_robot_colour(r), label=f"robot {r}") for r in robots]
    handles += [Line2D([], [], color="black", linestyle="-", label="true path"),
                Line2D([], [], color="black", linestyle="--", label="estimated path"),
                Line2D([], [], marker="o", color="0.35", linestyle="none", label="landmark"),
                Line2D([], [], marker="x", color="black", linestyle="none",
                       label="landmark estimate")]
    handles += [Line2D([], [], marker=TARGET_MARKERS[k], color="white", markeredgecolor="black",
                       linestyle="none", label=f"{k} target") for k in TARGET_TYPES]
    handles += [Line2D([], [], marker="o", markerfacecolor="none", markeredgecolor="black",
                       linestyle="none", label="uncertainty ellipse (3 sigma)"),
                Line2D([], [], marker="^", markerfacecolor="none", markeredgecolor="black",
                       markersize=5, linestyle="none", label="last frontiers (shape: type)")]
    if with_rendezvous:
        handles += [Line2D([], [], marker="o", markersize=10, markerfacecolor="none",
                           markeredgecolor=colour, markeredgewidth=2.0, linestyle="none",
                           label=label)
                    for colour, label in (("black", "rendezvous met"),
                                          ("0.5", "rendezvous not met"))]
    axes.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
                frameon=False)


def render_team_map(layers: TeamMapLayers, path: str | Path, dpi: int = 110) -> Path:
    """Draw ``layers`` into a PNG at ``path`` (parent folders created); returns the path."""
    explored = np.asarray(layers.explored)
    if explored.ndim != 2:
        raise ValueError(f"explored must be a 2-D cell mask, got shape {explored.shape}")
    figure = Figure(figsize=(9.0, 7.0))
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    _draw_explored(axes, layers)
    _draw_landmarks(axes, layers)
    _draw_paths(axes, layers)
    _draw_targets(axes, layers)
    _draw_uncertainty(axes, layers)
    _draw_rendezvous(axes, layers)
    axes.plot([0, layers.width_m, layers.width_m, 0, 0], [0, 0, layers.height_m,
              layers.height_m, 0], color="black", linewidth=1.0, zorder=1)
    margin = 0.02 * max(layers.width_m, layers.height_m)
    axes.set_xlim(-margin, layers.width_m + margin)
    axes.set_ylim(-margin, layers.height_m + margin)
    axes.set_aspect("equal")
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")
    if layers.title:
        axes.set_title(layers.title, fontsize=10)
    robots = sorted(set(layers.true_paths) | set(layers.estimated_paths) | set(layers.targets))
    _legend(axes, robots, bool(layers.rendezvous))
    figure.tight_layout()
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(target, dpi=dpi)
    return target
