"""Why a rendezvous is (not) chosen: utility terms of the best rendezvous candidate against
the chosen target, decision by decision, in one seeded em-sim run.

Prints one line per decision that had a rendezvous candidate: robot, time [s], explored
ratio, the EM weights, and for the chosen target and the best rendezvous candidate (lowest
total) U_M [m^2], U_T, U_D [m] and the weighted total; then how often the rendezvous lost
on each term. Example (the paper's sparse scenario)::

    python benchmarks/rendezvous_decisions.py --seed 0 --map-size 200 --cell-size 4 \\
        --landmarks 3 --max-steps 1500
"""
from __future__ import annotations

import argparse
import sys

from em_exploration_ros.core.planning.planner_api import CandidateUtility
from em_exploration_ros.core.planning.planners import EmPlanner
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args


def _terms(utility: CandidateUtility) -> str:
    return (f"U_M {utility.u_m:8.1f}  U_T {utility.u_t:5.2f}  U_D {utility.u_d:6.1f}  "
            f"total {utility.total:8.1f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_arguments(parser)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    params = params_from_args(args, args.seed)
    runner = TeamRunner(params)
    seen = [0] * len(runner.agents)
    lost_on = {"U_M": 0, "U_T": 0, "U_D": 0}
    offered = chosen = 0
    while runner.simulation.step < params.run.max_steps and not all(
            agent.finished for agent in runner.agents):
        runner.step_once()
        for agent in runner.agents:
            if len(agent.decisions) == seen[agent.robot_id]:
                continue
            seen[agent.robot_id] = len(agent.decisions)
            decision = agent.last_decision
            meets = [u for u in decision.utilities if u.frontier.kind == FrontierType.RENDEZVOUS]
            if not meets or not isinstance(agent.planner, EmPlanner):
                continue
            offered += 1
            best = min(meets, key=lambda u: u.total)
            pick = next(u for u in decision.utilities if u.frontier is decision.target)
            chosen += pick is best
            weights = agent.planner.weights(agent.explored_ratio)
            if pick is not best:
                gaps = {"U_M": weights[0] * (best.u_m - pick.u_m),
                        "U_T": weights[1] * (best.u_t - pick.u_t),
                        "U_D": weights[2] * (best.u_d - pick.u_d)}
                lost_on[max(gaps, key=gaps.get)] += 1
            record = decision.target.kind.name.lower()
            print(f"robot {agent.robot_id} t {agent.decisions[-1].stamp_s:6.1f} s  "
                  f"r {agent.explored_ratio:.3f}  weights {weights[0]:g}/{weights[1]:.1f}/"
                  f"{weights[2]:g}\n  chosen ({record:11s}) {_terms(pick)}\n"
                  f"  rendezvous (robot {best.frontier.partner_id}) {_terms(best)}")
    print(f"decisions with a rendezvous candidate: {offered}; rendezvous chosen: {chosen}; "
          f"largest weighted gap of a lost rendezvous: {lost_on}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
