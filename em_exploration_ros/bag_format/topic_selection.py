"""Which topics a recording or a replay takes: exact names, an include regex, an exclude regex."""
from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True)
class TopicSelection:
    """Topic filter with rosbag2's semantics.

    With neither ``topics`` nor ``include`` every topic is selected; otherwise a topic is
    selected if it is listed or matches ``include``. A topic matching ``exclude`` is never
    selected. Regular expressions match anywhere in the name (``re.search``).
    """

    topics: frozenset[str] = frozenset()
    include: re.Pattern[str] | None = None
    exclude: re.Pattern[str] | None = None

    @classmethod
    def from_strings(cls, topics: list[str] | None = None, include: str | None = None,
                     exclude: str | None = None) -> "TopicSelection":
        """Build from command-line strings; raises ``re.error`` for a bad expression."""
        return cls(frozenset(topics or ()), re.compile(include) if include else None,
                   re.compile(exclude) if exclude else None)

    def matches(self, topic: str) -> bool:
        """True if ``topic`` is selected."""
        if self.exclude is not None and self.exclude.search(topic):
            return False
        if not self.topics and self.include is None:
            return True
        return topic in self.topics or (self.include is not None
                                        and self.include.search(topic) is not None)
