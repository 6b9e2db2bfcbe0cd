"""What field sensing costs: CPU time per simulated second and per decision, and team
traffic, with the robots associating their own detections against ideal sensing.

For each seed, em-sim's team (``TeamRunner``, in this process) runs the mission twice,
one after the other: with the paper's ideal sonar and with a field sonar (identities off,
detection probability and clutter rate as given). Each run's CPU time of this process
(``time.process_time``, so other load on the machine counts less than in wall time) is
divided by the simulated time [s] and by the number of decisions. Printed per seed and as
the ratio field / ideal of the sums over the seeds. The team traffic (CDR bytes of every
TeamUpdate each robot publishes per simulated second, as ``team_traffic.py`` measures it)
is measured in a separate run of the first seed per setting, so its serialization does
not count in the CPU time.

Usage: ``python benchmarks/sensing_cost.py [--seeds 0 1 2] [--detection-prob 0.9]
[--clutter-rate 1] [em-sim run options]``.
"""
from __future__ import annotations

import argparse
import time
from typing import Sequence

from team_traffic import TrafficMeter, metered_run

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.nodes.conversions import team_update_to_msg
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args


def timed_run(params: ExplorationParams) -> tuple[float, float, int]:
    """CPU time [s], simulated time [s] and decisions of one mission."""
    runner = TeamRunner(params)
    start = time.process_time()
    runner.run()
    return time.process_time() - start, runner.simulation.stamp_s, runner.num_decisions


def traffic_bytes_per_s(params: ExplorationParams) -> float:
    """The team's TeamUpdate CDR bytes per simulated second over one mission."""
    runner = TeamRunner(params)
    meter = TrafficMeter()
    wire = TeamWireFormat(params)
    metered_run(runner, meter, lambda update: team_update_to_msg(update, wire))
    return sum(meter.total.values()) / runner.simulation.stamp_s


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args(argv)
    if args.landmark_ids is None:
        args.landmark_ids = "off"
    if args.detection_prob is None:
        args.detection_prob = 0.9
    if args.clutter_rate is None:
        args.clutter_rate = 1.0
    settings = {"ideal": lambda seed: params_from_args(args, seed).replace(
                    sensors={"landmark_ids": True, "detection_probability": 1.0,
                             "clutter_rate": 0.0}),
                "field": lambda seed: params_from_args(args, seed)}
    field = settings["field"](args.seeds[0]).sensors
    print(f"field sonar: identities {'on' if field.landmark_ids else 'off'}, detection "
          f"probability {field.detection_probability:g}, clutter {field.clutter_rate:g} / scan")
    print("seed  setting  CPU [s]  sim [s]  decisions  CPU ms / sim s  CPU ms / decision")
    totals = {name: [0.0, 0.0, 0] for name in settings}
    for seed in args.seeds:
        for name, make in settings.items():
            cpu_s, sim_s, decisions = timed_run(make(seed))
            for index, value in enumerate((cpu_s, sim_s, decisions)):
                totals[name][index] += value
            print(f"{seed:4d}  {name:7s}  {cpu_s:7.1f}  {sim_s:7.1f}  {decisions:9d}  "
                  f"{1e3 * cpu_s / sim_s:14.1f}  {1e3 * cpu_s / max(decisions, 1):17.1f}")
    ideal, field_total = totals["ideal"], totals["field"]
    per_sim = (field_total[0] / field_total[1]) / (ideal[0] / ideal[1])
    per_decision = (field_total[0] / field_total[2]) / (ideal[0] / ideal[2])
    print(f"field / ideal over seeds {args.seeds}: CPU per simulated second x{per_sim:.2f}, "
          f"per decision x{per_decision:.2f}")
    for name, make in settings.items():
        print(f"team traffic, {name}, seed {args.seeds[0]}: "
              f"{traffic_bytes_per_s(make(args.seeds[0])):.0f} CDR bytes per simulated second")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
