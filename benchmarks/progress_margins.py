"""How long robots go without progress toward their targets in runs, to choose the
progress window and minimum progress (``progress.*`` parameters) from measurement.

Runs em-sim's engine with the progress rule switched off (window 1e5 s, blacklist 0 s, so
targets are chosen as before the rule existed) and records, for every robot and every
approach to a target (from its choice to its end), from each robot's own data:

* the longest time the estimated distance to the target did not shrink by ``m`` metres,
  for each ``m`` of ``--min-progress``;
* the longest stretch of steps in which forward motion was commanded but the odometry
  measured under 10 % of it (blocked).

Prints the worst approaches and the distribution. A run that never blocks tells how long
a window must be so that it does not give up reachable targets; a blocked run tells how
quickly a window of that length reacts.

Usage: ``python benchmarks/progress_margins.py --seed 0`` (default scenario) or
``python benchmarks/progress_margins.py --planner CE --map-size 200 --cell-size 4
--landmarks 3 --seed 1``.
"""
from __future__ import annotations

import argparse

import numpy as np

from em_exploration_ros.core.agent.robot_agent import RobotAgent
from em_exploration_ros.core.params import ExplorationParams, ProgressParams
from em_exploration_ros.core.planning.progress import ProgressMonitor
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args

_BLOCKED_FRACTION = 0.1


class _RecordingMonitor(ProgressMonitor):
    """One agent's progress monitor, recording every update as (approach number, stamp
    [s], distance to the target [m], commanded forward [m], odometry forward [m])."""

    def __init__(self, params: ProgressParams) -> None:
        super().__init__(params)
        self._approach = 0
        self.samples: list[tuple[int, float, float, float, float]] = []

    def restart(self) -> None:
        super().restart()
        self._approach += 1

    def update(self, stamp_s, distance_m, commanded_forward_m, odometry_forward_m):
        self.samples.append((self._approach, stamp_s, distance_m, commanded_forward_m,
                             odometry_forward_m))
        return super().update(stamp_s, distance_m, commanded_forward_m, odometry_forward_m)


def _recording_runner(params: ExplorationParams) -> tuple[TeamRunner, list[_RecordingMonitor]]:
    """em-sim's engine whose agents judge progress with recording monitors (one per robot,
    in robot order)."""
    monitors = [_RecordingMonitor(params.progress) for _ in range(params.world.num_robots)]
    runner = TeamRunner(params, make_agent=lambda robot, params, anchor: RobotAgent(
        robot, params, anchor, progress_monitor=monitors[robot]))
    return runner, monitors


def _longest_without_progress(stamps: np.ndarray, distances: np.ndarray, margin: float) -> float:
    best, since, longest = np.inf, stamps[0], 0.0
    for stamp, distance in zip(stamps, distances):
        if distance <= best - margin:
            best, since = distance, stamp
        longest = max(longest, stamp - since)
    return longest


def _longest_blocked(stamps, commanded, odometry) -> float:
    longest, start = 0.0, None
    for stamp, c, o in zip(stamps, commanded, odometry):
        if c > 0.0 and o < _BLOCKED_FRACTION * c:
            start = stamp if start is None else start
            longest = max(longest,
                          stamp - start + (stamps[1] - stamps[0] if len(stamps) > 1 else 0))
        else:
            start = None
    return longest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-progress", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    args = parser.parse_args()
    params = params_from_args(args, args.seed).replace(
        progress={"window_s": 1e5, "blacklist_duration_s": 0.0})
    runner, monitors = _recording_runner(params)
    summary = runner.run()
    print(f"run: {summary.stop_reason}; explored {summary.explored_ratio:.3f}, distance "
          f"{summary.distance_m:.0f} m, {summary.decisions} decisions")
    rows = []
    for robot, monitor in enumerate(monitors):
        if not monitor.samples:
            continue
        data = np.array(monitor.samples)
        for approach in np.unique(data[:, 0]):
            part = data[data[:, 0] == approach]
            if len(part) < 2:
                continue
            stamps = part[:, 1]
            rows.append((robot, stamps[0], stamps[-1] - stamps[0],
                         [_longest_without_progress(stamps, part[:, 2], m)
                          for m in args.min_progress],
                         _longest_blocked(stamps, part[:, 3], part[:, 4])))
    blocked = np.array([r[4] for r in rows])
    print(f"{len(rows)} approaches, {np.count_nonzero(blocked)} with blocked steps (longest "
          f"blocked stretch {blocked.max():.1f} s)")
    for label, chosen in (("never blocked", blocked == 0), ("blocked", blocked > 0)):
        if not np.any(chosen):
            continue
        for index, margin in enumerate(args.min_progress):
            values = np.array([r[3][index] for r in rows])[chosen]
            print(f"{label}: longest time without {margin:g} m closer [s]: max "
                  f"{values.max():.1f}, 99th pct {np.percentile(values, 99):.1f}, median "
                  f"{np.median(values):.1f}")
    worst = sorted(rows, key=lambda r: -max(r[3]))[:5]
    for robot, start, length, longest, blocked_s in worst:
        print(f"  robot {robot} from t={start:.1f} s for {length:.1f} s: without progress "
              f"{', '.join(f'{v:.1f}' for v in longest)} s, blocked {blocked_s:.1f} s")


if __name__ == "__main__":
    main()
