"""How long a run's pictures take to draw: the map, the timeline and the animation.

Runs one em-sim mission (em-sim's run options; the frames of the animation taken as
``em-sim --animate`` takes them), then draws each picture into ``--out`` and prints its wall
and CPU time (the CPU time is what the drawing costs; the wall time grows with the load of a
shared machine). Example (the sparse 200 m scenario)::

    python benchmarks/picture_times.py --seed 0 --map-size 200 --cell-size 4 --landmarks 3 \\
        --out /tmp/pictures
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Callable

from em_exploration_ros.core.evaluation.map_render import render_team_map
from em_exploration_ros.core.evaluation.run_timeline import render_timeline
from em_exploration_ros.core.sessions.team_runner import Progress, TeamRunner
from em_exploration_ros.tools.run_pictures import AnimationFrames
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args


def timed(label: str, work: Callable[[], object]) -> None:
    """Run ``work`` and print its wall and CPU time [s]."""
    wall, cpu = time.perf_counter(), time.process_time()
    work()
    print(f"{label}: wall {time.perf_counter() - wall:.1f} s, "
          f"CPU {time.process_time() - cpu:.1f} s", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_arguments(parser)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True, help="folder for the pictures")
    args = parser.parse_args()
    runner = TeamRunner(params_from_args(args, args.seed))
    frames = AnimationFrames()

    def take_frame(progress: Progress) -> None:
        frames.offer(progress.metrics.stamp_s, runner.map_layers)

    started = time.perf_counter()
    summary = runner.run(take_frame)
    print(f"run: {summary.decisions} decisions, sim {summary.sim_time_s:.0f} s, "
          f"wall {time.perf_counter() - started:.1f} s", flush=True)
    layers = runner.map_layers()
    args.out.mkdir(parents=True, exist_ok=True)
    timed("map", lambda: render_team_map(layers, args.out / "map.png"))
    timed("timeline", lambda: render_timeline(summary.to_dict(), args.out / "timeline.png"))
    timed("animation", lambda: frames.write(summary.sim_time_s, layers, args.out / "run.gif"))
    print(f"animation: {len(frames.recorder.frames)} frames in {args.out / 'run.gif'}")


if __name__ == "__main__":
    main()
