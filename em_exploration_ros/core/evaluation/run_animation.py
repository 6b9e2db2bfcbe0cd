"""An animation of a run: the team map (``map_render``) at moments of the run, one frame each.

Whoever watches the run hands ``FrameRecorder.offer`` the map layers (``map_layers``) as
the run goes; the recorder keeps at most ``max_frames`` frames evenly spread over the run
(when full, it keeps every other frame and halves its rate) and thins each frame's true
paths to at most ``MAX_PATH_POINTS`` poses, so that a long mission costs little memory.
``render_animation`` draws the frames into a GIF (matplotlib's Pillow writer) or, for a
``.mp4`` path, an MP4 (matplotlib's ffmpeg writer; ffmpeg must be installed). Each frame
is the picture of the run so far, plus every robot's position at that moment (a ringed
dot).
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.animation import FFMpegWriter, PillowWriter
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.map_render import (Z, draw_team_map, drawable_layers,
                                                           label_rendezvous, robot_colour)

#: A frame's true paths keep at most this many poses per robot (the last one always).
MAX_PATH_POINTS = 1500
#: Formats ``render_animation`` writes, by path suffix.
ANIMATION_SUFFIXES = (".gif", ".mp4")


def thinned(layers: TeamMapLayers, max_points: int = MAX_PATH_POINTS) -> TeamMapLayers:
    """``layers`` with each true path cut to at most ``max_points`` evenly spaced poses,
    its first and last kept."""
    def thin(path: np.ndarray) -> np.ndarray:
        path = np.asarray(path, dtype=float).reshape(-1, 3)
        if len(path) <= max_points:
            return path
        rows = np.unique(np.linspace(0, len(path) - 1, max_points).round().astype(int))
        return path[rows]
    return dataclasses.replace(layers, true_paths={r: thin(p) for r, p in
                                                   layers.true_paths.items()})


def _frame(stamp_s: float, layers: TeamMapLayers) -> TeamMapLayers:
    """The frame of ``layers`` at ``stamp_s`` [s]: thinned, its time in the title."""
    title = f"{layers.title}, t = {stamp_s:.0f} s" if layers.title else f"t = {stamp_s:.0f} s"
    return dataclasses.replace(thinned(layers), title=title)


class FrameRecorder:
    """Keeps the frames of an animation (see the module docstring): a frame offered at
    simulation time ``stamp_s`` [s] is kept when ``interval_s`` has passed since the last
    kept one."""

    def __init__(self, interval_s: float = 5.0, max_frames: int = 120) -> None:
        if max_frames < 2 or interval_s <= 0:
            raise ValueError("an animation needs max_frames >= 2 and interval_s > 0")
        self.interval_s = interval_s
        self.max_frames = max_frames
        self.frames: list[TeamMapLayers] = []
        self._stamps: list[float] = []

    def due(self, stamp_s: float) -> bool:
        """Whether a frame offered at ``stamp_s`` would be kept (build its layers only then)."""
        return not self._stamps or stamp_s >= self._stamps[-1] + self.interval_s - 1e-9

    def offer(self, stamp_s: float, layers: TeamMapLayers) -> bool:
        """Keep ``layers`` as the frame at ``stamp_s`` if due; returns whether kept."""
        if not self.due(stamp_s):
            return False
        self.frames.append(_frame(stamp_s, layers))
        self._stamps.append(stamp_s)
        if len(self.frames) > self.max_frames:
            self.frames, self._stamps = self.frames[::2], self._stamps[::2]
            self.interval_s *= 2.0
        return True

    def finish(self, stamp_s: float, layers: TeamMapLayers) -> None:
        """Keep the run's final picture as the last frame, whatever the interval (in place of
        the last one kept if that was as late or the recorder is full)."""
        if self._stamps and (self._stamps[-1] >= stamp_s
                             or len(self.frames) >= self.max_frames):
            self.frames.pop()
            self._stamps.pop()
        self.frames.append(_frame(stamp_s, layers))
        self._stamps.append(stamp_s)


def _draw_frame(axes: Axes, layers: TeamMapLayers) -> None:
    """Draw one frame into ``axes``, in place of the previous frame's artists (the axes and
    their ticks are kept: making them anew costs a third of a frame)."""
    for artist in [*axes.lines, *axes.collections, *axes.patches, *axes.images, *axes.texts]:
        artist.remove()
    drawable, _ = drawable_layers(layers)
    robots = sorted(drawable.true_paths)
    now = Line2D([], [], marker="o", color="0.4", markersize=9, markeredgecolor="white",
                 markeredgewidth=2.0, linestyle="none", label="robot now")
    draw_team_map(axes, drawable, extra_handles=[now])
    for robot in robots:
        path = drawable.true_paths[robot]
        if len(path):
            axes.plot(path[-1, 0], path[-1, 1], "o", color=robot_colour(robot, len(robots)),
                      markersize=9, markeredgecolor="white", markeredgewidth=2.0,
                      linestyle="none", zorder=Z["start"])
    label_rendezvous(axes, drawable)


def render_animation(frames: Sequence[TeamMapLayers], path: str | Path, fps: float = 8.0,
                     dpi: int = 72) -> Path:
    """Draw ``frames`` in order into an animation at ``path`` (.gif, or .mp4 when ffmpeg is
    installed; parent folders created); returns the path. Raises ValueError for no frames,
    another suffix, an MP4 without ffmpeg, or layers that cannot be drawn."""
    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in ANIMATION_SUFFIXES:
        raise ValueError(f"an animation is written as {' or '.join(ANIMATION_SUFFIXES)}, "
                         f"not {target.name}")
    if suffix == ".mp4" and shutil.which("ffmpeg") is None:
        raise ValueError("an MP4 needs ffmpeg, which is not installed: write a .gif instead")
    if not frames:
        raise ValueError("an animation needs at least one frame")
    figure = Figure(figsize=(9.0, 7.0))
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    figure.subplots_adjust(left=0.08, right=0.74, bottom=0.08, top=0.94)
    writer = PillowWriter(fps=fps) if suffix == ".gif" else FFMpegWriter(fps=fps)
    target.parent.mkdir(parents=True, exist_ok=True)
    with writer.saving(figure, str(target), dpi):
        for layers in frames:
            _draw_frame(axes, layers)
            writer.grab_frame()
    return target
