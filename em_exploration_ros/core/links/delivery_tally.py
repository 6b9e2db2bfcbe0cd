"""How many of the link relay's deliveries a robot holds (relay mode; no ROS here).

In relay mode each SonarScan says how many records and requests the world's link relay has
delivered to the robot in all (``delivered_updates``, ``delivered_requests``); the robot
processes the step only once it holds as many (``core/links/link_relay.py``). The relay
publishes each kind to a robot on its own topic, from one writer that lives as long as the
world, so a delivery's publication sequence number (counted by that writer from 1) is the
number of deliveries of its kind made to the robot up to and with it. Counting by it, a
robot also accounts for the deliveries made before its reader matched the writer (those of
a process restarted mid-run, which DDS never hands a volatile reader); without one (a
middleware that does not give it) the deliveries heard are counted, plus the scan's count
at the first step of a restarted process (``start_at``).
"""
from __future__ import annotations

#: Index of each kind of delivery in the counts.
RECORDS, REQUESTS = 0, 1


def published_so_far(heard_before: int, publication_sequence: int | None) -> int:
    """How many messages a writer has published up to the one just heard: its publication
    sequence number (counted by the writer from 1; a restarted process's writer starts
    again), or without one ``heard_before`` + 1."""
    return heard_before + 1 if publication_sequence is None else publication_sequence


class DeliveryTally:
    """Deliveries (records, requests) a robot holds, compared with a scan's counts."""

    def __init__(self) -> None:
        self._heard = [0, 0]
        self._offset = [0, 0]
        self._by_sequence = [False, False]
        self._floor = [0, 0]

    def heard(self, kind: int, publication_sequence: int | None) -> None:
        """A delivery of ``kind`` (RECORDS or REQUESTS), with its publication sequence number
        if the middleware gives one."""
        if publication_sequence is not None:
            self._by_sequence[kind] = True
        self._heard[kind] = published_so_far(self._heard[kind], publication_sequence)

    def start_at(self, delivered: tuple[int, int]) -> None:
        """The first scan of a process restarted mid-run: the deliveries it counts that were
        made before this process subscribed are not waited for."""
        self._offset = [count - heard for count, heard in zip(delivered, self._heard)]

    def held(self) -> tuple[int, int]:
        """Deliveries of each kind accounted for, as a scan counts them."""
        return tuple(max(heard + (0 if by_sequence else offset), floor)
                     for heard, offset, by_sequence, floor in
                     zip(self._heard, self._offset, self._by_sequence, self._floor))

    def holds(self, delivered: tuple[int, int]) -> bool:
        """True when every delivery a scan counts (``delivered``) is accounted for."""
        return all(held >= count for held, count in zip(self.held(), delivered))

    def write_off(self, delivered: tuple[int, int]) -> None:
        """Take the deliveries a scan counts as held: the robot gave up waiting for them, and
        does not wait for them again at every later step (by sequence numbers the next
        delivery's count includes them; otherwise they are added to the offset)."""
        for kind, (held, count) in enumerate(zip(self.held(), delivered)):
            self._offset[kind] += max(count - held, 0)
            self._floor[kind] = max(self._floor[kind], count)
