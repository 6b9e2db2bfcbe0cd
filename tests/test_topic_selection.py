"""Topic expressions of em-record, em-replay and em-foxglove: matched with RE2 in time linear in
the topic name, and an expression RE2 refuses is refused by each tool's argument parsing."""
from __future__ import annotations

import subprocess
import sys
from typing import Callable

import pytest
from ros_process import REPO_ROOT

from em_exploration_ros.bag_format.topic_selection import (
    TopicPatternError, TopicSelection, compile_topic_pattern)
from em_exploration_ros.tools import foxglove_bridge, record, replay

#: Catastrophic backtracking: ``re`` tries every split of the a's, 2^40 ways (about 30 hours
#: here, 1.6 s already with 24 a's), in one C call that no signal interrupts.
HOSTILE_PATTERN = r"^/(a+)+$"
HOSTILE_TOPIC = "/" + "a" * 40 + "!"
#: Far above what RE2 takes (well under a millisecond), far below what ``re`` takes.
HOSTILE_TIMEOUT_S = 20.0
#: Run in a child process, which the timeout kills if the match never returns.
HOSTILE_MATCH = """
import sys
from em_exploration_ros.bag_format.topic_selection import TopicSelection
pattern, topic = sys.argv[1:]
print(TopicSelection.from_strings(include=pattern).matches(topic),
      TopicSelection.from_strings(exclude=pattern).matches(topic))
"""
REFUSED_REASON = ("(RE2 syntax: backreferences and lookaround are not supported, because "
                  "matching must stay linear in the length of the topic name)")
#: Each tool's argument parser and the arguments it needs besides the expression.
PARSERS: dict[str, tuple[Callable[[list[str]], object], list[str]]] = {
    "em-record": (record.parse_options, []),
    "em-replay": (replay.parse_options, ["x.mcap"]),
    "em-foxglove": (foxglove_bridge.parse_options, []),
}


def test_hostile_expression_matches_in_linear_time() -> None:
    try:
        result = subprocess.run([sys.executable, "-c", HOSTILE_MATCH, HOSTILE_PATTERN,
                                 HOSTILE_TOPIC], cwd=REPO_ROOT, capture_output=True, text=True,
                                timeout=HOSTILE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"matching {HOSTILE_PATTERN!r} against {HOSTILE_TOPIC!r} took over "
                    f"{HOSTILE_TIMEOUT_S} s (a backtracking matcher)")
    assert result.returncode == 0, result.stderr
    # Not included; not excluded, so selected by a selection of only an exclude.
    assert result.stdout.split() == ["False", "True"]


def test_refused_expressions_name_the_reason() -> None:
    for pattern, reason in [(r"(a)\1", r"invalid escape sequence: \1"),
                            (r"^/(?=robot)", "invalid perl operator: (?="),
                            (r"(?<!debug)/x", "invalid perl operator: (?<!")]:
        with pytest.raises(TopicPatternError) as refused:
            TopicSelection.from_strings(include=pattern)
        assert str(refused.value) == (f"invalid regular expression {pattern!r}: {reason} "
                                      f"{REFUSED_REASON}")


@pytest.mark.parametrize("prog", sorted(PARSERS))
@pytest.mark.parametrize("option, pattern, reason", [
    ("--regex", r"^/robot_(\d+)/.*\1$", r"invalid escape sequence: \1"),
    ("--exclude", r"^/(?!robot_)", "invalid perl operator: (?!")])
def test_each_tool_refuses_what_re2_refuses_in_one_line(
        prog: str, option: str, pattern: str, reason: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    parse, needed = PARSERS[prog]
    with pytest.raises(SystemExit) as stopped:
        parse([*needed, option, pattern])
    assert stopped.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    # The one line of the error and where to read on (no log line of RE2's).
    assert lines == [f"{prog}: error: argument {option}: invalid regular expression "
                     f"{pattern!r}: {reason} {REFUSED_REASON}", f"Try '{prog} --help'."]


@pytest.mark.parametrize("prog", sorted(PARSERS))
def test_each_tool_selects_with_re2(prog: str) -> None:
    parse, needed = PARSERS[prog]
    selection = parse([*needed, "--regex", r"^/robot_\d+/", "--exclude", "debug"]).selection
    assert type(selection.include) is type(selection.exclude) is type(compile_topic_pattern("x"))
    assert selection.matches("/robot_12/map") and not selection.matches("/robot_1/debug")
    assert not selection.matches("/world/markers")


def test_foxglove_default_selection_compiles_with_re2() -> None:
    selection = foxglove_bridge.parse_options([]).selection
    assert selection.matches("/robot_3/virtual_map") and selection.matches("/tf")
    assert not selection.matches("/robot_3/virtual_map/extra")


def test_an_empty_expression_is_no_expression() -> None:
    # As rosbag2 reads an empty --regex or --exclude: not given (not "matches everything").
    assert compile_topic_pattern("") is None
    selection = TopicSelection.from_strings(["/a"], "", "")
    assert selection.matches("/a") and not selection.matches("/b")
    options = record.parse_options(["--topics", "/a", "--regex", "", "--exclude", ""])
    assert options.selection == selection
