"""Where a lockstep step's round trip goes: trace the team's publishes and callbacks.

``run_team.sh --trace-steps DIR`` starts every node through ``run``: before the node's
module runs, rclpy's ``Publisher.publish`` and every subscription callback are wrapped to
record ``(CLOCK_MONOTONIC time [ns], event, topic)`` into ``DIR/<name>.trace`` as a publish
starts and as a callback starts (the clock is the host's, so the processes' times
compare). Nothing else changes; a traced run makes
the same decisions, a little slower.

``report`` reads such a directory and prints the median time of each stage of a step:
the world's publish phase (its ``/clock`` to its last ground truth), each sensor message's
way to its robot's callback, the robot's work up to its command, the command's way to the
world, and the whole step. Events are matched by order (the n-th ``/clock`` with the n-th
odometry callback and command of each robot), which holds for a lockstep run without lost
robots or re-sent steps.

    python -m em_exploration_ros.tools.step_trace report DIR
"""
from __future__ import annotations

import argparse
import atexit
import runpy
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO

import numpy as np

#: Events buffered before they are written (a killed process loses at most these).
_FLUSH_EVERY = 500
PUBLISH, CALLBACK_START = "pub", "cb"


class _TraceFile:
    """A bounded buffer of trace lines, written out every ``_FLUSH_EVERY`` and at exit."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.lines: list[str] = []

    def add(self, event: str, topic: str) -> None:
        self.lines.append(f"{time.monotonic_ns()} {event} {topic}\n")
        if len(self.lines) >= _FLUSH_EVERY:
            self.flush()

    def flush(self) -> None:
        self.stream.writelines(self.lines)
        self.stream.flush()
        self.lines.clear()


def install(trace: _TraceFile) -> None:
    """Wrap rclpy's publish and every subscription callback created from now on."""
    from rclpy.publisher import Publisher
    from rclpy.subscription import Subscription

    publish = Publisher.publish

    def traced_publish(self: Publisher, message: object) -> None:
        trace.add(PUBLISH, self.topic_name)  # before: a subscriber may take it at once
        publish(self, message)

    create = Subscription.__init__

    def traced_init(self: Subscription, *args: object, **kwargs: object) -> None:
        create(self, *args, **kwargs)
        callback: Callable[..., object] = self.callback
        topic = self.topic_name

        def traced_callback(*callback_args: object) -> object:
            trace.add(CALLBACK_START, topic)
            return callback(*callback_args)

        self.callback = traced_callback

    Publisher.publish = traced_publish
    Subscription.__init__ = traced_init


def run(trace_path: Path, module: str, args: list[str]) -> None:
    """Run ``python -m module args`` in this process with tracing into ``trace_path``."""
    stream = open(trace_path, "a", encoding="ascii")
    trace = _TraceFile(stream)
    atexit.register(trace.flush)
    install(trace)
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


@dataclass(frozen=True)
class StageTimes:
    """Per-step durations [s] of one stage (one value per matched step)."""

    name: str
    seconds: np.ndarray


def _events(path: Path, event: str, topic: str) -> np.ndarray:
    """Times [s] of one event on one topic in a trace file, in file order."""
    times = [int(stamp) for stamp, kind, name in
             (line.split() for line in path.read_text(encoding="ascii").splitlines()
              if line.count(" ") == 2)
             if kind == event and name == topic]
    return np.array(times, dtype=np.int64) * 1e-9


def stages(directory: Path, num_robots: int) -> list[StageTimes]:
    """The stage durations of a traced lockstep run (see the module docstring)."""
    world = directory / "world.trace"
    clock = _events(world, PUBLISH, "/clock")
    truth_last = _events(world, PUBLISH, f"/world/ground_truth/robot_{num_robots - 1}")
    result = []
    count = min(len(clock), len(truth_last))
    result.append(StageTimes("world publishes a step (clock to last ground truth)",
                             truth_last[:count] - clock[:count]))
    for robot in range(num_robots):
        robot_trace = directory / f"robot_{robot}.trace"
        odometry_sent = _events(world, PUBLISH, f"/robot_{robot}/odom")
        odometry_heard = _events(robot_trace, CALLBACK_START, f"/robot_{robot}/odom")
        command_sent = _events(robot_trace, PUBLISH, f"/robot_{robot}/motion_command")
        command_heard = _events(world, CALLBACK_START, f"/robot_{robot}/motion_command")
        count = min(len(odometry_sent), len(odometry_heard), len(command_sent),
                    len(command_heard))
        result += [
            StageTimes(f"robot {robot}: odometry published to its callback",
                       odometry_heard[:count] - odometry_sent[:count]),
            StageTimes(f"robot {robot}: odometry callback to command published",
                       command_sent[:count] - odometry_heard[:count]),
            StageTimes(f"robot {robot}: command published to the world's callback",
                       command_heard[:count] - command_sent[:count])]
    result.append(StageTimes("whole step (clock to next clock)", np.diff(clock)))
    return result


def report(directory: Path, num_robots: int) -> str:
    """The stage table of a traced run, as printed by the ``report`` command."""
    lines = [f"{'stage':58s} {'steps':>6s} {'median':>9s} {'mean':>9s} {'total':>8s}"]
    for stage in stages(directory, num_robots):
        seconds = stage.seconds
        if len(seconds) == 0:
            lines.append(f"{stage.name:58s} {0:6d} {'-':>9s} {'-':>9s} {'-':>8s}")
            continue
        lines.append(f"{stage.name:58s} {len(seconds):6d} {1e3 * np.median(seconds):7.2f}ms "
                     f"{1e3 * np.mean(seconds):7.2f}ms {np.sum(seconds):7.2f}s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``run`` (a traced node process) or ``report`` (the stage table of a traced run);
    returns the exit code (2 for bad arguments)."""
    parser = argparse.ArgumentParser(prog="python -m em_exploration_ros.tools.step_trace",
                                     description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    traced = commands.add_parser("run", help="run a node module with tracing")
    traced.add_argument("--out", type=Path, required=True, help="trace file to append to")
    traced.add_argument("module", help="the node's module (as for python -m)")
    traced.add_argument("args", nargs=argparse.REMAINDER, help="the node's arguments")
    summary = commands.add_parser("report", help="print the stage times of a traced run")
    summary.add_argument("directory", type=Path, help="the --trace-steps directory")
    summary.add_argument("--robots", type=int, default=None,
                         help="team size (default: the robot_<i>.trace files present)")
    args = parser.parse_args(argv)
    if args.command == "run":
        run(args.out, args.module, args.args)
        return 0
    if not (args.directory / "world.trace").is_file():
        parser.error(f"no world.trace in {args.directory} (run run_team.sh --trace-steps DIR)")
    robots = args.robots if args.robots is not None else len(
        list(args.directory.glob("robot_*.trace")))
    if robots < 1:
        parser.error(f"no robot_<i>.trace in {args.directory}")
    print(report(args.directory, robots))
    return 0


if __name__ == "__main__":
    sys.exit(main())
