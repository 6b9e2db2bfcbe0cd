"""Which topics a recording or a replay takes: exact names, an include regex, an exclude regex.

The expressions are matched with RE2 (module ``re2`` of the google-re2 package), in time
linear in the length of the topic name. Any node on the network can create a topic, and a
backtracking engine such as ``re`` takes time exponential in the name's length on some
expressions (``^/(a+)+$`` against ``/aaa…a!``), inside one C call that no signal interrupts.
"""
from __future__ import annotations

from dataclasses import dataclass

import re2

#: RE2's defaults, except that a refused expression is not also logged to stderr by RE2
#: (the caller reports it in one line).
_RE2_OPTIONS = re2.Options()
_RE2_OPTIONS.log_errors = False


class TopicPatternError(ValueError):
    """A topic expression that RE2 refuses; the message names the expression and the reason."""


def compile_topic_pattern(pattern: str | None) -> re2._Regexp | None:
    """Compile a topic expression with RE2, or None for None or an empty string (no expression,
    as rosbag2 reads an empty ``--regex``).

    ``re2._Regexp`` is the type ``re2.compile`` returns (re2 gives it no public name). Raises
    ``TopicPatternError`` for an expression RE2 refuses, e.g. one with a backreference or a
    lookaround (neither can be matched in linear time).
    """
    if not pattern:
        return None
    try:
        return re2.compile(pattern, _RE2_OPTIONS)
    except (re2.error, UnicodeEncodeError) as error:
        reason = error.args[0] if isinstance(error, re2.error) else "not valid UTF-8"
        if isinstance(reason, bytes):
            reason = reason.decode("utf-8", "replace")
        raise TopicPatternError(
            f"invalid regular expression {pattern!r}: {reason} (RE2 syntax: backreferences "
            "and lookaround are not supported, because matching must stay linear in the "
            "length of the topic name)") from None


@dataclass(frozen=True)
class TopicSelection:
    """Topic filter with rosbag2's semantics.

    With neither ``topics`` nor ``include`` every topic is selected; otherwise a topic is
    selected if it is listed or matches ``include``. A topic matching ``exclude`` is never
    selected. Regular expressions match anywhere in the name (``search``, as ``re.search``),
    in RE2 syntax (see ``compile_topic_pattern``).
    """

    topics: frozenset[str] = frozenset()
    include: re2._Regexp | None = None
    exclude: re2._Regexp | None = None

    @classmethod
    def from_strings(cls, topics: list[str] | None = None, include: str | None = None,
                     exclude: str | None = None) -> "TopicSelection":
        """Build from command-line strings; raises ``TopicPatternError`` for an expression
        RE2 refuses."""
        return cls(frozenset(topics or ()), compile_topic_pattern(include),
                   compile_topic_pattern(exclude))

    def matches(self, topic: str) -> bool:
        """True if ``topic`` is selected."""
        if self.exclude is not None and self.exclude.search(topic):
            return False
        if not self.topics and self.include is None:
            return True
        return topic in self.topics or (self.include is not None
                                        and self.include.search(topic) is not None)
