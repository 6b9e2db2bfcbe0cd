"""Exploration parameters declared on a ROS node, from a --params-file (in-process node)."""
from __future__ import annotations

import rclpy

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.nodes.ros_params import declare_exploration_params


def declared_params(tmp_path, text: str):
    """The exploration parameters a node named em_robot declares with ``text`` as its file."""
    path = tmp_path / "params.yaml"
    path.write_text(text)
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "--params-file", str(path)])
    try:
        node = rclpy.create_node("em_robot", context=context)
        try:
            return declare_exploration_params(node)
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_deprecated_planner_name_is_upgraded_with_a_warning(tmp_path, capfd):
    params = declared_params(tmp_path, "/**:\n  ros__parameters:\n    planner.name: NF\n"
                             "    world.num_robots: 2\n")
    assert params.planner.name == "NEAREST" and params.world.num_robots == 2
    assert "planner name 'NF' is deprecated; using 'NEAREST'" in capfd.readouterr().err


def test_removed_parameter_in_the_file_is_ignored_with_a_warning(tmp_path, capfd):
    params = declared_params(tmp_path, "/**:\n  ros__parameters:\n"
                             "    planner.allocation_waypoint_spacing_m: 10.0\n")
    assert params == ExplorationParams()
    assert "allocation_waypoint_spacing_m is deprecated and ignored" in capfd.readouterr().err


def test_no_warning_without_deprecated_parameters(tmp_path, capfd):
    assert declared_params(tmp_path, "/**:\n  ros__parameters:\n    planner.name: CE\n"
                           ).planner.name == "CE"
    assert "deprecated" not in capfd.readouterr().err
