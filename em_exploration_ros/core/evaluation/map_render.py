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

Points with a non-finite coordinate or farther than ``FAR_OUT_MISSION_SIZES`` mission sizes
outside the rectangle (a diverged estimate, a corrupt recording) are left out, and the
picture says how many: they would not show, and matplotlib's Agg renderer fails on such
coordinates.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers, UncertaintyEllipses
from em_exploration_ros.core.evaluation.summary import TARGET_TYPES

#: Marker of each target type.
TARGET_MARKERS = {"exploration": "^", "revisiting": "s", "rendezvous": "*"}
#: Shade of explored cells (RGBA); unexplored cells are left transparent.
EXPLORED_RGBA = (0.80, 0.90, 0.80, 1.0)


#: How far outside the mission rectangle a point may lie and still be drawn [mission sizes].
FAR_OUT_MISSION_SIZES = 10.0


def drawable_layers(layers: TeamMapLayers) -> tuple[TeamMapLayers, int]:
    """``layers`` without the points that cannot be drawn (see the module docstring), and
    how many were left out (an unusable landmark radius counts as one and is replaced by 0).
    Raises ValueError if the mission size or cell size is not finite and positive."""
    sizes = {"width_m": layers.width_m, "height_m": layers.height_m,
             "cell_size_m": layers.cell_size_m}
    for name, value in sizes.items():
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"the map's {name} must be finite and positive, got {value}")
    reach = FAR_OUT_MISSION_SIZES * max(layers.width_m, layers.height_m)
    left_out = 0

    def near(points: Any, columns: int) -> tuple[np.ndarray, np.ndarray]:
        """(points as (K, columns) floats, mask of those drawable)."""
        nonlocal left_out
        array = np.asarray(points, dtype=float).reshape(-1, columns)
        x, y = array[:, 0], array[:, 1]
        with np.errstate(invalid="ignore"):
            mask = (np.isfinite(array[:, :2]).all(axis=1) & (x >= -reach) & (y >= -reach)
                    & (x <= layers.width_m + reach) & (y <= layers.height_m + reach))
        left_out += int(np.count_nonzero(~mask))
        return array, mask

    def rows(points: Any, columns: int) -> np.ndarray:
        array, mask = near(points, columns)
        return array[mask]

    def entries(items: Sequence[Any]) -> list[Any]:
        _, mask = near([(item.x, item.y) for item in items], 2)
        return [item for item, keep in zip(items, mask) if keep]

    def ellipses(shapes: UncertaintyEllipses) -> UncertaintyEllipses:
        nonlocal left_out
        _, mask = near(shapes.centres, 2)
        axes = np.asarray(shapes.axes, dtype=float).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            sane = ((np.abs(axes) <= reach).all(axis=1)
                    & np.isfinite(np.asarray(shapes.angles, dtype=float)))
        left_out += int(np.count_nonzero(mask & ~sane))
        keep = mask & sane
        return UncertaintyEllipses(shapes.centres[keep], shapes.axes[keep], shapes.angles[keep])

    radius = layers.landmark_radius_m
    if not (np.isfinite(radius) and 0 <= radius <= reach):
        radius, left_out = 0.0, left_out + 1
    drawable = dataclasses.replace(
        layers, landmark_radius_m=radius, true_landmarks=rows(layers.true_landmarks, 2),
        true_paths={r: rows(p, 3) for r, p in layers.true_paths.items()},
        estimated_paths={r: rows(p, 3) for r, p in layers.estimated_paths.items()},
        estimated_landmarks={r: rows(p, 2) for r, p in layers.estimated_landmarks.items()},
        targets={r: entries(t) for r, t in layers.targets.items()},
        uncertainty_ellipses={r: ellipses(e) for r, e in layers.uncertainty_ellipses.items()},
        frontiers={r: entries(f) for r, f in layers.frontiers.items()},
        rendezvous=tuple(entries(layers.rendezvous)))
    return drawable, left_out


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
    """Draw ``layers`` into a PNG at ``path`` (parent folders created); returns the path.
    Raises ValueError for layers that cannot be drawn (see ``drawable_layers``)."""
    explored = np.asarray(layers.explored)
    if explored.ndim != 2:
        raise ValueError(f"explored must be a 2-D cell mask, got shape {explored.shape}")
    layers, left_out = drawable_layers(layers)
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
    if left_out:
        figure.text(0.01, 0.01, f"{left_out} points with non-finite or far-out coordinates "
                    "left out", fontsize=8, color="darkred")
    figure.tight_layout()
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(target, dpi=dpi)
    return target
