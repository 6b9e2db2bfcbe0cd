"""Where a lockstep step's round trip goes: trace the team's publishes and callbacks.

``run_team.sh --trace-steps DIR`` starts every node through ``run``: before the node's
module runs, rclpy's ``Publisher.publish`` and every subscription callback are wrapped to
record ``(CLOCK_MONOTONIC time [ns], event, topic)`` into ``DIR/<name>.trace`` as a publish
starts and as a callback starts (the clock is the host's, so the processes' times
compare); as the process exits, a last line records the CPU time it used. Nothing else
changes; a traced run makes the same decisions, a little slower.

``report`` reads such a directory and prints the median time of each stage of a step:
the world's publish phase (its ``/clock`` to its last ground truth), each sensor message's
way to its robot's callback, the robot's work up to its command, the command's way to the
world, and the whole step; then each process's CPU time. Events are matched by order (the
n-th ``/clock`` with the n-th odometry callback and command of each robot), which holds
for a lockstep run without lost robots or re-sent steps.

    python -m em_exploration_ros.tools.step_trace report DIR
"""
from __future__ import annotations

import argparse
import atexit
import resource
import runpy
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO

import numpy as np

from em_exploration_ros.tools.cli_parser import CliParser

#: Events buffered before they are written (a killed process loses at most these).
_FLUSH_EVERY = 500
PUBLISH, CALLBACK_START = "pub", "cb"
#: The event of the line a process writes as it exits; its third field is its CPU time [s].
CPU = "cpu"
#: The latest time a trace line can carry [ns of the monotonic clock]: the int64 range of
#: the arrays it is read into.
_LATEST_NS = 2 ** 63 - 1


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

    def finish(self) -> None:
        """At exit: the process's CPU time (user + system, every thread), then flush."""
        usage = resource.getrusage(resource.RUSAGE_SELF)
        self.lines.append(f"{time.monotonic_ns()} {CPU} {usage.ru_utime + usage.ru_stime:.3f}\n")
        self.flush()


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
    atexit.register(trace.finish)
    install(trace)
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


@dataclass(frozen=True)
class StageTimes:
    """Per-step durations [s] of one stage (one value per matched step)."""

    name: str
    seconds: np.ndarray


@dataclass(frozen=True)
class ProcessTrace:
    """One process's trace file, read once: event times [s] by (event, topic) in file
    order, its CPU time [s] (None if it did not exit normally) and how many lines could not
    be read (a process killed while writing leaves a cut line)."""

    times: dict[tuple[str, str], np.ndarray]
    cpu_s: float | None
    unreadable: int

    def of(self, event: str, topic: str) -> np.ndarray:
        """Times [s] of one event on one topic (empty if none)."""
        return self.times.get((event, topic), np.zeros(0))


def read_trace(path: Path) -> ProcessTrace:
    """Read a ``.trace`` file written by ``run``."""
    groups: dict[tuple[str, str], list[int]] = defaultdict(list)
    cpu_s, unreadable = None, 0
    for line in path.read_text(encoding="ascii", errors="replace").splitlines():
        fields = line.split(" ")
        if len(fields) != 3 or not fields[0].isdigit() or int(fields[0]) > _LATEST_NS:
            unreadable += 1
        elif fields[1] == CPU:
            try:
                cpu_s = float(fields[2])
            except ValueError:
                unreadable += 1
        else:
            groups[(fields[1], fields[2])].append(int(fields[0]))
    return ProcessTrace({key: np.array(values, dtype=np.int64) * 1e-9
                         for key, values in groups.items()}, cpu_s, unreadable)


def read_traces(directory: Path, num_robots: int) -> dict[str, ProcessTrace]:
    """The traces of the world, robots 0..N-1 and the evaluator (if it has one).

    Raises:
        FileNotFoundError: the world's or a robot's trace is missing.
    """
    names = ["world", *(f"robot_{robot}" for robot in range(num_robots))]
    if (directory / "evaluator.trace").is_file():
        names.append("evaluator")
    return {name: read_trace(directory / f"{name}.trace") for name in names}


def stages(traces: dict[str, ProcessTrace], num_robots: int) -> list[StageTimes]:
    """The stage durations of a traced lockstep run (see the module docstring)."""
    world = traces["world"]
    clock = world.of(PUBLISH, "/clock")
    truth_last = world.of(PUBLISH, f"/world/ground_truth/robot_{num_robots - 1}")
    result = []
    count = min(len(clock), len(truth_last))
    result.append(StageTimes("world publishes a step (clock to last ground truth)",
                             truth_last[:count] - clock[:count]))
    for robot in range(num_robots):
        robot_trace = traces[f"robot_{robot}"]
        odometry_sent = world.of(PUBLISH, f"/robot_{robot}/odom")
        odometry_heard = robot_trace.of(CALLBACK_START, f"/robot_{robot}/odom")
        command_sent = robot_trace.of(PUBLISH, f"/robot_{robot}/motion_command")
        command_heard = world.of(CALLBACK_START, f"/robot_{robot}/motion_command")
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


def report(traces: dict[str, ProcessTrace], num_robots: int) -> str:
    """The stage table and the processes' CPU times of a traced run, as printed by the
    ``report`` command."""
    lines = [f"{'stage':58s} {'steps':>6s} {'median':>9s} {'mean':>9s} {'total':>8s}"]
    for stage in stages(traces, num_robots):
        seconds = stage.seconds
        if len(seconds) == 0:
            lines.append(f"{stage.name:58s} {0:6d} {'-':>9s} {'-':>9s} {'-':>8s}")
            continue
        lines.append(f"{stage.name:58s} {len(seconds):6d} {1e3 * np.median(seconds):7.2f}ms "
                     f"{1e3 * np.mean(seconds):7.2f}ms {np.sum(seconds):7.2f}s")
    lines.append("CPU time [s]: " + ", ".join(
        f"{name} {'? (no exit line)' if trace.cpu_s is None else f'{trace.cpu_s:.2f}'}"
        for name, trace in traces.items()))
    unreadable = {name: t.unreadable for name, t in traces.items() if t.unreadable}
    if unreadable:
        lines.append(f"unreadable lines skipped: {unreadable}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``run`` (a traced node process) or ``report`` (the stage table of a traced run);
    returns the exit code (2 for bad arguments)."""
    parser = CliParser(prog="python -m em_exploration_ros.tools.step_trace",
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
    if args.robots is not None and args.robots < 1:
        parser.error(f"--robots must be at least 1, got {args.robots}")
    if robots < 1:
        parser.error(f"no robot_<i>.trace in {args.directory}")
    try:
        traces = read_traces(args.directory, robots)
    except FileNotFoundError as error:
        parser.error(f"{error.filename}: no such trace (--robots {robots}?)")
    except OSError as error:
        parser.error(f"{error.filename}: cannot read it ({error.strerror})")
    print(report(traces, robots))
    return 0


if __name__ == "__main__":
    sys.exit(main())
