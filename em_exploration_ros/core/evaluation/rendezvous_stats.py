"""Outcome of every rendezvous of a run, from the robots' ``Rendezvous`` events.

Whoever watches a run (em-sim's team runner, the em-evaluator node reading the robots'
``TeamUpdate`` streams) hands the events it saw to ``count_rendezvous``. A rendezvous is
identified by its requester and ``rendezvous_id``; it was

- *requested* when its REQUEST was seen,
- *met* when both the requester and the partner sent ARRIVED,
- *timed out* when it ended without meeting: a RELEASE from either robot, or its wait
  limit (REQUEST stamp + timeout) passed by the end of the run,
- *open* otherwise (the run ended while it was under way).

``activity_totals`` adds up, over several run summaries (JSON data), the decisions per
frontier type, the planner failures and the rendezvous counts.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

from em_exploration_ros.core.evaluation.summary import RendezvousCounts
from em_exploration_ros.core.records.team_data import RendezvousEvent, RendezvousState


@dataclass(frozen=True)
class RendezvousOutcome:
    """One requested rendezvous: who asked whom, where (map frame [m]), when [s], and its
    outcome: ``met``, ``timed_out`` or ``open``."""

    requester_id: int
    partner_id: int
    rendezvous_id: int
    requested_at_s: float
    x: float
    y: float
    outcome: str


def rendezvous_outcomes(events: Iterable[RendezvousEvent], end_s: float
                        ) -> list[RendezvousOutcome]:
    """The rendezvous requested before ``end_s`` [s, simulation time] in request order,
    judged with the events stamped before ``end_s`` (any order, duplicates allowed)."""
    requests: dict[tuple[int, int], RendezvousEvent] = {}
    arrived: dict[tuple[int, int], set[int]] = {}
    released: set[tuple[int, int]] = set()
    for event in events:
        if event.stamp_s >= end_s:
            continue
        key = (event.requester_id, event.rendezvous_id)
        if event.state == RendezvousState.REQUEST:
            requests[key] = event
        elif event.state == RendezvousState.ARRIVED:
            arrived.setdefault(key, set()).add(event.sender_id)
        else:
            released.add(key)
    outcomes = []
    for key, request in sorted(requests.items(), key=lambda item: (item[1].stamp_s, item[0])):
        if {request.requester_id, request.partner_id} <= arrived.get(key, set()):
            outcome = "met"
        elif key in released or request.stamp_s + request.timeout_s <= end_s:
            outcome = "timed_out"
        else:
            outcome = "open"
        outcomes.append(RendezvousOutcome(request.requester_id, request.partner_id,
                                          request.rendezvous_id, request.stamp_s,
                                          float(request.meeting_point[0]),
                                          float(request.meeting_point[1]), outcome))
    return outcomes


def count_rendezvous(events: Iterable[RendezvousEvent], end_s: float) -> RendezvousCounts:
    """Counts of ``rendezvous_outcomes(events, end_s)``."""
    counts = RendezvousCounts()
    for outcome in rendezvous_outcomes(events, end_s):
        counts.requested += 1
        setattr(counts, outcome.outcome, getattr(counts, outcome.outcome) + 1)
    return counts


def activity_totals(summaries: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Sums over run summaries (``RunSummary.to_dict`` data): ``decisions_by_type``,
    ``planner_failures`` and ``rendezvous`` (same keys as in one summary), and ``meetings``
    (how many meetings recorded an inter-robot factor), ``team_updates`` (teammate updates
    sent, delivered on time / late / never, over the links) and ``slam_recoveries`` (SLAM
    updates re-solved in batch, every robot's). Summaries written before these fields
    existed, and robots whose count is not known (null), count as zero."""
    by_type: dict[str, int] = {}
    team_updates = {"sent": 0, "on_time": 0, "late": 0, "never": 0}
    rendezvous = asdict(RendezvousCounts())
    failures = meetings = slam_recoveries = 0
    for summary in summaries:
        for kind, count in (summary.get("decisions_by_type") or {}).items():
            by_type[kind] = by_type.get(kind, 0) + int(count)
        for key, count in (summary.get("rendezvous") or {}).items():
            if key in rendezvous:
                rendezvous[key] += int(count)
        failures += int(summary.get("planner_failures") or 0)
        meetings += len(summary.get("meetings") or ())
        slam_recoveries += sum(int(robot.get("slam_recoveries") or 0)
                               for robot in summary.get("robots") or ())
        for key, count in (summary.get("team_updates") or {}).items():
            if key in team_updates:
                team_updates[key] += int(count)
    return {"decisions_by_type": by_type, "planner_failures": failures,
            "rendezvous": rendezvous, "meetings": meetings, "team_updates": team_updates,
            "slam_recoveries": slam_recoveries}
