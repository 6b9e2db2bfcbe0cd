"""When a robot re-sends its team updates: rate-limited per requester, coalesced, bounded.

Teammates (and the evaluator) ask a robot for ranges of its update stream they missed
(``TeamUpdateRequest``). Answering every request at once lets one flooding sender make
the robot publish its whole history many times a second, which fills the middleware's
send queues. ``ResendScheduler`` keeps **one pending range per requester** (a new request
widens it), sends to each requester at most once every ``min_interval_s`` and at most
``max_records`` records at a time (the rest stays pending for the next turn).
"""
from __future__ import annotations

from dataclasses import dataclass

#: Most records re-sent to one requester in one turn.
MAX_RESEND_RECORDS = 200


@dataclass(frozen=True)
class ResendRange:
    """Records ``first_sequence..last_sequence`` (inclusive) to publish again for a requester."""

    requester_id: int
    first_sequence: int
    last_sequence: int


class ResendScheduler:
    """Pending re-sends of one robot's stream (see module docstring). Times are monotonic
    wall seconds given by the caller."""

    def __init__(self, min_interval_s: float, max_records: int = MAX_RESEND_RECORDS) -> None:
        self.min_interval_s = min_interval_s
        self.max_records = max_records
        self._pending: dict[int, tuple[int, int]] = {}
        self._last_sent_s: dict[int, float] = {}

    def request(self, requester_id: int, first_sequence: int, last_sequence: int,
                latest_sequence: int) -> None:
        """File a request for ``first..last`` (``last`` 0: up to the latest) of a stream whose
        latest record is ``latest_sequence``; merged with the requester's pending range.
        Ranges past the latest record are cut to it; an empty range is ignored."""
        last = latest_sequence if last_sequence == 0 else min(last_sequence, latest_sequence)
        first = max(first_sequence, 1)
        if first > last:
            return
        pending = self._pending.get(requester_id)
        if pending is not None:
            first, last = min(first, pending[0]), max(last, pending[1])
        self._pending[requester_id] = (first, last)

    def due(self, now_s: float) -> list[ResendRange]:
        """Ranges to publish now, in requester order: for every requester with a pending
        range whose last re-send is at least ``min_interval_s`` old, up to ``max_records``
        records (the rest stays pending)."""
        ranges = []
        for requester, (first, last) in sorted(self._pending.items()):
            sent = self._last_sent_s.get(requester)
            if sent is not None and now_s - sent < self.min_interval_s:
                continue
            end = min(last, first + self.max_records - 1)
            ranges.append(ResendRange(requester, first, end))
            self._last_sent_s[requester] = now_s
            if end < last:
                self._pending[requester] = (end + 1, last)
            else:
                del self._pending[requester]
        return ranges

    @property
    def pending(self) -> int:
        """Number of requesters with a pending range."""
        return len(self._pending)
