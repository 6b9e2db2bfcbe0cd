"""Parameters: defaults, checks, and the ROS 2 parameter YAML files."""
import subprocess
import sys
from pathlib import Path

import pytest

from em_exploration_ros.core.output_paths import output_path_problem
from em_exploration_ros.core.params import (ExplorationParams, ParameterDeprecationWarning,
                                            upgrade_deprecated)
from em_exploration_ros.core.params_yaml import ParamsFileError, dump_params, load_params
from em_exploration_ros.tools import sim_cli

SHIPPED_CONFIG = Path(__file__).resolve().parents[1] / "config" / "exploration.yaml"


def test_shipped_config_holds_every_default():
    text = SHIPPED_CONFIG.read_text()
    params = ExplorationParams()
    assert load_params(SHIPPED_CONFIG) == params
    for name in params.flat():
        assert f" {name.split('.')[1]}:" in text, f"{name} missing from {SHIPPED_CONFIG.name}"


def test_dump_and_load_round_trip(tmp_path):
    params = ExplorationParams().replace(world={"num_robots": 5, "width_m": 150.0},
                                         planner={"name": "BSP"}, slam={"use_fixed_sigmas": True})
    path = tmp_path / "p.yaml"
    path.write_text(dump_params(params))
    assert load_params(path) == params


def test_dotted_names_and_node_sections_merge(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    planner.name: CE\n    world: {num_robots: 4}\n"
                    "/robot_1/em_robot:\n  ros__parameters:\n    world.num_robots: 2\n")
    params = load_params(path)
    assert params.planner.name == "CE" and params.world.num_robots == 2


def test_node_settings_are_not_exploration_parameters(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    planner.name: BSP\n"
                    "/em_world:\n  ros__parameters:\n    robot_timeout_s: 3.0\n"
                    "    world.num_robots: 4\n")
    params = load_params(path)
    assert params.planner.name == "BSP" and params.world.num_robots == 4
    path.write_text("/**:\n  ros__parameters:\n    robot_timeout_s: 3.0\n")
    with pytest.raises(ParamsFileError, match="has no group"):
        load_params(path)


@pytest.mark.parametrize("text, message", [
    ("/**:\n  ros__parameters:\n    bogus.x: 1\n", "unknown parameter group"),
    ("/**:\n  ros__parameters:\n    world.nope: 1\n", "unknown parameter"),
    ("/**:\n  ros__parameters:\n    world.num_robots: 0\n", "outside"),
    ("/**:\n  ros__parameters:\n    planner.name: XY\n", "must be one of"),
    ("/**:\n  ros__parameters:\n    slam.prior_sigmas: [1, 2]\n", "list of 3"),
    ("/**:\n  ros__parameters:\n    sensors.noise_enabled: 1\n", "true or false"),
    ("/**:\n  ros__parameters:\n    world.widht_m: 60\n", "did you mean 'width_m'"),
    ("/**:\n  ros__parameters:\n    wrold.width_m: 60\n", "did you mean 'world'"),
    ("/em_world:\n  ros__parameters:\n    robot_timout_s: 3.0\n",
     "did you mean 'robot_timeout_s'"),
    ("/em_world:\n  ros__parameters:\n    robot_timeout_s: abc\n", "must be a number"),
    ("/em_world:\n  ros__parameters:\n    clock_mode: fast\n", "must be one of"),
    ("/robot_0/em_robt:\n  ros__parameters:\n    barrier_timeout_s: 3.0\n",
     "did you mean 'em_robot'"),
    ("/robot_0/em_robot:\n  ros__parameters:\n    request_period_s: -1.0\n", "outside"),
    ("world: [unclosed\n", "not valid YAML"),
    ("- a\n- b\n", "mapping"),
])
def test_bad_files_give_clear_errors(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ParamsFileError, match=message):
        load_params(path)


def test_a_binary_file_is_a_clear_error(tmp_path):
    path = tmp_path / "binary.yaml"
    path.write_bytes(b"/**:\n\xe9\x00\xff")
    with pytest.raises(ParamsFileError, match=r"binary.yaml is not UTF-8 text \(byte 5: "):
        load_params(path)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ParamsFileError, match="cannot read"):
        load_params(tmp_path / "absent.yaml")


def test_integers_are_accepted_where_numbers_are_expected(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    world: {width_m: 60, height_m: 60}\n"
                    "/em_world:\n  ros__parameters:\n    robot_timeout_s: 3\n"
                    "/**/em_evaluator:\n  ros__parameters:\n    silence_timeout_s: 30\n")
    params = load_params(path)
    assert params.world.width_m == 60.0 and isinstance(params.world.width_m, float)


def test_output_paths_are_checked_before_a_run(tmp_path):
    assert output_path_problem(tmp_path / "s.json") is None
    assert "does not exist" in output_path_problem(tmp_path / "absent" / "s.json")
    assert "is a directory" in output_path_problem(tmp_path)
    problem = output_path_problem("/proc/s.json", "--summary")  # not writable, even for root
    assert problem.startswith("--summary") and "cannot write in /proc" in problem


def test_deprecated_planner_name_still_selects_its_planner(tmp_path):
    path = tmp_path / "old.yaml"
    path.write_text("/**:\n  ros__parameters:\n    planner.name: NF\n")
    with pytest.warns(ParameterDeprecationWarning, match="'NF' is deprecated; using 'NEAREST'"):
        assert load_params(path).planner.name == "NEAREST"
    with pytest.warns(ParameterDeprecationWarning, match="'NF' is deprecated"):
        assert ExplorationParams().replace(planner={"name": "NF"}).planner.name == "NEAREST"
    with pytest.warns(ParameterDeprecationWarning, match="'NF' is deprecated"):
        args = sim_cli.build_parser().parse_args(["--planner", "NF"])
    assert args.planner == "NEAREST"


def test_deprecation_warning_is_shown_once_per_process(tmp_path):
    path = tmp_path / "old.yaml"
    path.write_text("/**:\n  ros__parameters:\n    planner.name: NF\n")
    script = ("import sys; from em_exploration_ros.core.params_yaml import load_params\n"
              "for _ in range(3): assert load_params(sys.argv[1]).planner.name == 'NEAREST'\n")
    done = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True,
                          text=True, timeout=60, check=True)
    assert done.stderr.count("'NF' is deprecated") == 1


def test_upgrade_deprecated_reports_each_replacement():
    groups, messages = upgrade_deprecated({"planner": {"name": "NF"}, "world": {"width_m": 5.0}})
    assert groups == {"planner": {"name": "NEAREST"}, "world": {"width_m": 5.0}}
    assert len(messages) == 1 and "NEAREST" in messages[0]
    assert upgrade_deprecated({"planner": {"name": "CE"}}) == ({"planner": {"name": "CE"}}, [])


def test_removed_parameter_loads_with_a_warning(tmp_path):
    path = tmp_path / "old.yaml"
    path.write_text("/**:\n  ros__parameters:\n    planner:\n"
                    "      allocation_waypoint_spacing_m: 10.0\n      name: CE\n")
    with pytest.warns(ParameterDeprecationWarning,
                      match="allocation_waypoint_spacing_m is deprecated and ignored"):
        params = load_params(path)
    assert params == ExplorationParams().replace(planner={"name": "CE"})
    assert "planner.allocation_waypoint_spacing_m" not in params.flat()
