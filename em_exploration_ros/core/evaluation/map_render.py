"""Picture of a team's map: a PNG drawn with matplotlib's Agg backend (no display).

Layers (:class:`map_layers.TeamMapLayers`), all in the mission rectangle
``[0, width] x [0, height]`` (the map frame, which is the world frame in simulation), metres,
drawn so that a mission of hundreds of decisions still reads at a glance:

- the explored area of the team virtual map (explored cells shaded);
- the team virtual map's uncertainty: a 1-sigma ellipse per observed cell (grey outlines),
  as in the paper's figures (from a recording: the smallest of the robots' own ellipses);
- each robot's true trajectory (solid) and estimated keyframe trajectory (dashed), one colour
  per robot, with its start (a large dot);
- true landmarks (dark discs, at least ``MIN_LANDMARK_FRACTION`` of the mission size across)
  and each robot's landmark estimates (crosses), above everything but the labels;
- the targets each robot chose, small, marker shape by frontier type (exploration,
  revisiting; rendezvous targets larger) and colour by robot; targets given up as large
  crosses; each robot's last frontier candidates (hollow markers) when known;
- requested rendezvous: a ring at the meeting point, black when the robots met, grey
  otherwise; one label per meeting place (``1→0``; ``0→2, 2→0`` when both asked there; a
  count when more than once), placed where it covers no other label (left out, and counted,
  where no place is free).

The legend names every symbol drawn. Points with a non-finite coordinate or farther than
``FAR_OUT_MISSION_SIZES`` mission sizes outside the rectangle (a diverged estimate, a
corrupt recording) are left out, and the picture says how many: they would not show, and
matplotlib's Agg renderer fails on such coordinates.

``draw_team_map`` draws the layers into given axes (the picture and each frame of
``run_animation``).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.axes import Axes
from matplotlib.collections import EllipseCollection
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.legend_handler import HandlerPatch
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Ellipse
from matplotlib.transforms import Bbox

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers, fused_ellipses
from em_exploration_ros.core.evaluation.summary import TARGET_TYPES
from em_exploration_ros.core.virtual_map.ellipses import ELLIPSE_SIGMAS, UncertaintyEllipses

#: Marker of each target type.
TARGET_MARKERS = {"exploration": "^", "revisiting": "s", "rendezvous": "*"}
#: Marker size [pt] of each chosen target type: small, the rendezvous ones stand out.
TARGET_SIZES = {"exploration": 3.5, "revisiting": 4.0, "rendezvous": 9.0}
#: True landmarks are drawn at least this fraction of the mission size across.
MIN_LANDMARK_FRACTION = 0.025
#: Diameter of a rendezvous ring [points].
RING_SIZE = 14.0
#: Rendezvous closer than this fraction of the mission size share one label.
RENDEZVOUS_PLACE_FRACTION = 0.03
#: Offsets [points] tried in turn for a rendezvous label, from its ring's centre.
LABEL_OFFSETS = ((8, 8), (8, -16), (-8, 8), (-8, -16), (12, -4), (-12, -4), (0, 14),
                 (0, -22))
#: Z-order of each layer, bottom to top.
Z = {"explored": 0, "ellipses": 1, "border": 1, "frontiers": 2, "targets": 3,
     "true_path": 4, "estimated_path": 5, "rings": 6, "rendezvous_target": 7, "given_up": 8,
     "start": 9, "landmark": 10, "landmark_estimate": 11, "label": 12}
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
        rendezvous=tuple(entries(layers.rendezvous)),
        given_up={r: entries(g) for r, g in layers.given_up.items()},
        team_uncertainty=(None if layers.team_uncertainty is None
                          else ellipses(layers.team_uncertainty)))
    return drawable, left_out


def robot_colour(robot: int, robots: int = 10) -> tuple[float, float, float, float]:
    """One colour per robot: tab10 for teams of up to 10, tab20 for larger ones."""
    if robots <= 10:
        return colormaps["tab10"](robot % 10)
    return colormaps["tab20"](robot % 20)


def _robots(layers: TeamMapLayers) -> list[int]:
    return sorted(set(layers.true_paths) | set(layers.estimated_paths) | set(layers.targets)
                  | set(layers.estimated_landmarks) | set(layers.given_up))


def _draw_explored(axes: Axes, layers: TeamMapLayers) -> None:
    explored = np.asarray(layers.explored, dtype=bool)
    rows, cols = explored.shape
    shaded = np.ma.masked_where(~explored, np.ones(explored.shape))
    axes.imshow(shaded, origin="lower", cmap=ListedColormap([EXPLORED_RGBA]),
                extent=(0.0, cols * layers.cell_size_m, 0.0, rows * layers.cell_size_m),
                interpolation="nearest", zorder=Z["explored"])


def _team_ellipses(layers: TeamMapLayers) -> UncertaintyEllipses | None:
    """The one set of cell ellipses drawn: the team's, else the robots' own fused."""
    if layers.team_uncertainty is not None:
        return layers.team_uncertainty
    if any(e.count for e in layers.uncertainty_ellipses.values()):
        return fused_ellipses(layers.uncertainty_ellipses)
    return None


def _draw_uncertainty(axes: Axes, layers: TeamMapLayers) -> int:
    """1-sigma cell ellipses; returns how many were drawn."""
    ellipses = _team_ellipses(layers)
    if ellipses is None or not ellipses.count:
        return 0
    axes.add_collection(EllipseCollection(
        ellipses.axes[:, 0] / ELLIPSE_SIGMAS, ellipses.axes[:, 1] / ELLIPSE_SIGMAS,
        np.degrees(ellipses.angles), units="xy", offsets=ellipses.centres,
        offset_transform=axes.transData, facecolors="none", edgecolors="0.45",
        linewidths=0.4, zorder=Z["ellipses"], label="_cell ellipses"))
    return ellipses.count


def _landmark_radius(layers: TeamMapLayers) -> float:
    """Radius [m] a true landmark is drawn with."""
    size = max(layers.width_m, layers.height_m)
    return max(layers.landmark_radius_m, 0.5 * MIN_LANDMARK_FRACTION * size)


def _draw_landmarks(axes: Axes, layers: TeamMapLayers, robots: int) -> None:
    radius = _landmark_radius(layers)
    for x, y in np.asarray(layers.true_landmarks, dtype=float).reshape(-1, 2):
        axes.add_patch(Circle((x, y), radius, facecolor="0.2", edgecolor="white",
                              linewidth=1.0, zorder=Z["landmark"]))
    for robot, positions in sorted(layers.estimated_landmarks.items()):
        xy = np.asarray(positions, dtype=float).reshape(-1, 2)
        axes.plot(xy[:, 0], xy[:, 1], "x", color=robot_colour(robot, robots), markersize=6,
                  markeredgewidth=1.6, linestyle="none", zorder=Z["landmark_estimate"])


def _draw_paths(axes: Axes, layers: TeamMapLayers, robots: int) -> None:
    for robot, poses in sorted(layers.true_paths.items()):
        xy = np.asarray(poses, dtype=float).reshape(-1, 3)[:, :2]
        if len(xy):
            axes.plot(xy[:, 0], xy[:, 1], "-", color=robot_colour(robot, robots),
                      linewidth=1.3, zorder=Z["true_path"])
            axes.plot(xy[0, 0], xy[0, 1], "o", color=robot_colour(robot, robots),
                      markersize=8, markeredgecolor="black", linestyle="none",
                      zorder=Z["start"])
    for robot, poses in sorted(layers.estimated_paths.items()):
        xy = np.asarray(poses, dtype=float).reshape(-1, 3)[:, :2]
        axes.plot(xy[:, 0], xy[:, 1], "--", color=robot_colour(robot, robots), linewidth=1.0,
                  alpha=0.9, zorder=Z["estimated_path"])


def _draw_targets(axes: Axes, layers: TeamMapLayers, robots: int) -> None:
    for robot, entries in sorted(layers.targets.items()):
        colour = robot_colour(robot, robots)
        for kind in TARGET_TYPES:
            xy = np.array([(t.x, t.y) for t in entries if t.type == kind]).reshape(-1, 2)
            if kind == "rendezvous":
                axes.plot(xy[:, 0], xy[:, 1], TARGET_MARKERS[kind], color=colour,
                          markeredgecolor="black", markeredgewidth=0.6,
                          markersize=TARGET_SIZES[kind], linestyle="none",
                          zorder=Z["rendezvous_target"])
            else:
                axes.plot(xy[:, 0], xy[:, 1], TARGET_MARKERS[kind], color=colour,
                          markeredgewidth=0.0, markersize=TARGET_SIZES[kind], alpha=0.8,
                          linestyle="none", zorder=Z["targets"])
    for robot, entries in sorted(layers.given_up.items()):
        xy = np.array([(g.x, g.y) for g in entries]).reshape(-1, 2)
        axes.plot(xy[:, 0], xy[:, 1], "X", color=robot_colour(robot, robots),
                  markeredgecolor="black", markeredgewidth=0.8, markersize=8,
                  linestyle="none", zorder=Z["given_up"])
    for robot, entries in sorted(layers.frontiers.items()):
        for kind in TARGET_TYPES:
            xy = np.array([(f.x, f.y) for f in entries if f.type == kind]).reshape(-1, 2)
            axes.plot(xy[:, 0], xy[:, 1], TARGET_MARKERS[kind], markerfacecolor="none",
                      markeredgecolor=robot_colour(robot, robots), markersize=5,
                      linestyle="none", zorder=Z["frontiers"])


def rendezvous_labels(layers: TeamMapLayers) -> list[tuple[float, float, str, bool]]:
    """One label per meeting place: (x [m], y [m], text, any met there), the rendezvous
    within ``RENDEZVOUS_PLACE_FRACTION`` of the mission size of the place's first one
    grouped, each pair named once (``a→b``, with ``×n`` when asked n > 1 times there)."""
    reach = RENDEZVOUS_PLACE_FRACTION * max(layers.width_m, layers.height_m)
    places: list[tuple[float, float, dict[tuple[int, int], int], list[bool]]] = []
    for meeting in layers.rendezvous:
        for x, y, pairs, met in places:
            if np.hypot(meeting.x - x, meeting.y - y) <= reach:
                break
        else:
            x, y, pairs, met = meeting.x, meeting.y, {}, []
            places.append((x, y, pairs, met))
        pair = (meeting.requester_id, meeting.partner_id)
        pairs[pair] = pairs.get(pair, 0) + 1
        met.append(meeting.outcome == "met")
    return [(x, y, ", ".join(f"{a}\u2192{b}" + (f" \u00d7{n}" if n > 1 else "")
                             for (a, b), n in sorted(pairs.items())), any(met))
            for x, y, pairs, met in places]


def _draw_rendezvous(axes: Axes, layers: TeamMapLayers) -> None:
    for meeting in layers.rendezvous:
        met = meeting.outcome == "met"
        axes.plot(meeting.x, meeting.y, "o", markersize=RING_SIZE, markerfacecolor="none",
                  markeredgecolor="black" if met else "0.5", markeredgewidth=1.8,
                  linestyle="none", zorder=Z["rings"])


def _label_obstacles(axes: Axes, layers: TeamMapLayers) -> list[Bbox]:
    """Display extents a label must not cover: the rendezvous rings and true landmarks."""
    half = 0.5 * RING_SIZE * axes.figure.dpi / 72.0
    boxes = []
    for meeting in layers.rendezvous:
        x, y = axes.transData.transform((meeting.x, meeting.y))
        boxes.append(Bbox.from_extents(x - half, y - half, x + half, y + half))
    radius = _landmark_radius(layers)
    for x, y in np.asarray(layers.true_landmarks, dtype=float).reshape(-1, 2):
        corners = axes.transData.transform([(x - radius, y - radius), (x + radius, y + radius)])
        boxes.append(Bbox(corners))
    return boxes


def label_rendezvous(axes: Axes, layers: TeamMapLayers) -> int:
    """Label the meeting places (``rendezvous_labels``), each at the first offset of
    ``LABEL_OFFSETS`` where it lies inside the axes and covers no label placed before, no
    rendezvous ring and no landmark; returns how many found no free place (left out). Call
    it once the figure's layout is final: the check is made on the extents as drawn."""
    renderer = axes.figure.canvas.get_renderer()
    frame = axes.get_window_extent(renderer)
    obstacles = _label_obstacles(axes, layers)
    placed: list[Bbox] = []
    unplaced = 0
    for x, y, text, met in rendezvous_labels(layers):
        for offset in LABEL_OFFSETS:
            label = axes.annotate(text, (x, y), xytext=offset, textcoords="offset points",
                                  fontsize=7, color="black" if met else "0.35",
                                  zorder=Z["label"], annotation_clip=True,
                                  bbox={"boxstyle": "square,pad=0.05", "facecolor": "white",
                                        "edgecolor": "none", "alpha": 0.7})
            box = label.get_window_extent(renderer)
            inside = (box.x0 >= frame.x0 and box.x1 <= frame.x1 and box.y0 >= frame.y0
                      and box.y1 <= frame.y1)
            if inside and not any(box.overlaps(other) for other in placed + obstacles):
                placed.append(box)
                break
            label.remove()
        else:
            unplaced += 1
    return unplaced


class _EllipseHandler(HandlerPatch):
    """Legend key of the cell ellipses: an ellipse that fills the key's height."""

    def create_artists(self, legend, orig_handle, xdescent, ydescent, width, height,
                       fontsize, trans):
        ellipse = Ellipse((width / 2 - xdescent, height / 2 - ydescent), width * 0.9,
                          height * 1.3, angle=0.0, facecolor="none", edgecolor="0.3",
                          linewidth=1.0, transform=trans)
        return [ellipse]


def legend_handles(layers: TeamMapLayers, ellipses: int) -> list[Any]:
    """A legend entry for every symbol ``draw_team_map`` draws of ``layers`` (``ellipses``:
    how many cell ellipses were drawn)."""
    robots = _robots(layers)
    handles: list[Any] = [Line2D([], [], color=robot_colour(r, len(robots)), linewidth=2.0,
                                 label=f"robot {r}") for r in robots]
    handles += [Line2D([], [], color="black", linestyle="-", label="true path"),
                Line2D([], [], color="black", linestyle="--", label="estimated path"),
                Line2D([], [], marker="o", color="0.6", markeredgecolor="black", markersize=8,
                       linestyle="none", label="start"),
                Line2D([], [], marker="o", color="0.2", markersize=7, linestyle="none",
                       label="landmark"),
                Line2D([], [], marker="x", color="black", markeredgewidth=1.6,
                       linestyle="none", label="landmark estimate")]
    chosen = {t.type for entries in layers.targets.values() for t in entries}
    handles += [Line2D([], [], marker=TARGET_MARKERS[k], color="0.3",
                       markersize=max(TARGET_SIZES[k], 5.0),
                       markeredgecolor="black" if k == "rendezvous" else "0.3",
                       linestyle="none", label=f"{k} target")
                for k in TARGET_TYPES if k in chosen]
    if any(layers.given_up.values()):
        handles.append(Line2D([], [], marker="X", color="0.6", markeredgecolor="black",
                              markersize=8, linestyle="none", label="target given up"))
    if any(layers.frontiers.values()):
        handles.append(Line2D([], [], marker="^", markerfacecolor="none",
                              markeredgecolor="black", markersize=5, linestyle="none",
                              label="last frontiers (shape: type)"))
    if ellipses:
        handles.append(Ellipse((0, 0), 1, 1, facecolor="none", edgecolor="0.3",
                               label="cell uncertainty (1 sigma)"))
    outcomes = {m.outcome == "met" for m in layers.rendezvous}
    handles += [Line2D([], [], marker="o", markersize=10, markerfacecolor="none",
                       markeredgecolor=colour, markeredgewidth=1.8, linestyle="none",
                       label=label)
                for met, colour, label in ((True, "black", "rendezvous met"),
                                           (False, "0.5", "rendezvous not met"))
                if met in outcomes]
    return handles


def draw_team_map(axes: Axes, layers: TeamMapLayers, extra_handles: Sequence[Any] = ()) -> int:
    """Draw drawable ``layers`` (``drawable_layers``) into ``axes`` with the legend beside
    them (``extra_handles`` last: the caller's own symbols), all but the rendezvous labels
    (``label_rendezvous``, once the layout is final). Returns how many cell ellipses were
    drawn."""
    robots = len(_robots(layers))
    _draw_explored(axes, layers)
    ellipses = _draw_uncertainty(axes, layers)
    _draw_targets(axes, layers, robots)
    _draw_paths(axes, layers, robots)
    _draw_landmarks(axes, layers, robots)
    axes.plot([0, layers.width_m, layers.width_m, 0, 0], [0, 0, layers.height_m,
              layers.height_m, 0], color="black", linewidth=1.0, zorder=Z["border"])
    margin = 0.02 * max(layers.width_m, layers.height_m)
    axes.set_xlim(-margin, layers.width_m + margin)
    axes.set_ylim(-margin, layers.height_m + margin)
    axes.set_aspect("equal")
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")
    if layers.title:
        axes.set_title(layers.title, fontsize=10)
    _draw_rendezvous(axes, layers)
    axes.legend(handles=legend_handles(layers, ellipses) + list(extra_handles),
                handler_map={Ellipse: _EllipseHandler()}, loc="upper left",
                bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return ellipses


def render_team_map(layers: TeamMapLayers, path: str | Path, dpi: int = 110) -> Path:
    """Draw ``layers`` into a PNG at ``path`` (parent folders created); returns the path.
    Raises ValueError for layers that cannot be drawn (see ``drawable_layers``)."""
    figure = team_map_figure(layers)
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(target, dpi=dpi)
    return target


def team_map_figure(layers: TeamMapLayers) -> Figure:
    """The picture of ``layers`` as a matplotlib figure (Agg canvas); its first axes hold
    the map. Raises ValueError for layers that cannot be drawn (see ``drawable_layers``)."""
    explored = np.asarray(layers.explored)
    if explored.ndim != 2:
        raise ValueError(f"explored must be a 2-D cell mask, got shape {explored.shape}")
    layers, left_out = drawable_layers(layers)
    figure = Figure(figsize=(9.0, 7.0))
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    draw_team_map(axes, layers)
    figure.tight_layout()
    notes = []
    if left_out:
        notes.append(f"{left_out} points with non-finite or far-out coordinates left out")
    unlabelled = label_rendezvous(axes, layers)
    if unlabelled:
        notes.append(f"{unlabelled} rendezvous places unlabelled (no free place)")
    if notes:
        figure.text(0.01, 0.01, "; ".join(notes), fontsize=8, color="darkred")
    return figure
