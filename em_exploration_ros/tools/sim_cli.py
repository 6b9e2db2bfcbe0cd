"""em-sim: one seeded N-robot exploration in one process, with progress and a JSON summary.

Each robot's SLAM is fed only by its own measurements and by what its teammates would
send it (see core/sessions/team_runner.py). Examples::

    em-sim --robots 3 --planner EM_3 --seed 7 --summary out/run.json
    em-sim --params config/exploration.yaml --map-size 200 --cell-size 4

Exit status: 0 when the run ended by its stop rule (explored ratio, distance, every
robot finished, max_steps), 4 when it stalled (``run.stall_timeout_s`` without team
progress), 2 for bad arguments (output paths included, checked before the run) or an
impossible world, 1 when the summary or the map could not be written at the end (full
disk; no partial file is left), 130 when interrupted.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path
from typing import Callable, Sequence

from em_exploration_ros.core.evaluation.association_stats import association_line
from em_exploration_ros.core.evaluation.summary import activity_line
from em_exploration_ros.core.output_paths import output_path_problem, write_replacing
from em_exploration_ros.core.params import (ExplorationParams, SensorParams,
                                            current_planner_name)
from em_exploration_ros.core.params_yaml import ParamsFileError, load_params
from em_exploration_ros.core.planner_registry import installed_planner_names
from em_exploration_ros.core.sessions.team_runner import Progress, TeamRunner
from em_exploration_ros.core.world.world_file import (WorldFileError, params_for_world,
                                                      read_world_file, world_for_params,
                                                      world_yaml)
from em_exploration_ros.tools.cli_parser import CliParser
from em_exploration_ros.tools.run_pictures import (AnimationFrames, add_picture_arguments,
                                                   default_pictures, picture_problem)

#: A progress line every this many simulation steps.
PROGRESS_EVERY_STEPS = 250
#: Exit status when the summary or the map could not be written after the run.
EXIT_WRITE_FAILED = 1

#: The installed planners: the built-in ones and the plugins' (docs/plugins.md).
PLANNER_NAMES = installed_planner_names()
#: argparse ``type`` of options that name planners: deprecated names map to the new ones.
PLANNER_TYPE = current_planner_name
#: ``--landmark-ids`` values, as ``sensors.landmark_ids``.
LANDMARK_IDS = {"on": True, "off": False}


def sensor_number(field_name: str) -> Callable[[str], float]:
    """argparse ``type`` of an option that sets the number ``sensors.<field_name>``: a value
    outside the field's range is refused with the range."""
    metadata = SensorParams.__dataclass_fields__[field_name].metadata
    low, high = metadata["low"], metadata["high"]

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expects a number, got {text!r}") from None
        if not low <= value <= high:  # NaN too
            raise argparse.ArgumentTypeError(f"must be in [{low:g}, {high:g}], got {text}")
        return value

    return parse


def add_run_arguments(parser: argparse.ArgumentParser, sweep_map_sizes: bool = False) -> None:
    """The options shared by em-sim and the benchmark for one exploration setting.

    With ``sweep_map_sizes`` (the benchmark), ``--map-size`` and ``--cell-size`` take one
    or more values (lists in the parsed arguments).
    """
    sizes = "+" if sweep_map_sizes else None
    parser.add_argument("--params", type=Path, help="ROS 2 parameter YAML file to start from")
    parser.add_argument("--robots", type=int, help="number of robots (default 3)")
    parser.add_argument("--planner", type=PLANNER_TYPE, choices=PLANNER_NAMES,
                        help="planner: a built-in one or an installed plugin's (default EM_3)")
    parser.add_argument("--map-size", type=float, metavar="M", nargs=sizes,
                        help="side of the square map [m] (default 100)")
    parser.add_argument("--cell-size", type=float, metavar="M", nargs=sizes,
                        help="virtual map cell size [m] (default 2)")
    parser.add_argument("--landmarks", type=int, help="number of landmarks (default 20)")
    parser.add_argument("--world", type=Path, metavar="FILE",
                        help="world YAML file (map size, landmarks, start poses; "
                        "docs/worlds.md) instead of the world the seed generates; the "
                        "robots default to one per start")
    parser.add_argument("--until-explored", type=float, metavar="RATIO",
                        help="stop at this team explored ratio (default 0.85)")
    parser.add_argument("--max-steps", type=int, help="stop after this many steps (default 20000)")
    parser.add_argument("--comm-range", type=float, metavar="M",
                        help="links: communication range [m] (default 0 = unlimited)")
    parser.add_argument("--comm-loss", type=float, metavar="P",
                        help="links: loss probability per transmission and receiver (default 0)")
    parser.add_argument("--comm-latency", type=float, metavar="S",
                        help="links: latency [s] (default 0)")
    parser.add_argument("--comm-bandwidth", type=float, metavar="B",
                        help="links: each robot's budget [bytes/s] (default 0 = unlimited)")
    parser.add_argument("--landmark-ids", choices=tuple(LANDMARK_IDS),
                        help="sonar: on, each detection names its landmark (default); off, "
                        "none does and each robot associates its detections itself")
    parser.add_argument("--detection-prob", type=sensor_number("detection_probability"),
                        metavar="P", help="sonar: probability of detecting each landmark in "
                        "range, 0..1 (default 1)")
    parser.add_argument("--clutter-rate", type=sensor_number("clutter_rate"), metavar="R",
                        help="sonar: mean number of false detections per scan, uniform in "
                        "range and bearing (default 0)")


def params_from_args(args: argparse.Namespace, seed: int | None = None) -> ExplorationParams:
    """Parameters from --params and the command-line overrides (ValueError if invalid)."""
    params = load_params(args.params) if args.params else ExplorationParams()
    overrides: dict[str, dict[str, object]] = {}

    def put(group: str, name: str, value: object) -> None:
        if value is not None:
            overrides.setdefault(group, {})[name] = value

    put("world", "num_robots", args.robots)
    put("world", "num_landmarks", args.landmarks)
    if args.map_size is not None:
        put("world", "width_m", args.map_size)
        put("world", "height_m", args.map_size)
    put("map", "cell_size_m", args.cell_size)
    put("planner", "name", args.planner)
    put("run", "until_explored", args.until_explored)
    put("run", "max_steps", args.max_steps)
    put("run", "seed", seed)
    put("links", "range_m", args.comm_range)
    put("links", "loss_probability", args.comm_loss)
    put("links", "latency_s", args.comm_latency)
    put("links", "bandwidth_bytes_per_s", args.comm_bandwidth)
    if args.landmark_ids is not None:
        put("sensors", "landmark_ids", LANDMARK_IDS[args.landmark_ids])
    put("sensors", "detection_probability", args.detection_prob)
    put("sensors", "clutter_rate", args.clutter_rate)
    if args.world is not None and (args.map_size is not None or args.landmarks is not None):
        raise ValueError("--world gives the map size and the landmarks: drop --map-size and "
                         "--landmarks")
    params = params.replace(**overrides) if overrides else params
    if args.world is not None:
        params = params_for_world(params, read_world_file(args.world), args.world, args.robots)
    return params


def build_parser() -> argparse.ArgumentParser:
    parser = CliParser(
        prog="em-sim", description="Run one seeded multi-robot exploration in one process.")
    add_run_arguments(parser)
    parser.add_argument("--seed", type=int, default=None, help="seed of world and noise")
    parser.add_argument("--summary", type=Path, help="write the JSON summary here")
    parser.add_argument("--map", type=Path, metavar="PNG",
                        help="draw the final team map (paths, landmarks, uncertainty, targets, "
                        "rendezvous) into this PNG file (.png); default with --summary: "
                        "beside it, <stem>_map.png, with <stem>_timeline.png")
    add_picture_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    parser.add_argument("--restart", type=_restart, action="append", default=[],
                        metavar="ROBOT:STEP",
                        help="restart robot ROBOT's process before step STEP: it rejoins from "
                        "its journals as a restarted em-robot does (repeatable; "
                        "docs/robustness.md, what a restart costs)")
    parser.add_argument("--save-world", type=Path, metavar="FILE",
                        help="write the run's world (the one the seed generates, or --world's) "
                        "to this YAML file and exit, to edit it and run it with --world and "
                        "the same --seed")
    return parser


def _restart(text: str) -> tuple[int, int]:
    """ROBOT:STEP of ``--restart``."""
    try:
        robot, step = (int(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not ROBOT:STEP") from None
    return robot, step


def _format_progress(progress: Progress) -> str:
    m = progress.metrics
    loc = "n/a" if math.isnan(m.loc_rmse_m) else f"{m.loc_rmse_m:.3f} m"
    return (f"t={m.stamp_s:7.1f} s  explored {m.explored_ratio:5.3f}  "
            f"distance {m.distance_m:7.1f} m  loc RMSE {loc}  decisions {progress.decisions}")


def main(argv: Sequence[str] | None = None,
         make_runner: Callable[[ExplorationParams], TeamRunner] = TeamRunner,
         write_file: Callable[[Path, Callable[[Path], object]], None] = write_replacing
         ) -> int:
    """Entry point of em-sim; returns the process exit code. ``argv``: the arguments (default
    the command line's); ``make_runner``: builds the run's engine from the parameters;
    ``write_file(path, write)``: writes one output file after the run with ``write``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(message)s")
    try:
        params = params_from_args(args, args.seed)
    except WorldFileError as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 2
    except (ParamsFileError, ValueError) as error:
        parser.error(str(error))
    default_pictures(args)
    problem = _output_problem(args) or picture_problem(args)
    if problem:
        parser.error(problem)
    log = logging.getLogger("em-sim")
    if args.save_world:
        return _save_world(params, args.save_world)
    try:
        runner = (make_runner(params, args.restart) if args.restart
                  else make_runner(params))
    except ValueError as error:
        log.error("cannot build the world: %s", error)
        return 2
    frames = AnimationFrames() if args.animate else None

    def report(progress: Progress) -> None:
        if not args.quiet and progress.step % PROGRESS_EVERY_STEPS == 0:
            say(_format_progress(progress))
        if frames is not None:
            frames.offer(progress.metrics.stamp_s, runner.map_layers)

    try:
        summary = runner.run(report)
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    # The files first: a reader that closes stdout early (| head) must not cost them.
    unwritten: list[Path] = []
    if args.summary and not _write_output(args.summary, "--summary", summary.write,
                                          write_file):
        unwritten.append(args.summary)
    if args.map:
        # Imported here: matplotlib takes about 0.4 s to load, half of a trial's start-up,
        # and only a run that draws its map needs it.
        from em_exploration_ros.core.evaluation.map_render import render_team_map
        layers = runner.map_layers()
        if not _write_output(args.map, "--map", lambda path: render_team_map(layers, path),
                             write_file):
            unwritten.append(args.map)
    if args.timeline:
        from em_exploration_ros.core.evaluation.run_timeline import render_timeline
        data = summary.to_dict()
        if not _write_output(args.timeline, "--timeline",
                             lambda path: render_timeline(data, path), write_file):
            unwritten.append(args.timeline)
    if frames is not None:
        final = runner.map_layers()
        if not _write_output(args.animate, "--animate",
                             lambda path: frames.write(summary.sim_time_s, final, path),
                             write_file):
            unwritten.append(args.animate)
    say(f"done ({summary.stop_reason}): explored {summary.explored_ratio:.3f}, "
        f"distance {summary.distance_m:.1f} m, loc RMSE {summary.loc_rmse_m:.3f} m, "
        f"landmark RMSE {summary.landmark_rmse_m:.3f} m, {summary.decisions} decisions, "
        f"wall {summary.wall_s:.1f} s, sim {summary.sim_time_s:.1f} s")
    say(activity_line(summary.to_dict()))
    if summary.association is not None:
        say(association_line(summary.association))
    for agent in runner.agents:
        for recovery in agent.slam.recoveries:
            log.warning("robot %d: %s", agent.robot_id, recovery.describe())
    for label, path in (("summary", args.summary), ("map", args.map),
                        ("timeline", args.timeline), ("animation", args.animate)):
        if path and path not in unwritten:
            say(f"{label}: {path}")
    if unwritten:
        return EXIT_WRITE_FAILED
    return runner.monitor.exit_code  # as em-evaluator's (em-sim loses no robot)


def _output_problem(args: argparse.Namespace) -> str | None:
    """Why --summary or --map cannot be written, or None: each must be writable
    (``output_path_problem``), the map a .png (the only format it is drawn in), and the
    two must not be the same file."""
    for path, option, suffix in ((args.summary, "--summary", None), (args.map, "--map", ".png"),
                                 (args.save_world, "--save-world", None)):
        problem = output_path_problem(path, option, suffix) if path is not None else None
        if problem:
            return problem
    if (args.summary and args.map
            and args.summary.expanduser().resolve() == args.map.expanduser().resolve()):
        return f"--summary and --map name the same file {args.map}"
    return None


def _save_world(params: ExplorationParams, path: Path) -> int:
    """``--save-world``: write the run's world to ``path``; the exit code (2 if the world
    cannot be built, ``EXIT_WRITE_FAILED`` if the file cannot be written)."""
    try:
        world = world_for_params(params)
    except ValueError as error:
        logging.getLogger("em-sim").error("cannot build the world: %s", error)
        return 2
    seed = params.run.seed
    origin = (f"read from {params.world.file}" if params.world.file else
              f"generated by em-sim --seed {seed}")
    comment = (f"World {origin} (docs/worlds.md).\nRun it with: em-sim --world {path.name} "
               f"--seed {seed}\n(the seed draws the sensor noise: the same seed, the same run)")
    text = world_yaml(world, comment)
    if not _write_output(path, "--save-world",
                         lambda target: target.write_text(text, encoding="utf-8")):
        return EXIT_WRITE_FAILED
    say(f"world: {path}")
    return 0


def _write_output(path: Path, option: str, write: Callable[[Path], object],
                  write_file: Callable[[Path, Callable[[Path], object]], None] = write_replacing
                  ) -> bool:
    """Write one output file whole with ``write_file`` (``write_replacing``); False, with
    one error line, if writing failed."""
    try:
        write_file(path, write)
    except OSError as error:
        logging.getLogger("em-sim").error("cannot write %s %s: %s", option, path,
                                          error.strerror or error)
        return False
    return True


def say(line: str) -> None:
    """Print a line to stdout at once; once its reader has gone (``em-sim ... | head``),
    stdout goes to /dev/null and the run goes on to write its files."""
    try:
        print(line, flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


if __name__ == "__main__":
    sys.exit(main())
