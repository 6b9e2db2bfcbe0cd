"""Parameters: defaults, checks, and the ROS 2 parameter YAML files."""
import subprocess
import sys
from pathlib import Path

import pytest

from em_exploration_ros.core.output_paths import output_path_problem
from em_exploration_ros.core.params import (ExplorationParams, ParameterDeprecationWarning,
                                            upgrade_deprecated)
from em_exploration_ros.core import params_yaml
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
    with pytest.raises(ParamsFileError, match=message) as refused:
        load_params(path)
    assert "\n" not in str(refused.value)  # one line, PyYAML's several parts too


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


def _alias_bomb(levels: int, as_lists: bool) -> str:
    """A YAML document of ``levels`` + 1 lines whose last anchor expands to 10**levels
    values through aliases of aliases (a mapping bomb, or a list bomb inside a value)."""
    if as_lists:
        lines = ["world:", "  start_region_x_fraction:", "    - &l0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
        lines += [f"    - &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]"
                  for i in range(1, levels + 1)]
    else:
        lines = ["a0: &a0 {" + ", ".join(f"k{k}: {k}" for k in range(10)) + "}"]
        lines += [f"a{i}: &a{i} {{" + ", ".join(f"k{k}: *a{i - 1}" for k in range(10)) + "}"
                  for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("as_lists", [False, True], ids=["mapping", "list"])
def test_alias_bombs_are_refused(tmp_path, as_lists):
    path = tmp_path / "bomb.yaml"
    path.write_text(_alias_bomb(6, as_lists))  # 1e6 values; the bomb found had 1e9
    with pytest.raises(ParamsFileError, match="expands to more than 100000 values"):
        load_params(path)


def test_anchors_and_aliases_within_the_bound_are_used(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    world: &world {num_robots: 4}\n"
                    "/robot_0/em_robot:\n  ros__parameters:\n    world: *world\n")
    assert load_params(path).world.num_robots == 4


def test_values_in_error_messages_are_bounded():
    bomb: list = [1.0] * 10
    for _ in range(5):
        bomb = [bomb] * 10  # 1e6 numbers, 6 levels deep
    for world in ({"start_region_x_fraction": bomb}, {"num_robots": 10**400},
                  {"width_m": "x" * 10**6}):
        with pytest.raises(ValueError) as raised:
            ExplorationParams().replace(world=world)
        assert len(str(raised.value)) < 300, str(raised.value)[:400]


@pytest.mark.parametrize("text, message", [
    ("world:\n  width_m: " + "9" * 400 + "\n", r"width_m must be finite, got <integer of"),
    ("world:\n  start_region_x_fraction: [" + "9" * 400 + ", 1]\n",
     r"start_region_x_fraction must be finite"),
    ("/em_world: {ros__parameters: {robot_timeout_s: " + "9" * 400 + "}}\n",
     r"section '/em_world': .*robot_timeout_s must be finite"),
])
def test_integers_beyond_the_float_range_are_clear_errors(tmp_path, text, message):
    path = tmp_path / "big.yaml"
    path.write_text(text)
    with pytest.raises(ParamsFileError, match=message):
        load_params(path)


@pytest.mark.parametrize("text, message", [
    ("world:\n  start_region_x_fraction: [0.1, 1]\n",
     r"^.*: world.start_region_x_fraction: the list \[0.1, 1\] mixes floats and integers; "
     r"a ROS 2 parameter file needs one type per list"),
    ("/**:\n  ros__parameters:\n    links: {range_m: 30.0}\n    x: [true, 1]\n",
     r"/\*\*.ros__parameters.x: the list \[True, 1\] mixes booleans and integers"),
])
def test_a_list_of_mixed_types_is_refused_as_the_ros_nodes_would(tmp_path, text, message):
    """rcl's parameter-file parser refuses a list mixing integers and floats (the nodes of
    run_team.sh all died on [0.1, 1]); em-sim and run_team.sh's check refuse it first."""
    path = tmp_path / "mixed.yaml"
    path.write_text(text)
    with pytest.raises(ParamsFileError, match=message):
        load_params(path)
    path.write_text(text.replace("[0.1, 1]", "[0.1, 1.0]").replace("x: [true, 1]\n", ""))
    load_params(path)


@pytest.mark.parametrize("text, message", [
    ("{" * 500 + "}" * 500 + "\n", "is nested too deeply to parse"),  # the parser's recursion
    ("a: " + "{b: " * 100 + "1" + "}" * 100 + "\n", "nests deeper than 32 levels")])
def test_deep_nesting_is_a_clear_error(tmp_path, text, message):
    path = tmp_path / "deep.yaml"
    path.write_text(text)
    with pytest.raises(ParamsFileError, match=message):
        load_params(path)


def test_a_parameter_file_must_be_a_regular_file_of_bounded_size(tmp_path):
    # /dev/null: without the check it read as an empty file (and /dev/zero without end)
    with pytest.raises(ParamsFileError, match="/dev/null is not a regular file"):
        load_params("/dev/null")
    assert params_yaml.MAX_FILE_BYTES == 1 << 20
    path = tmp_path / "large.yaml"  # a 2 KiB limit: a 1 MiB file parses slowly
    path.write_text("#" * 2048 + "\n")
    with pytest.raises(ParamsFileError, match="large.yaml is larger than 2 KiB"):
        load_params(path, max_bytes=2048)
    path.write_text("#" * 2047 + "\n")
    assert load_params(path, max_bytes=2048) == ExplorationParams()


@pytest.mark.parametrize("free_below, occupied_above, valid", [
    (0.9, 0.1, False), (0.6, 0.7, False), (0.3, 0.4, False), (0.5, 0.5, True), (0.2, 0.9, True)])
def test_explored_thresholds_must_leave_unknown_cells_unexplored(free_below, occupied_above,
                                                                 valid):
    thresholds = {"explored_free_below": free_below, "explored_occupied_above": occupied_above}
    if valid:
        assert ExplorationParams().replace(map=thresholds).map.explored_free_below == free_below
    else:
        with pytest.raises(ValueError, match="explored_free_below .* must be at most 0.5"):
            ExplorationParams().replace(map=thresholds)


@pytest.mark.parametrize("slam, valid", [
    ({"track_confirm_hits": 6}, False), ({"loop_closure_confirm_hits": 6}, False),
    ({"track_window_keyframes": 2}, False), ({"track_window_keyframes": 3}, True),
    ({"track_confirm_hits": 5, "loop_closure_confirm_hits": 5}, True)])
def test_a_track_must_be_confirmable_within_its_window(slam, valid):
    """A track is seen at most once per keyframe: a confirmation asking for more sightings
    than the window's keyframes is refused when the parameters are made, not when a robot
    first builds its tracks."""
    if valid:
        assert ExplorationParams().replace(slam=slam).slam.track_window_keyframes >= 3
    else:
        with pytest.raises(ValueError, match="must be at most track_window_keyframes"):
            ExplorationParams().replace(slam=slam)


@pytest.mark.parametrize("width_m, height_m, cell_size_m, valid", [
    (40.0, 40.0, 50.0, False), (40.0, 40.0, 10.5, False), (100.0, 30.0, 8.0, False),
    (40.0, 40.0, 10.0, True), (10.0, 10.0, 2.0, True)])
def test_the_cell_size_must_give_a_few_cells_per_side(width_m, height_m, cell_size_m, valid):
    overrides = {"world": {"width_m": width_m, "height_m": height_m},
                 "map": {"cell_size_m": cell_size_m}}
    if valid:
        assert ExplorationParams().replace(**overrides).map.cell_size_m == cell_size_m
    else:
        with pytest.raises(ValueError, match="fewer than 4 cells along the world's"):
            ExplorationParams().replace(**overrides)
