"""What restarting one robot's process costs the team's estimate.

For each seed, em-sim's engine runs the mission three times: clean, with one restart of
robot ``--robot`` (before step 800, about half of the default mission) and with three
(before steps 400, 800 and 1200). A restarted robot rejoins from its journals as a
restarted em-robot with a ``state_dir`` does (``TeamRunner(restarts)``, em-sim
``--restart ROBOT:STEP``). Printed per seed and as means over the seeds:

* the mission's end: robot and landmark RMSE [m] (em-sim's summary) and decisions;
* right after the first restart (its step processed, before any decision could diverge):
  the largest difference [m] between the restarted robot's estimate of its trajectory and
  the clean run's at the same step.

Usage: ``python benchmarks/restart_cost.py`` (seeds 0-9, the default mission; about 30
em-sim runs) or ``--seeds 0 1 --jobs 2``. Results: docs/robustness.md.
"""
from __future__ import annotations

import argparse
import math
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args

#: Restart steps of each configuration (before these steps).
CONFIGURATIONS = {"clean": (), "1 restart": (800,), "3 restarts": (400, 800, 1200)}
#: Steps after which the clean run's trajectory estimate is kept for comparison.
COMPARED_STEPS = (401, 801)


def run_mission(args: argparse.Namespace, seed: int, name: str) -> dict:
    """One mission of ``seed`` with the restarts of configuration ``name``: its end RMSE
    and, at each compared step, the restarted robot's trajectory estimate."""
    params = params_from_args(args, seed)
    runner = TeamRunner(params, [(args.robot, step) for step in CONFIGURATIONS[name]])
    trajectories = {}
    monitor = runner.monitor
    runner.observe(0.0)
    while not monitor.stopped and runner.simulation.step < monitor.final_step:
        runner.step_once()
        runner.observe(0.0)
        if runner.simulation.step in COMPARED_STEPS:
            trajectories[runner.simulation.step] = runner.agents[args.robot].slam.trajectory(
                args.robot)[1].copy()
    summary = runner.summary(0.0)
    return {"seed": seed, "name": name, "loc": summary.loc_rmse_m,
            "landmark": summary.landmark_rmse_m, "decisions": summary.decisions,
            "steps": runner.simulation.step, "trajectories": trajectories}


def after_resume(clean: dict, restarted: dict, name: str) -> float:
    """Largest difference [m, rad] of the restarted robot's trajectory estimate from the
    clean run's right after the configuration's first restart; NaN if none was made."""
    if not CONFIGURATIONS[name]:
        return math.nan
    step = CONFIGURATIONS[name][0] + 1
    if step not in clean["trajectories"] or step not in restarted["trajectories"]:
        return math.nan
    a, b = clean["trajectories"][step], restarted["trajectories"][step]
    if a.shape != b.shape:
        return math.inf
    return float(np.abs(a - b).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--robot", type=int, default=1, help="the robot restarted")
    parser.add_argument("--jobs", type=int, default=1, help="missions run at once")
    args = parser.parse_args()
    tasks = [(seed, name) for seed in args.seeds for name in CONFIGURATIONS]
    results = []
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = [pool.submit(run_mission, args, seed, name) for seed, name in tasks]
        for future in as_completed(futures):
            r = future.result()
            results.append(r)
            print(f"done: seed {r['seed']} {r['name']}: robot RMSE {r['loc']:.3f} m, landmark "
                  f"RMSE {r['landmark']:.3f} m, {r['decisions']} decisions", flush=True)
    by = {(r["seed"], r["name"]): r for r in results}
    print(f"robot {args.robot} restarted before steps: "
          + "; ".join(f"{name}: {list(steps)}" for name, steps in CONFIGURATIONS.items()))
    print(f"{'seed':>4} {'run':<11} {'steps':>5} {'dec':>4} {'robot RMSE':>10} "
          f"{'lm RMSE':>8} {'after resume':>12}")
    for seed in args.seeds:
        for name in CONFIGURATIONS:
            r = by[seed, name]
            print(f"{seed:>4} {name:<11} {r['steps']:>5} {r['decisions']:>4} {r['loc']:>10.3f} "
                  f"{r['landmark']:>8.3f} {after_resume(by[seed, 'clean'], r, name):>12.2e}")
    print("\nmeans over the seeds (ratio to clean)")
    clean_loc = np.mean([by[s, "clean"]["loc"] for s in args.seeds])
    clean_lm = np.mean([by[s, "clean"]["landmark"] for s in args.seeds])
    for name in CONFIGURATIONS:
        loc = np.mean([by[s, name]["loc"] for s in args.seeds])
        lm = np.mean([by[s, name]["landmark"] for s in args.seeds])
        gap = [after_resume(by[s, "clean"], by[s, name], name) for s in args.seeds]
        print(f"{name:<11} robot RMSE {loc:.3f} m ({loc / clean_loc:.2f})  landmark RMSE "
              f"{lm:.3f} m ({lm / clean_lm:.2f})  after resume: max {np.max(gap):.2e} m")


if __name__ == "__main__":
    main()
