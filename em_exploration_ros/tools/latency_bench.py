"""em-bench latency: planner decision time against the size of the team graph.

Builds a synthetic 3-robot team graph (random walks at 2 m per keyframe in a 100 m x 100 m
map with 20 landmarks, exact measurements with the sensor-derived noise models, teammate
readings whenever two robots are within sonar range at the same keyframe) with 250, 500,
1000 and 2000 poses, gives robot 0 about 20 candidates (exploration frontiers around it,
revisiting frontiers near landmarks, rendezvous at the teammates' targets) and prints the
median wall and CPU time of one decision of each planner, and the agreement of the fast
EM step with the re-solve oracle (largest relative difference of a 3x3 covariance block)
together with the oracle's time per candidate. BLAS is single-threaded by default (see
the package docstring).
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from em_exploration_ros.core.planning.frontiers import Frontier, FrontierType
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.planners import PlanningContext, make_planner
from em_exploration_ros.core.sim.sensors import OdometryReading, odometry_covariance_per_step
from em_exploration_ros.core.slam.team_slam import OdometryAccumulator, TeamSlam
from em_exploration_ros.core.slam.synthetic_team import exact_team_slam
from em_exploration_ros.core.planning.em_oracle import propagate_oracle
from em_exploration_ros.core.planning.em_scenario import ScenarioBuilder, TeamSnapshot, VirtualNoise
from em_exploration_ros.core.planning.em_step import DecisionFactorization
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


def timed_decisions(ctx: PlanningContext, name: str, repeats: int) -> tuple[float, float]:
    """Median wall and CPU time [s] of ``repeats`` decisions (after one warm-up)."""
    planner = make_planner(PARAMS, name)
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
    scenarios = [builder.build(c.position) for c in ctx.candidates[-count:]]
    boundary = sorted(set().union(*(s.boundary_keys for s in scenarios)))
    fast_path = DecisionFactorization(snapshot, builder.predicted, boundary, True, True)
    worst, oracle_times = 0.0, []
    for scenario in scenarios:
        fast = fast_path.propagate(scenario)
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


#: One-line help of the ``latency`` subcommand of em-bench.
LATENCY_HELP = "planner decision time against the number of poses in the graph"


def add_latency_arguments(latency: argparse.ArgumentParser) -> None:
    """Description, options and handler of ``latency``, the em-bench subcommand's parser."""
    latency.description = __doc__.split("\n\n")[1].replace("\n", " ")
    latency.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000],
                         help="numbers of poses in the team graph")
    latency.add_argument("--planners", nargs="+", type=PLANNER_TYPE, choices=PLANNER_NAMES,
                         default=["EM_2", "EM_3", "BSP", "CE", "NEAREST"],
                         help="planners to time")
    latency.add_argument("--repeats", type=int, default=7, help="timed decisions per size")
    latency.add_argument("--seed", type=int, default=3, help="seed of the synthetic team")
    latency.set_defaults(handler=command_latency)


def command_latency(args: argparse.Namespace) -> int:
    """Print the latency table (one row per graph size)."""
    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, "
          f"load average {os.getloadavg()[0]:.2f}")
    print("median wall / CPU time of one decision [ms]")
    header = "".join(f"{name:>16}" for name in args.planners)
    print(f"{'poses':>6} {'cands':>5}{header} {'oracle/cand [ms]':>17} {'fast vs oracle':>14}")
    for size in args.sizes:
        ctx = build_context(size, args.seed)
        timings = "".join(
            "{:>9.1f} /{:>5.1f}".format(*(1e3 * t for t in timed_decisions(ctx, name,
                                                                           args.repeats)))
            for name in args.planners)
        error, oracle_s = oracle_agreement(ctx, 3)
        poses = ctx.slam.num_variables() - len(ctx.slam.landmark_estimates())
        print(f"{poses:>6} {len(ctx.candidates):>5}{timings} {oracle_s * 1e3:>17.1f} "
              f"{error:>14.1e}", flush=True)
    return 0
