"""Messages a recorder subscribed to but never received, from publication sequence numbers.

A DDS writer numbers what it publishes from 1 and a received message carries that number
(rclpy's message info, ``publication_sequence_number``). Between two messages of one
writer, a jump of the number is what the recorder lost: a best-effort stream dropped them,
or the subscription's keep-last queue overflowed while the recorder fell behind. Messages
carry no writer identity in rclpy, so the numbers are trusted only while the topic has one
matched writer (``writers``, called at every graph poll) and no second numbering has shown
up since (a number at or below the last one: another writer, or a restarted one); that
counts no false losses on topics with several writers and misses none on the usual one.
What a writer published before the subscription matched it, or after its last message
that arrived, is not counted.
"""
from __future__ import annotations


class MessageLosses:
    """Losses of one recorded topic (``lost``; ``reported`` of them already reported)."""

    def __init__(self, writers: int) -> None:
        self.lost = 0
        self.reported = 0
        self._last: int | None = None
        self._trusted = writers == 1

    def writers(self, count: int) -> None:
        """The number of writers the subscription is matched with now."""
        if count == 1 and not self._trusted:
            self._last = None  # the last number may be a departed writer's
        self._trusted = count == 1

    def received(self, publication_sequence: int | None) -> None:
        """A message arrived with this publication sequence number (None: not given)."""
        if publication_sequence is None:
            return
        last = self._last
        if last is not None:
            if publication_sequence <= last:
                self._trusted = False  # another writer's numbering, until a poll says
            elif self._trusted:
                self.lost += publication_sequence - last - 1
        self._last = publication_sequence

    def unreported(self) -> int:
        """Losses counted since the last call (marked as reported)."""
        new, self.reported = self.lost - self.reported, self.lost
        return new
