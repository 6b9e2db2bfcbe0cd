"""Outcome of every rendezvous of a run, from the robots' ``Rendezvous`` events.

Whoever watches a run (em-sim's team runner, the em-evaluator node reading the robots'
``TeamUpdate`` streams) hands the events it saw to ``count_rendezvous``. A rendezvous is
identified by its requester and ``rendezvous_id``; it was

- *requested* when its REQUEST was seen,
- *met* when both the requester and the partner sent ARRIVED,
- *timed out* when it ended without meeting: a RELEASE from either robot, or its wait
  limit (REQUEST stamp + timeout) passed by the end of the run,
- *open* otherwise (the run ended while it was under way).
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from em_exploration_ros.core.agent.team_data import RendezvousEvent, RendezvousState


@dataclass
class RendezvousCounts:
    """How many rendezvous were requested, met, timed out (ended without meeting) and
    still open at the end of the run."""

    requested: int = 0
    met: int = 0
    timed_out: int = 0
    open: int = 0


def count_rendezvous(events: Iterable[RendezvousEvent], end_s: float) -> RendezvousCounts:
    """Counts of the rendezvous requested before ``end_s`` [s, simulation time], judged
    with the events stamped before ``end_s`` (any order, duplicates allowed)."""
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
    counts = RendezvousCounts(requested=len(requests))
    for key, request in requests.items():
        if {request.requester_id, request.partner_id} <= arrived.get(key, set()):
            counts.met += 1
        elif key in released or request.stamp_s + request.timeout_s <= end_s:
            counts.timed_out += 1
        else:
            counts.open += 1
    return counts
