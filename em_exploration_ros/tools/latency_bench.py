"""em-bench latency: planner decision time against the size of the team graph.

Builds a synthetic 3-robot team graph (random walks at 2 m per keyframe in a 100 m x 100 m
map with 20 landmarks, exact measurements with the sensor-derived noise models, teammate
readings whenever two robots are within sonar range at the same keyframe) with 250, 500,
1000 and 2000 poses, gives robot 0 about 20 candidates (exploration frontiers around it,
revisiting frontiers near landmarks, rendezvous at the teammates' targets) and prints the
median wall and CPU time of one decision of each planner and that time per candidate,
the agreement of the fast EM step with the re-solve oracle (largest relative difference
of a 3x3 covariance block) together with the oracle's time per candidate, and the error
of the approximate U_M (planner.history_change_tolerance) against the exact one; then a
least-squares line ``time per candidate = a + b * graph variables`` per planner, to set
against the authors' 0.057 s + 2.7e-4 s per variable. BLAS is single-threaded by default
(see the package docstring).
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from typing import Sequence

import numpy as np

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.em_oracle import propagate_oracle
from em_exploration_ros.core.planning.em_scenario import ScenarioBuilder, TeamSnapshot, VirtualNoise
from em_exploration_ros.core.planning.em_step import DecisionFactorization
from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.planning.planners import PlanningContext, make_planner
from em_exploration_ros.core.records.readings import OdometryReading
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.slam.synthetic_team import exact_team_slam
from em_exploration_ros.core.slam.team_slam import OdometryAccumulator, TeamSlam
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid
from em_exploration_ros.core.world.sensors import odometry_covariance_per_step
from em_exploration_ros.tools.sim_cli import PLANNER_NAMES, PLANNER_TYPE

PARAMS = ExplorationParams()
SIZE_M = 100.0
NUM_ROBOTS = 3


def random_walks(num_poses: int, rng: np.random.Generator) -> list[np.ndarray]:
    """One keyframe trajectory (K, 3) per robot: 2 m steps, random heading drift, turning
    away from the 4 m border band; robots start 3 m apart in the middle-left region."""
    trajectories = []
    for robot in range(NUM_ROBOTS):
        pose = np.array([12.0, SIZE_M / 2 + 3.0 * (robot - 1), 0.0])
        poses = [pose.copy()]
        for _ in range(num_poses // NUM_ROBOTS - 1):
            pose = pose.copy()
            pose[2] += rng.normal(0.0, 0.25)
            step = 2.0 * np.array([np.cos(pose[2]), np.sin(pose[2])])
            if not np.all((pose[:2] + step > 4.0) & (pose[:2] + step < SIZE_M - 4.0)):
                pose[2] += 0.75 * np.pi
                step = 2.0 * np.array([np.cos(pose[2]), np.sin(pose[2])])
            pose[:2] = np.clip(pose[:2] + step, 4.0, SIZE_M - 4.0)
            poses.append(pose)
        trajectories.append(np.array(poses))
    return trajectories


def keyframe_covariance() -> np.ndarray:
    """Odometry covariance of one 2 m keyframe interval (10 straight steps)."""
    accumulator = OdometryAccumulator()
    step = PARAMS.motion.speed_mps * PARAMS.motion.time_step_s
    for _ in range(PARAMS.slam.keyframe_interval_steps):
        accumulator.add(OdometryReading(np.array([step, 0.0, 0.0]),
                                        odometry_covariance_per_step(step, False, PARAMS.sensors)))
    return accumulator.take()[1]


def candidates_and_targets(slam: TeamSlam, landmarks: np.ndarray, rng: np.random.Generator
                           ) -> tuple[list[Frontier], dict[int, np.ndarray]]:
    """About 20 candidates for robot 0 and a current target for each teammate."""
    here = slam.pose(0, slam.latest_index(0))[:2]
    inside = lambda xy: np.clip(xy, 5.0, SIZE_M - 5.0)  # noqa: E731
    angles = np.linspace(0.0, 2.0 * np.pi, 14, endpoint=False)
    candidates = [Frontier(inside(here + rng.uniform(6.0, 12.0) * np.array([np.cos(a), np.sin(a)])),
                           FrontierType.EXPLORATION) for a in angles]
    nearest = np.argsort(np.linalg.norm(landmarks - here, axis=1))[:4]
    candidates += [Frontier(inside(landmarks[j] + [4.0, 4.0]), FrontierType.REVISITING)
                   for j in nearest]
    targets = {}
    for robot in range(1, NUM_ROBOTS):
        position = slam.pose(robot, slam.latest_index(robot))[:2]
        targets[robot] = inside(position + rng.uniform(-20.0, 20.0, 2))
        waiting = abs(np.linalg.norm(targets[robot] - here)
                      - np.linalg.norm(targets[robot] - position))
        candidates.append(Frontier(targets[robot], FrontierType.RENDEZVOUS, robot, waiting))
    return candidates, targets


def build_context(num_poses: int, seed: int) -> PlanningContext:
    """The synthetic team and robot 0's decision context."""
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(8.0, SIZE_M - 8.0, (20, 2))
    slam = exact_team_slam(random_walks(num_poses, rng), dict(enumerate(landmarks)),
                           keyframe_covariance(), PARAMS)
    grid = OccupancyGrid(SIZE_M, SIZE_M, PARAMS.map, PARAMS.sensors.sonar_max_range_m)
    known = np.array(list(slam.landmark_estimates().values())).reshape(-1, 2)
    grid.rebuild(np.vstack([slam.trajectory(r)[1] for r in range(NUM_ROBOTS)]), known)
    candidates, targets = candidates_and_targets(slam, landmarks, rng)
    teammates = {r: (slam.pose(r, slam.latest_index(r))[:2], targets[r]) for r in targets}
    return PlanningContext(0, slam, grid, candidates, slam.pose(0, slam.latest_index(0)),
                           teammates, {r: [t] for r, t in targets.items()},
                           grid.explored_ratio())


def timed_decisions(ctx: PlanningContext, params: ExplorationParams, name: str,
                    repeats: int) -> tuple[float, float]:
    """Median wall and CPU time [s] of ``repeats`` decisions (after one warm-up)."""
    planner = make_planner(params, name)
    planner.choose(ctx)
    wall, cpu = [], []
    for _ in range(repeats):
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        planner.choose(ctx)
        wall.append(time.perf_counter() - wall_start)
        cpu.append(time.process_time() - cpu_start)
    return float(np.median(wall)), float(np.median(cpu))


def oracle_agreement(ctx: PlanningContext, count: int) -> tuple[float, float]:
    """Largest block-relative difference fast vs oracle over the first ``count`` candidates
    (alpha's history and all waypoints) and the oracle's median time per candidate [s]."""
    snapshot = TeamSnapshot.from_slam(ctx.slam, 0)
    noise = VirtualNoise(ctx.slam.noise, PARAMS.sensors, PARAMS.motion)
    builder = ScenarioBuilder(snapshot, {r: t for r, (_, t) in ctx.teammates.items()}, noise,
                              PARAMS.planner.virtual_waypoint_spacing_m,
                              PARAMS.sensors.sonar_max_range_m)
    scenarios = builder.build_all(np.array([c.position for c in ctx.candidates[-count:]]))
    boundary = sorted(set().union(*(s.boundary_keys for s in scenarios)))
    fast_path = DecisionFactorization(snapshot, builder.predicted, boundary, True, True)
    worst, oracle_times = 0.0, []
    for scenario, fast in zip(scenarios, fast_path.propagate_all(scenarios)):
        start = time.perf_counter()
        oracle = propagate_oracle(snapshot, scenario)
        oracle_times.append(time.perf_counter() - start)
        for mine, theirs in ((fast.history_covariances, oracle.history_covariances),
                             (fast.predicted_covariances, oracle.predicted_covariances),
                             (fast.next_covariances, oracle.next_covariances)):
            if len(theirs):
                worst = max(worst, float(np.max(np.linalg.norm(mine - theirs, axis=(1, 2))
                                                / np.linalg.norm(theirs, axis=(1, 2)))))
    return worst, float(np.median(oracle_times))


def approximation_error(ctx: PlanningContext, tolerance: float) -> tuple[float, bool, float]:
    """EM_3's approximate U_M (``history_change_tolerance``) against the exact one: the
    largest relative difference over the candidates, whether the chosen target differs,
    and the approximate decision's median CPU time [s]."""
    exact_planner = make_planner(PARAMS, "EM_3")
    approximate_params = PARAMS.replace(planner={"history_change_tolerance": tolerance})
    approximate_planner = make_planner(approximate_params, "EM_3")
    exact = exact_planner.choose(ctx)
    approximate = approximate_planner.choose(ctx)
    exact_u_m = np.array([u.u_m for u in exact.utilities])
    approximate_u_m = np.array([u.u_m for u in approximate.utilities])
    error = float(np.max(np.abs(approximate_u_m - exact_u_m)
                         / np.maximum(np.abs(exact_u_m), 1e-12)))
    _, cpu = timed_decisions(ctx, approximate_params, "EM_3", 3)
    return error, approximate.target is not exact.target, cpu


def fit_line(x: Sequence[float], y: Sequence[float]) -> tuple[float, float]:
    """Least-squares ``y = a + b x``: returns ``(a, b)``."""
    slope, intercept = np.polyfit(np.asarray(x, dtype=float), np.asarray(y, dtype=float), 1)
    return float(intercept), float(slope)


#: One-line help of the ``latency`` subcommand of em-bench.
LATENCY_HELP = "planner decision time against the number of poses in the graph"


def add_latency_arguments(latency: argparse.ArgumentParser) -> None:
    """Description, options and handler of ``latency``, the em-bench subcommand's parser."""
    latency.description = __doc__.split("\n\n")[1].replace("\n", " ")
    latency.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000, 4000],
                         help="numbers of poses in the team graph")
    latency.add_argument("--planners", nargs="+", type=PLANNER_TYPE, choices=PLANNER_NAMES,
                         default=["EM_2", "EM_3", "BSP", "CE", "NEAREST"],
                         help="planners to time")
    latency.add_argument("--repeats", type=int, default=7, help="timed decisions per size")
    latency.add_argument("--seed", type=int, default=3, help="seed of the synthetic team")
    latency.add_argument("--approximate", type=float, default=1e-3, metavar="TOLERANCE",
                         help="planner.history_change_tolerance whose U_M error against "
                         "the exact U_M is reported (EM_3; default 1e-3)")
    latency.set_defaults(handler=command_latency)


def check_latency_arguments(args: argparse.Namespace) -> None:
    """ValueError naming the first argument of ``latency`` that cannot give a measurement,
    before anything is built."""
    if min(args.sizes) < NUM_ROBOTS:
        raise ValueError(f"--sizes: every graph needs at least one pose per robot "
                         f"({NUM_ROBOTS}), got {min(args.sizes)}")
    for option, values in (("--sizes", args.sizes), ("--planners", args.planners)):
        repeated = sorted({value for value in values if values.count(value) > 1})
        if repeated:
            raise ValueError(f"{option}: {', '.join(map(str, repeated))} given more than "
                             f"once (one table row per size, one column per planner)")
    if args.repeats < 1:
        raise ValueError(f"--repeats must be at least 1, got {args.repeats}")
    if args.seed < 0:
        raise ValueError(f"--seed must not be negative, got {args.seed}")
    PARAMS.replace(planner={"history_change_tolerance": args.approximate})


def command_latency(args: argparse.Namespace) -> int:
    """Print the latency table (one row per graph size), then the per-candidate fits."""
    check_latency_arguments(args)
    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, "
          f"load average {os.getloadavg()[0]:.2f}")
    print("median wall / CPU time of one decision [ms], and CPU time per candidate [ms]")
    header = "".join(f"{name:>18}{'/cand':>7}" for name in args.planners)
    print(f"{'poses':>6} {'vars':>5} {'cands':>5}{header} {'oracle/cand [ms]':>17} "
          f"{'fast vs oracle':>14} {'approx. U_M err':>15} {'argmin moved':>12} "
          f"{'approx. CPU [ms]':>16}", flush=True)
    variables, per_candidate = [], {name: ([], []) for name in args.planners}
    for size in args.sizes:
        ctx = build_context(size, args.seed)
        count = len(ctx.candidates)
        columns = ""
        for name in args.planners:
            wall, cpu = timed_decisions(ctx, PARAMS, name, args.repeats)
            per_candidate[name][0].append(wall / count)
            per_candidate[name][1].append(cpu / count)
            columns += f"{wall * 1e3:>9.1f} / {cpu * 1e3:>6.1f}{cpu / count * 1e3:>7.2f}"
        error, oracle_s = oracle_agreement(ctx, 3)
        approximate_error, moved, approximate_cpu = approximation_error(ctx, args.approximate)
        poses = ctx.slam.num_variables() - len(ctx.slam.landmark_estimates())
        variables.append(ctx.slam.num_variables())
        print(f"{poses:>6} {variables[-1]:>5} {count:>5}{columns} {oracle_s * 1e3:>17.1f} "
              f"{error:>14.1e} {approximate_error:>15.1e} {'yes' if moved else 'no':>12} "
              f"{approximate_cpu * 1e3:>16.1f}", flush=True)
    if len(variables) > 1:
        print("time per candidate = a + b * graph variables (least squares over the sizes); "
              "authors: a = 0.057 s, b = 2.7e-4 s")
        for name in args.planners:
            wall_fit, cpu_fit = (fit_line(variables, times) for times in per_candidate[name])
            print(f"{name:>6}: wall a = {wall_fit[0]:.2e} s, b = {wall_fit[1]:.2e} s; "
                  f"CPU a = {cpu_fit[0]:.2e} s, b = {cpu_fit[1]:.2e} s "
                  f"({cpu_fit[1] / 2.7e-4:.4f} of the authors' slope)")
    return 0
