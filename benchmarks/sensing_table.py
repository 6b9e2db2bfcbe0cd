"""Field sensing against ideal sensing: em-bench trials over a grid of sonar settings, one
Markdown table, and the goal checks.

Each sonar setting (landmark identities on or off, detection probability, clutter rate per
scan) runs as one ``em-bench planners`` invocation into ``OUT/<setting>`` (resumable: a
rerun only runs the trials that are missing), with the map, planners and seeds given here.
The table has one row per setting and planner: trials done (failed), explored ratio reached,
distance [m], robot and landmark RMSE [m] (means over the finished trials), the team's
association precision and recall and the spurious landmarks per run (means; "-" with
identities on, where nothing is associated).

The goal checks compare ``--goal`` (identities off, 1 clutter per scan, detection
probability 0.9 unless given) with ideal sensing on the same seeds, per planner:

* the mean robot RMSE ratio goal / ideal (goal: at most 1.3);
* the lowest association precision of a run (goal: at least 0.99);
* the largest ratio of one run's robot RMSE to its ideal run's (goal: at most 5);
* EM more accurate than CE: the paired difference of robot RMSE (EM_3 - CE) with its 95 %
  interval.

Usage (the 100 m map over 20 seeds, EM_3 and CE, ideal and the goal setting)::

    python benchmarks/sensing_table.py --out OUT --trials 20 --jobs 2
    python benchmarks/sensing_table.py --out OUT --trials 5 --grid      # the whole grid
    python benchmarks/sensing_table.py --out OUT --trials 10 -- --map-size 200 \\
        --cell-size 4 --landmarks 3                                      # sparse 200 m

Arguments after ``--`` go to every ``em-bench planners`` call.
"""
from __future__ import annotations

import argparse
import itertools
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from em_exploration_ros.core.evaluation.trial_stats import paired_difference
from em_exploration_ros.tools import bench


@dataclass(frozen=True)
class Sonar:
    """One sonar setting: identities, detection probability, clutter rate [per scan]."""

    landmark_ids: bool
    detection_prob: float
    clutter_rate: float

    @property
    def name(self) -> str:
        """Folder name, e.g. ``ids-off_pd0.9_clutter1``."""
        ids = "on" if self.landmark_ids else "off"
        return f"ids-{ids}_pd{self.detection_prob:g}_clutter{self.clutter_rate:g}"

    @property
    def ideal(self) -> bool:
        """The paper's sonar."""
        return self.landmark_ids and self.detection_prob == 1.0 and self.clutter_rate == 0.0

    def bench_arguments(self) -> list[str]:
        """The em-bench flags of this setting."""
        return ["--landmark-ids", "on" if self.landmark_ids else "off",
                "--detection-prob", f"{self.detection_prob:g}",
                "--clutter-rate", f"{self.clutter_rate:g}"]


IDEAL = Sonar(True, 1.0, 0.0)


def grid_settings() -> list[Sonar]:
    """Identities on/off x clutter 0, 0.5 and 2 x detection probability 1.0 and 0.8."""
    return [Sonar(ids, prob, clutter) for ids, clutter, prob
            in itertools.product((True, False), (0.0, 0.5, 2.0), (1.0, 0.8))]


def run_setting(out: Path, sonar: Sonar, args: argparse.Namespace) -> Path:
    """Run (or complete) the trials of one setting with em-bench; its output folder."""
    folder = out / sonar.name
    argv = ["planners", "--planners", *args.planners, "--trials", str(args.trials),
            "--jobs", str(args.jobs), "--out", str(folder), *sonar.bench_arguments(),
            *args.bench_args]
    code = bench.main(argv)
    if code != 0:
        raise SystemExit(f"em-bench {' '.join(argv)} exited with {code}")
    return folder


def finished(folder: Path) -> dict[str, dict[int, dict[str, Any] | None]]:
    """``{planner: {seed: summary}}`` of the trials in an em-bench folder; a failed trial's
    summary is None."""
    by_planner: dict[str, dict[int, dict[str, Any] | None]] = {}
    for record in bench.load_records(folder):
        runs = by_planner.setdefault(record["planner"], {})
        runs[record["seed"]] = record["summary"] if record["status"] == "done" else None
    return by_planner


def _mean(values: Sequence[float]) -> str:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return f"{statistics.fmean(values):.3f}" if values else "-"


def row(sonar: Sonar, planner: str, runs: dict[int, dict[str, Any] | None]) -> str:
    """One Markdown row of the table (see the module docstring)."""
    done = [s for s in runs.values() if s is not None]
    association = [s["association"] for s in done if s.get("association")]
    ids = "on" if sonar.landmark_ids else "off"
    return (f"| {ids} | {sonar.detection_prob:g} | {sonar.clutter_rate:g} | {planner} | "
            f"{len(done)} ({len(runs) - len(done)}) | "
            f"{_mean([s['explored_ratio'] for s in done])} | "
            f"{_mean([s['distance_m'] for s in done]).split('.')[0]} | "
            f"{_mean([s['loc_rmse_m'] for s in done])} | "
            f"{_mean([s['landmark_rmse_m'] for s in done])} | "
            f"{_mean([a['precision'] for a in association])} | "
            f"{_mean([a['recall'] for a in association])} | "
            f"{_mean([a['spurious_landmarks'] for a in association])} |")


TABLE_HEAD = ("| ids | detection prob | clutter / scan | planner | trials done (failed) | "
              "explored | distance [m] | robot RMSE [m] | landmark RMSE [m] | precision | "
              "recall | spurious landmarks |\n" + "|---" * 12 + "|")


def goal_lines(goal: dict[str, dict[int, Any]], ideal: dict[str, dict[int, Any]]
               ) -> list[str]:
    """The goal checks (see the module docstring), one line each."""
    lines = []
    for planner in sorted(set(goal) & set(ideal)):
        seeds = sorted(seed for seed in set(goal[planner]) & set(ideal[planner])
                       if goal[planner][seed] is not None and ideal[planner][seed] is not None)
        if not seeds:
            continue
        field = [goal[planner][seed]["loc_rmse_m"] for seed in seeds]
        base = [ideal[planner][seed]["loc_rmse_m"] for seed in seeds]
        precision = [goal[planner][seed]["association"]["precision"] for seed in seeds]
        worst = max(f / b for f, b in zip(field, base))
        lines.append(
            f"{planner}, {len(seeds)} common seeds: mean robot RMSE {statistics.fmean(field):.3f}"
            f" m vs ideal {statistics.fmean(base):.3f} m, ratio "
            f"{statistics.fmean(field) / statistics.fmean(base):.2f} (goal <= 1.3); lowest "
            f"precision {min(precision):.4f} (goal >= 0.99); largest run ratio {worst:.2f} "
            f"(goal <= 5)")
    if "EM_3" in goal and "CE" in goal:
        def by_seed(runs: dict[int, Any]) -> dict[int, float]:
            return {seed: s["loc_rmse_m"] for seed, s in runs.items() if s is not None}
        difference = paired_difference(by_seed(goal["EM_3"]), by_seed(goal["CE"]))
        lines.append(f"EM_3 - CE robot RMSE under the goal setting: {difference.mean:+.3f} "
                     f"± {difference.ci95:.3f} m over {difference.n} seeds (negative: "
                     f"EM more accurate)")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--planners", nargs="+", default=["EM_3", "CE"])
    parser.add_argument("--trials", type=int, default=20, help="seeds 0..N-1 per setting")
    parser.add_argument("--jobs", type=int, default=1, help="parallel trials")
    parser.add_argument("--grid", action="store_true",
                        help="the whole grid of settings, not only ideal and the goal")
    parser.add_argument("--goal", type=float, nargs=2, default=[0.9, 1.0],
                        metavar=("PROB", "CLUTTER"),
                        help="the goal setting's detection probability and clutter rate")
    parser.add_argument("bench_args", nargs="*", help="after --: more em-bench arguments")
    args = parser.parse_args(argv)
    goal = Sonar(False, args.goal[0], args.goal[1])
    settings = list(dict.fromkeys([IDEAL, goal, *(grid_settings() if args.grid else [])]))
    results = {sonar: finished(run_setting(args.out, sonar, args)) for sonar in settings}
    print(TABLE_HEAD)
    for sonar in settings:
        for planner in args.planners:
            if planner in results[sonar]:
                print(row(sonar, planner, results[sonar][planner]))
    print()
    for line in goal_lines(results[goal], results[IDEAL]):
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
