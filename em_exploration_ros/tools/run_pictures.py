"""em-sim's pictures of a run: which files, where, and the frames of its animation.

- the map (``--map PNG``, ``map_render``) and the timeline (``--timeline PNG``,
  ``run_timeline``): named, they are drawn where named; with neither named, a run that
  writes a summary draws both beside it, as run_team.sh's evaluator draws its map
  (``run.json`` -> ``run_map.png``, ``run_timeline.png``), unless ``--no-pictures``;
- the animation (``--animate GIF|MP4``, ``run_animation``): only when asked; its frames are
  the map layers taken during the run (``AnimationFrames``).

matplotlib is imported only when a picture is drawn (about 0.4 s, half of a trial's
start-up).
"""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Callable

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.output_paths import output_path_problem

#: Suffixes of the default pictures beside a summary ``<stem>.json``.
MAP_SUFFIX, TIMELINE_SUFFIX = "_map.png", "_timeline.png"
#: Simulation time between the animation's frames at first [s] (``FrameRecorder``).
ANIMATION_INTERVAL_S = 5.0
#: At most this many frames in an animation.
ANIMATION_MAX_FRAMES = 60


def add_picture_arguments(parser: argparse.ArgumentParser) -> None:
    """``--timeline``, ``--animate`` and ``--no-pictures`` (``--map`` is em-sim's own)."""
    parser.add_argument("--timeline", type=Path, metavar="PNG",
                        help="draw the metrics over time (explored ratio, RMSE, each robot's "
                        "position uncertainty, rendezvous) into this PNG file")
    parser.add_argument("--animate", type=Path, metavar="GIF",
                        help="draw an animation of the run into this .gif (or .mp4 where "
                        "ffmpeg is installed)")
    parser.add_argument("--no-pictures", action="store_true",
                        help="with --summary, draw no map and no timeline beside it")


def default_pictures(args: argparse.Namespace) -> None:
    """Fill ``args.map`` and ``args.timeline`` beside ``args.summary`` when neither is named
    (see the module docstring)."""
    if args.summary and not args.no_pictures and args.map is None and args.timeline is None:
        stem = args.summary.with_suffix("").name
        args.map = args.summary.with_name(stem + MAP_SUFFIX)
        args.timeline = args.summary.with_name(stem + TIMELINE_SUFFIX)


def picture_problem(args: argparse.Namespace) -> str | None:
    """Why ``--timeline`` or ``--animate`` cannot be written, or None."""
    if args.timeline is not None:
        problem = output_path_problem(args.timeline, "--timeline", ".png")
        if problem:
            return problem
    if args.animate is not None:
        suffix = args.animate.suffix.lower()
        problem = output_path_problem(args.animate, "--animate",
                                      suffix if suffix in (".gif", ".mp4") else ".gif")
        if problem:
            return problem
        if suffix == ".mp4" and shutil.which("ffmpeg") is None:
            return f"--animate {args.animate}: an MP4 needs ffmpeg, not installed (use .gif)"
    return None


class AnimationFrames:
    """The frames of ``--animate``: ``offer`` them every evaluation, ``write`` at the end."""

    def __init__(self) -> None:
        from em_exploration_ros.core.evaluation.run_animation import FrameRecorder
        self.recorder = FrameRecorder(ANIMATION_INTERVAL_S, ANIMATION_MAX_FRAMES)

    def offer(self, stamp_s: float, layers: Callable[[], TeamMapLayers]) -> None:
        """A frame at simulation time ``stamp_s`` [s]; ``layers`` is called only if due."""
        if self.recorder.due(stamp_s):
            self.recorder.offer(stamp_s, layers())

    def write(self, stamp_s: float, final: TeamMapLayers, path: Path) -> None:
        """The animation, ending on ``final`` (the run's map at ``stamp_s``), into ``path``."""
        from em_exploration_ros.core.evaluation.run_animation import render_animation
        self.recorder.finish(stamp_s, final)
        render_animation(self.recorder.frames, path)
