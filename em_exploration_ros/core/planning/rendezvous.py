"""Rendezvous bookkeeping between robots: who waits for whom, and when a meeting ends.

A robot that chooses a rendezvous candidate (``frontiers.rendezvous_frontiers``) requests a
meeting at its partner's current target; ``RendezvousBook`` follows the ``Rendezvous``
message events until both robots arrived, the deadline passed or either was released.
The deadline is set by the requester (``meeting_timeout_s``: it scales with the
requester's travel to the meeting point) and travels with the REQUEST.
Meeting points are in the team ``map`` frame [m]; times are simulation time [s].
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from em_exploration_ros.core.geometry import read_only_point


@dataclass(frozen=True, eq=False)
class Meeting:
    """A rendezvous: ``requester_id`` drives to ``meeting_point`` (2,) [m, map frame], the
    current target of ``partner_id``, which waits there until both arrived or
    ``deadline_s`` (simulation time) passes."""

    rendezvous_id: int
    requester_id: int
    partner_id: int
    meeting_point: np.ndarray
    requested_at_s: float
    deadline_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "meeting_point", read_only_point(self.meeting_point))


@dataclass
class _OpenMeeting:
    """A meeting and the robots that have arrived so far."""

    meeting: Meeting
    arrived: set[int] = field(default_factory=set)

    def involves(self, robot_id: int) -> bool:
        """True when the robot is the requester or the partner."""
        return robot_id in (self.meeting.requester_id, self.meeting.partner_id)


def meeting_timeout_s(travel_m: float, speed_mps: float, factor: float,
                      margin_s: float) -> float:
    """How long a partner waits for the requester [s]: ``factor`` times the requester's
    travel time to the meeting point (``travel_m`` [m] at ``speed_mps`` [m/s]) plus
    ``margin_s`` [s]."""
    return factor * max(float(travel_m), 0.0) / speed_mps + margin_s


class RendezvousBook:
    """ROS-free bookkeeping of rendezvous between robots (simulation time in seconds).

    Mirrors the ``Rendezvous`` message events: ``request`` (REQUEST), ``arrived``
    (ARRIVED), ``release`` / ``release_meeting`` (RELEASE; ``release`` also when a robot
    finished or is lost), plus the timeout (``expire``). A requester has at most one open
    meeting: a new request replaces the previous one. A meeting closes when both robots
    have arrived, at its deadline (``requested_at_s + timeout_s`` of its request), or when
    it or either robot is released.
    """

    def __init__(self) -> None:
        self._open: dict[int, _OpenMeeting] = {}

    def request(self, requester_id: int, partner_id: int, meeting_point: np.ndarray,
                time_s: float, timeout_s: float, rendezvous_id: int = 0) -> Meeting:
        """Record that ``requester_id`` wants to meet ``partner_id`` at ``meeting_point``
        from ``time_s`` on, for at most ``timeout_s`` [s]."""
        if requester_id == partner_id:
            raise ValueError(f"robot {requester_id} cannot rendezvous with itself")
        meeting = Meeting(rendezvous_id, requester_id, partner_id, meeting_point,
                          float(time_s), float(time_s) + float(timeout_s))
        self._open[requester_id] = _OpenMeeting(meeting)
        return meeting

    def meeting_of(self, requester_id: int) -> Meeting | None:
        """The open meeting requested by ``requester_id``, or None."""
        entry = self._open.get(requester_id)
        return None if entry is None else entry.meeting

    def open_meetings(self) -> list[Meeting]:
        """Open meetings, in ascending requester id."""
        return [self._open[key].meeting for key in sorted(self._open)]

    def arrived(self, robot_id: int, time_s: float,
                requester_id: int | None = None) -> list[Meeting]:
        """Mark ``robot_id`` arrived at its open meetings (only the one of ``requester_id``
        when given) at ``time_s``; returns the meetings completed by this arrival (closed)."""
        self.expire(time_s)
        for key, entry in self._open.items():
            if entry.involves(robot_id) and requester_id in (None, key):
                entry.arrived.add(robot_id)
        return self._close(lambda entry: len(entry.arrived) == 2)

    def expire(self, time_s: float) -> list[Meeting]:
        """Close and return the meetings whose deadline is at or before ``time_s``."""
        return self._close(lambda entry: entry.meeting.deadline_s <= time_s)

    def release(self, robot_id: int) -> list[Meeting]:
        """Close and return every meeting the robot takes part in (finished or lost)."""
        return self._close(lambda entry: entry.involves(robot_id))

    def release_meeting(self, requester_id: int, rendezvous_id: int) -> list[Meeting]:
        """Close and return the meeting ``rendezvous_id`` of ``requester_id`` if it is open
        (a RELEASE of one meeting; an older or unknown id closes nothing)."""
        return self._close(lambda entry: (entry.meeting.requester_id == requester_id
                                          and entry.meeting.rendezvous_id == rendezvous_id))

    def is_waiting(self, robot_id: int) -> np.ndarray | None:
        """Meeting point (2,) [m] where the robot must go and wait, or None.

        A partner waits from the request on; a requester waits once it has arrived. With
        several meetings, the earliest request wins.
        """
        waiting = [entry.meeting for entry in self._open.values()
                   if entry.meeting.partner_id == robot_id
                   or (entry.meeting.requester_id == robot_id and robot_id in entry.arrived)]
        if not waiting:
            return None
        return min(waiting, key=lambda m: (m.requested_at_s, m.requester_id)).meeting_point

    def _close(self, should_close: Callable[[_OpenMeeting], bool]) -> list[Meeting]:
        """Remove and return (ascending requester id) the open meetings matching the rule."""
        closing = sorted(key for key, entry in self._open.items() if should_close(entry))
        return [self._open.pop(key).meeting for key in closing]
