"""Rendezvous outcomes and decision counts: what the summary, em-bench and run_team.sh
report about frontier types, planner failures and rendezvous."""
import numpy as np

from em_exploration_ros.core.evaluation.evaluator import TeamMetrics
from em_exploration_ros.core.evaluation.rendezvous_stats import (RendezvousCounts, activity_totals,
                                                                 count_rendezvous,
                                                                 rendezvous_outcomes)
from em_exploration_ros.core.evaluation.run_monitor import DecisionEntry, RunMonitor
from em_exploration_ros.core.evaluation.summary import MeetingEntry, activity_line
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import FrontierType, RendezvousEvent, RendezvousState

REQUEST, ARRIVED, RELEASE = (RendezvousState.REQUEST, RendezvousState.ARRIVED,
                             RendezvousState.RELEASE)


def event(requester, partner, sender, state, stamp_s, rendezvous_id=0, timeout_s=50.0):
    return RendezvousEvent(rendezvous_id, requester, partner, sender, state, stamp_s,
                           np.array([10.0 * requester, 5.0]), timeout_s)


EVENTS = [
    # robot 0 meets robot 1 (both arrived), robot 2 gives up on robot 1 (RELEASE),
    # robot 1 asks robot 2 and waits past the limit, robot 0 asks again and is under way.
    event(0, 1, 0, REQUEST, 1.0), event(0, 1, 1, ARRIVED, 5.0), event(0, 1, 0, ARRIVED, 9.0),
    event(2, 1, 2, REQUEST, 2.0, rendezvous_id=3), event(2, 1, 2, RELEASE, 4.0, rendezvous_id=3),
    event(1, 2, 1, REQUEST, 3.0, rendezvous_id=1, timeout_s=10.0),
    event(1, 2, 1, ARRIVED, 6.0, rendezvous_id=1),
    event(0, 2, 0, REQUEST, 20.0, rendezvous_id=4),
]


def test_outcomes_met_timed_out_and_open():
    outcomes = rendezvous_outcomes(reversed(EVENTS), end_s=30.0)
    assert [(o.requester_id, o.partner_id, o.outcome) for o in outcomes] == [
        (0, 1, "met"), (2, 1, "timed_out"), (1, 2, "timed_out"), (0, 2, "open")]
    assert (outcomes[0].x, outcomes[0].y) == (0.0, 5.0)
    assert count_rendezvous(EVENTS, 30.0) == RendezvousCounts(4, 1, 2, 1)
    # Judged at t = 8 s: robot 0 had not arrived yet, robot 1's wait had not run out.
    assert count_rendezvous(EVENTS, 8.0) == RendezvousCounts(3, 0, 1, 2)


def test_summary_counts_types_failures_and_rendezvous_before_the_stop():
    params = ExplorationParams().replace(run={"until_explored": 0.5})
    monitor = RunMonitor(params)
    monitor.observe(150, TeamMetrics(30.0, 10.0, 0.6, 0.1, 0.1, (5.0, 5.0)))
    decisions = [[DecisionEntry(1.0, (1.0, 1.0), FrontierType.EXPLORATION, 0.1),
                  DecisionEntry(2.0, (2.0, 1.0), FrontierType.RENDEZVOUS, 0.1),
                  DecisionEntry(3.0, (3.0, 1.0), FrontierType.EXPLORATION, 0.1, True),
                  DecisionEntry(40.0, (3.0, 1.0), FrontierType.REVISITING, 0.1)],
                 [DecisionEntry(4.0, (1.0, 2.0), FrontierType.REVISITING, 0.1)]]
    meetings = [MeetingEntry(0, 1, 0, 1.0, 4.5, 0.9, 0.2), MeetingEntry(0, 2, 4, 20.0, 35.0, 1, 1)]
    summary = monitor.summary(decisions, 1.0, rendezvous_events=EVENTS, meetings=meetings).to_dict()
    assert summary["decisions_by_type"] == {"exploration": 2, "revisiting": 1, "rendezvous": 1}
    assert summary["planner_failures"] == 1
    assert summary["rendezvous"] == {"requested": 4, "met": 1, "timed_out": 2, "open": 1}
    assert [m["trace_after_m2"] for m in summary["meetings"]] == [0.2]
    assert activity_line(summary) == (
        "decisions: 2 exploration, 1 revisiting, 1 rendezvous; planner failed 1; "
        "rendezvous: 4 requested, 1 met, 2 timed out, 1 open")
    summary["robots"][1]["slam_recoveries"] = 2
    unknown = {"robots": [{"id": 0, "slam_recoveries": None}]}  # run_team.sh cannot know
    totals = activity_totals([summary, summary, {"explored_ratio": 0.9}, unknown])
    assert totals["slam_recoveries"] == 4
    assert totals["decisions_by_type"]["exploration"] == 4
    assert totals["rendezvous"]["met"] == 2 and totals["planner_failures"] == 2
    assert totals["meetings"] == 2
