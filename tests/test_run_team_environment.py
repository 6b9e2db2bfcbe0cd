"""The ROS environment of a team run: what run_team.sh gives its processes (em_activate:
ROS_DISTRO=jazzy, planner plugins of EM_PLUGIN_PATH), what the ``ros2 run`` launchers
export, and the lines it prints before the first step for a second terminal, which give that
terminal the run's ROS environment."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from ros_process import (REPO_ROOT, RUN_PROCESS_PATTERN, finish_team_run, processes_in_domain,
                         start_team_run)

from em_exploration_ros.tools.ament_install import launcher_text

COMMON = REPO_ROOT / "launch_scripts" / "_common.sh"
#: The variables of the run's ROS environment the pasted lines must carry.
ROS_VARIABLES = ("ROS_DISTRO", "ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                 "RMW_IMPLEMENTATION", "FASTRTPS_DEFAULT_PROFILES_FILE")


def _activated(extra: dict[str, str]) -> dict[str, str]:
    """The environment after ``em_activate``, from ``extra`` added to this one."""
    result = subprocess.run(["bash", "-c", f"source {COMMON} && em_activate && env -0"],
                            env={**os.environ, **extra}, capture_output=True, timeout=30,
                            check=True)
    return dict(item.split("=", 1) for item in result.stdout.decode().split("\0") if item)


def test_em_activate_sets_the_distribution_and_the_plugin_path():
    environment = _activated({"PYTHONPATH": "/opt/other/site-packages"})
    assert environment["ROS_DISTRO"] == "jazzy"
    assert "PYTHONPATH" not in environment  # another install's packages stay out
    environment = _activated({"EM_PLUGIN_PATH": "/tmp/plugins:/tmp/more"})
    assert environment["PYTHONPATH"] == "/tmp/plugins:/tmp/more"


def test_the_ros2_run_launchers_set_the_distribution():
    script = launcher_text(Path(sys.prefix), Path(sys.executable), "os:getcwd").rsplit(
        "exec ", 1)[0] + 'echo "$ROS_DISTRO"\n'
    result = subprocess.run(["sh", "-c", script], env={"PATH": os.environ["PATH"]},
                            capture_output=True, text=True, timeout=30)
    assert result.stdout.strip() == "jazzy"


def _environ(pid: int) -> dict[str, str]:
    data = Path(f"/proc/{pid}/environ").read_bytes().decode()
    return dict(item.split("=", 1) for item in data.split("\0") if "=" in item)


def test_run_team_prints_the_second_terminals_lines_before_the_first_step(tmp_path):
    summary = tmp_path / "run" / "summary.json"
    run, domain = start_team_run(tmp_path, "--robots", "1", "--map-size", "20", "--landmarks",
                                 "0", "--planner", "NEAREST", "--max-sim-time", "30",
                                 "--summary", str(summary))
    try:
        world = processes_in_domain(r"world_node", domain)
        assert len(world) == 1
        node_environment = _environ(world[0])
    finally:
        code = finish_team_run(run, 150.0)
    output = run.output()
    assert code == 0, output[-3000:]
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
    lines = output.splitlines()
    header = lines.index("run_team.sh: to see the team from a second terminal (ROS 2 Jazzy; "
                         "docs/topics.md), paste:")
    source, paths, exports = lines[header + 1:header + 4]
    assert source == "source /opt/ros/jazzy/setup.bash"
    # Printed before the evaluator's first line (its log follows on the terminal).
    assert all("explored" not in line for line in lines[:header])
    # Pasted (without the source line: this machine has no /opt/ros), they give the second
    # terminal the variables the nodes have, and this venv's packages on its paths.
    pasted = subprocess.run(["bash", "-c", f"set -e; {paths}; {exports}; env -0"],
                            env={"PATH": os.environ["PATH"], "AMENT_PREFIX_PATH": "/opt/ros",
                                 "PYTHONPATH": "/opt/ros/lib"},
                            capture_output=True, timeout=30, check=True)
    terminal = dict(item.split("=", 1) for item in pasted.stdout.decode().split("\0") if item)
    assert node_environment["ROS_DISTRO"] == "jazzy"
    assert node_environment["ROS_DOMAIN_ID"] == domain
    for name in ROS_VARIABLES:
        assert terminal[name] == node_environment[name], name
    venv = REPO_ROOT / ".venv"
    assert terminal["AMENT_PREFIX_PATH"] == f"/opt/ros:{venv}"
    site = Path(terminal["PYTHONPATH"].split(":")[1])
    assert terminal["PYTHONPATH"].startswith("/opt/ros/lib:") and (site / "em_exploration_msgs"
                                                                  ).is_dir()
