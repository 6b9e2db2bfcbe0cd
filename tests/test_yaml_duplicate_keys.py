"""Issue 40, point 7: a duplicate key in any YAML file the project reads is refused, naming
the key and its line (``yaml.safe_load`` kept the last value without a word)."""
import subprocess
import sys

import pytest

from em_exploration_ros.bag_format.qos_yaml import QosFormatError, qos_profiles_from_yaml
from em_exploration_ros.bag_format.rosbag2_metadata import (MetadataFormatError,
                                                            parse_bag_metadata)
from em_exploration_ros.core.params_yaml import ParamsFileError, load_params
from em_exploration_ros.core.untrusted_yaml import load_yaml


class _Refused(ValueError):
    """The caller's error type, as load_yaml's callers pass theirs."""


@pytest.mark.parametrize("text, message", [
    ("world: 1\nrobot_count: 3\nrobot_count: 4\n",
     "f.yaml: duplicate key 'robot_count' at line 3 (first at line 2)"),
    ("a:\n  b:\n    - {c: 1}\n    - x: 1\n      y: 2\n      x: 3\n",
     "f.yaml: duplicate key 'x' at line 6 (first at line 4)"),
    ("{a: 1, a: 2}\n", "f.yaml: duplicate key 'a' at line 1 (first at line 1)"),
    ("1: a\n0x1: b\n", "f.yaml: duplicate key 1 at line 2 (first at line 1)"),
    ("base: &base {a: 1}\nm: {<<: *base, b: 2, b: 3}\n", "duplicate key 'b' at line 2"),
])
def test_load_yaml_refuses_a_duplicate_key_at_any_depth(text, message):
    with pytest.raises(_Refused) as refused:
        load_yaml(text, "f.yaml", _Refused)
    assert str(refused.value) == message or message in str(refused.value)
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("text, value", [
    ("a: 1\nb: {a: 2}\n", {"a": 1, "b": {"a": 2}}),  # one name in two mappings
    ("- {a: 1}\n- {a: 2}\n", [{"a": 1}, {"a": 2}]),
    # A key given explicitly overrides one a merge key brings in (YAML's merge rule),
    # also when the merged mapping was itself merged into another before its own turn.
    ("base: &base {a: 1, b: 1}\nm: {<<: *base, a: 2}\n",
     {"base": {"a": 1, "b": 1}, "m": {"a": 2, "b": 1}}),
    ("base: &base {a: 1}\nx: {mid: &mid {<<: *base, a: 2}}\ntop: {<<: *mid, c: 1}\n",
     {"base": {"a": 1}, "x": {"mid": {"a": 2}}, "top": {"a": 2, "c": 1}}),
    ("a: &k x\n*k: 1\n", {"a": "x", "x": 1}),
])
def test_load_yaml_keeps_what_is_not_a_duplicate(text, value):
    assert load_yaml(text, "f.yaml", _Refused) == value


def test_other_yaml_errors_are_unchanged():
    with pytest.raises(_Refused, match=r"(?s)f.yaml is not valid YAML: .*found unhashable key"):
        load_yaml("? [1]\n: 2\n", "f.yaml", _Refused)
    with pytest.raises(_Refused, match="f.yaml is nested too deeply to parse"):
        load_yaml("[" * 600 + "]" * 600, "f.yaml", _Refused)


def test_the_bag_readers_refuse_a_duplicate_key():
    with pytest.raises(QosFormatError, match="duplicate key 'depth' at line 3"):
        qos_profiles_from_yaml("- history: 1\n  depth: 10\n  depth: 1\n")
    with pytest.raises(MetadataFormatError, match="duplicate key 'version' at line 2"):
        parse_bag_metadata("version: 9\nversion: 4\n")


_SECTION = "/**:\n  ros__parameters:\n"


@pytest.mark.parametrize("body, key, line", [
    ("    world.num_robots: 3\n    planner.name: CE\n    world.num_robots: 5\n",
     "world.num_robots", 5),
    ("    world:\n      num_robots: 3\n      width_m: 60.0\n      num_robots: 5\n",
     "num_robots", 6),  # nested
])
def test_a_parameter_file_with_a_duplicate_key_is_refused(tmp_path, body, key, line):
    path = tmp_path / "dup.yaml"
    path.write_text(_SECTION + body)
    with pytest.raises(ParamsFileError, match=f"dup.yaml: duplicate key '{key}' at line {line}"):
        load_params(path)


def test_a_duplicate_section_is_refused(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text(_SECTION + "    planner.name: CE\n" + _SECTION + "    planner.name: BSP\n")
    with pytest.raises(ParamsFileError, match="duplicate key '/\\*\\*' at line 4"):
        load_params(path)


@pytest.mark.parametrize("body, key, line", [
    ("    world.num_robots: 3\n    world.num_robots: 5\n", "world.num_robots", 4),
    ("    world:\n      num_robots: 3\n      num_robots: 5\n", "num_robots", 5),
])
def test_em_sim_refuses_a_parameter_file_with_a_duplicate_key(tmp_path, body, key, line):
    path = tmp_path / "dup.yaml"
    path.write_text(_SECTION + body)
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.sim_cli",
                             "--params", str(path), "--max-steps", "10"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stdout == ""
    errors = [text for text in result.stderr.splitlines() if "error" in text]
    assert errors == [f"em-sim: error: {path}: duplicate key '{key}' at line {line} "
                      f"(first at line {line - 1})"], result.stderr
