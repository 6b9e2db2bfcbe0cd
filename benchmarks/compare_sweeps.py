"""Two em-bench output directories of the same trials (e.g. an older main against the
current one), compared seed by seed, and the rendezvous of one directory.

``compare`` prints one Markdown row per setting and planner found in both directories:
runs that reached the explored ratio, ended stalled or at the final step (max_steps),
targets given up per run (mean, range; the second directory), the longest run of one
robot choosing the same target again and again ("repeats"), and the means of simulated
time [s], distance [m] and the localization and landmark RMSEs [m], each "first / second";
then the paired differences (second - first) with 95 % t intervals.

``rendezvous`` prints, for each trial of one planner, the rendezvous chosen and their
outcomes and, over all trials, the meetings' effect on the requesters' pose-covariance
trace (the summary's ``meetings``).

Usage::

    python benchmarks/compare_sweeps.py compare OLD_OUT NEW_OUT
    python benchmarks/compare_sweeps.py rendezvous NEW_OUT --planner EM_3
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from em_exploration_ros.core.evaluation.trial_stats import paired_difference

#: A meeting counts as reducing the requester's uncertainty when its trace falls by more
#: than this fraction at the inter-robot factor.
_MEETING_DROP = 0.1
#: A factor this soon after the request [s sim time] means the partner was already in sight.
_IN_SIGHT_S = 2.0


def load_trials(out_dir: Path) -> dict[tuple[str, str, int], dict]:
    """The summaries of the finished trials: (setting, planner, seed) -> summary."""
    trials = {}
    for path in sorted(out_dir.glob("trials/*/*/seed_*.json")):
        summary = json.loads(path.read_text()).get("summary")
        if summary:
            seed = int(path.stem.removeprefix("seed_"))
            trials[(path.parent.parent.name, path.parent.name, seed)] = summary
    return trials


def longest_repeat(summary: dict) -> int:
    """The longest run of one robot choosing the same target position in a row."""
    longest = 0
    for robot in summary["robots"]:
        targets = [(t["x"], t["y"]) for t in robot["targets"]]
        run = 0
        for index, target in enumerate(targets):
            run = run + 1 if index and target == targets[index - 1] else 1
            longest = max(longest, run)
    return longest


def _count(summaries: list[dict], starts: tuple[str, ...]) -> int:
    return sum(any(s["stop_reason"].startswith(p) for p in starts) for s in summaries)


def _paired(first: list[dict], second: list[dict], key: str) -> str:
    """Mean of second - first, seed by seed, with its 95 % interval half-width."""
    difference = paired_difference(dict(enumerate(s[key] for s in second)),
                                   dict(enumerate(s[key] for s in first)))
    return f"{key} {difference.mean:+.2f} ± {difference.ci95:.2f}"


def compare(first_dir: Path, second_dir: Path) -> None:
    """Print the comparison table and the paired differences (see module docstring)."""
    first, second = load_trials(first_dir), load_trials(second_dir)
    groups = sorted({key[:2] for key in first} & {key[:2] for key in second})
    print("| setting | planner | seeds | reached | stalled | max_steps | given up per run "
          "| repeats | sim time [s] | distance [m] | loc. RMSE [m] | landmark RMSE [m] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    differences = []
    for setting, planner in groups:
        seeds = sorted(k[2] for k in second if k[:2] == (setting, planner)
                       and (setting, planner, k[2]) in first)
        a = [first[(setting, planner, s)] for s in seeds]
        b = [second[(setting, planner, s)] for s in seeds]
        given_up = [sum(len(r.get("given_up") or []) for r in s["robots"]) for s in b]

        def both(value) -> str:
            return f"{value(a)} / {value(b)}"

        def mean(key: str, digits: int) -> str:
            return both(lambda runs: f"{statistics.fmean(s[key] for s in runs):.{digits}f}")

        print(f"| {setting} | {planner} | {seeds[0]}-{seeds[-1]} ({len(seeds)}) "
              f"| {both(lambda runs: _count(runs, ('explored ratio',)))} "
              f"| {both(lambda runs: _count(runs, ('stalled',)))} "
              f"| {both(lambda runs: _count(runs, ('final step',)))} "
              f"| {statistics.fmean(given_up):.1f} ({min(given_up)}-{max(given_up)}) "
              f"| {both(lambda runs: max(longest_repeat(s) for s in runs))} "
              f"| {mean('sim_time_s', 0)} | {mean('distance_m', 0)} "
              f"| {mean('loc_rmse_m', 2)} | {mean('landmark_rmse_m', 2)} |")
        differences.append(f"{setting} {planner}: " + "; ".join(
            _paired(a, b, key) for key in ("distance_m", "sim_time_s", "loc_rmse_m",
                                           "landmark_rmse_m")))
    print("\npaired differences (second - first, mean ± 95 % t interval):")
    print("\n".join(differences))


def rendezvous(out_dir: Path, planner: str) -> None:
    """Print the rendezvous of each trial of ``planner`` and the meetings' effect."""
    meetings = []
    for (setting, name, seed), summary in sorted(load_trials(out_dir).items()):
        if name != planner:
            continue
        entries = summary.get("meetings") or []
        meetings += [(m, m["requested_at_s"] / summary["sim_time_s"]) for m in entries]
        print(f"{setting} seed {seed}: chosen {summary['decisions_by_type']['rendezvous']}, "
              f"{summary['rendezvous']}, meetings {len(entries)}, first: " + (
                  "{requester_id}->{partner_id} {trace_before_m2:.1f} -> {trace_after_m2:.1f}"
                  .format(**entries[0]) if entries else "none"))
    fell = [(m, f) for m, f in meetings
            if m["trace_after_m2"] < (1.0 - _MEETING_DROP) * m["trace_before_m2"]]
    rest = [(m, f) for m, f in meetings if (m, f) not in fell]
    for label, group in ((f"trace fell > {_MEETING_DROP:.0%}", fell), ("the others", rest)):
        if not group:
            continue
        entries = [m for m, _ in group]
        before = statistics.median(m["trace_before_m2"] for m in entries)
        after = statistics.median(m["trace_after_m2"] for m in entries)
        ratio = statistics.median(m["trace_after_m2"] / m["trace_before_m2"] for m in entries)
        waited = statistics.median(m["stamp_s"] - m["requested_at_s"] for m in entries)
        print(f"{label}: {len(group)} meetings, median trace {before:.1f} -> {after:.1f}, "
              f"median ratio {ratio:.2f}, median {waited:.1f} s from request to factor, "
              f"{sum(f < 1 / 3 for _, f in group)} requested in the first third of the run")
    quick = sum(m["stamp_s"] - m["requested_at_s"] <= _IN_SIGHT_S for m, _ in meetings)
    print(f"factor within {_IN_SIGHT_S:g} s of the request: {quick} of {len(meetings)}")
    largest = sorted(fell, key=lambda mf: -mf[0]["trace_before_m2"])[:3]
    print("largest: " + ", ".join(f"{m['trace_before_m2']:.1f} -> {m['trace_after_m2']:.1f}"
                                  for m, _ in largest))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    pair = commands.add_parser("compare", help="two output directories, seed by seed")
    pair.add_argument("first", type=Path)
    pair.add_argument("second", type=Path)
    meets = commands.add_parser("rendezvous", help="rendezvous and meetings of one planner")
    meets.add_argument("out", type=Path)
    meets.add_argument("--planner", default="EM_3")
    args = parser.parse_args()
    if args.command == "compare":
        compare(args.first, args.second)
    else:
        rendezvous(args.out, args.planner)


if __name__ == "__main__":
    main()
