"""em_exploration_ros as ``ros2 pkg`` and ``ros2 run`` find it in the venv's ament prefix.

ros2cli is not on PyPI, so these tests resolve the package the way ros2cli does:
``ros2 pkg prefix``/``executables`` take ``ament_index_python.get_package_prefix(pkg)`` and
list the executable files under ``<prefix>/lib/<pkg>/`` (hidden folders skipped); ``ros2 run
pkg name ARGS`` runs the file of that name with ARGS. Each node started that way with
``--ros-args`` must come up, also from a shell that sourced another ROS 2 install (its
PYTHONPATH, libraries and ament prefix belong to another Python: the launchers set the venv's).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from ament_index_python.packages import get_package_prefix, get_package_share_directory
from catkin_pkg.package import parse_package

from ros_process import REPO_ROOT, NodeProcess, ProcessSet, ros_args

from em_exploration_ros.tools.ament_install import console_scripts, launcher_text

PACKAGE = "em_exploration_ros"
STARTUP_S = 40.0
PARAMS = {"world.num_robots": 1, "world.width_m": 30.0, "world.height_m": 30.0,
          "world.num_landmarks": 3, "planner.name": "CE"}


def package_executables(package: str) -> dict[str, Path]:
    """``{name: path}`` as ``ros2 pkg executables`` lists them."""
    base = Path(get_package_prefix(package)) / "lib" / package
    found = {}
    for directory, subdirectories, files in os.walk(base):
        subdirectories[:] = sorted(d for d in subdirectories if not d.startswith("."))
        for name in sorted(files):
            path = Path(directory) / name
            if os.access(path, os.X_OK):
                found[name] = path
    return found


def test_package_is_in_the_ament_index_with_its_manifest_and_config() -> None:
    assert Path(get_package_prefix(PACKAGE)) == Path(sys.prefix)
    share = Path(get_package_share_directory(PACKAGE))
    manifest = parse_package(share)
    manifest.validate()
    assert manifest.name == PACKAGE and manifest.get_build_type() == "ament_python"
    configs = [path for path in (REPO_ROOT / "config").rglob("*") if path.is_file()]
    assert REPO_ROOT / "config" / "worlds" / "paper_100m_seed0.yaml" in configs
    for config in configs:  # config/worlds/ too
        name = config.relative_to(REPO_ROOT)
        assert (share / name).read_bytes() == config.read_bytes(), name


def test_every_console_script_is_an_executable_of_the_package() -> None:
    scripts = set(console_scripts())
    executables = package_executables(PACKAGE)
    assert set(executables) == scripts
    assert {"em-world", "em-robot", "em-evaluator", "em-record", "em-foxglove"} <= scripts
    result = subprocess.run([str(executables["em-bag"]), "--help"], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0 and "usage: em-bag" in result.stdout


def test_launchers_export_the_teams_fast_dds_profile_unless_one_is_chosen() -> None:
    """``ros2 run`` gets the heartbeat profile the launch scripts export (without it a lost
    packet stalls a lockstep team for 3 s); a profile the caller set is kept."""
    script = launcher_text(Path(sys.prefix), Path(sys.executable), "os:getcwd").rsplit(
        "exec ", 1)[0] + 'echo "$FASTRTPS_DEFAULT_PROFILES_FILE"\n'
    environment = {name: value for name, value in os.environ.items()
                   if name != "FASTRTPS_DEFAULT_PROFILES_FILE"}

    def exported(extra: dict[str, str]) -> str:
        return subprocess.run(["sh", "-c", script], env=dict(environment, **extra),
                              capture_output=True, text=True, timeout=30).stdout.strip()

    team_profile = Path(exported({}))
    assert team_profile.read_bytes() == (REPO_ROOT / "config" / "fastdds_profiles.xml").read_bytes()
    assert exported({"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/my_profiles.xml"}) == \
        "/etc/my_profiles.xml"


def foreign_ros_environment(tmp_path: Path) -> dict[str, str]:
    """What a shell that sourced another ROS 2 install passes on: a PYTHONPATH whose rclpy
    cannot be imported by this Python, that install's libraries and ament prefix."""
    rclpy = tmp_path / "foreign_site_packages" / "rclpy"
    rclpy.mkdir(parents=True)
    (rclpy / "__init__.py").write_text("raise ImportError('rclpy of another ROS 2 install')\n")
    return {"PYTHONPATH": str(rclpy.parent), "LD_LIBRARY_PATH": str(tmp_path / "ros" / "lib"),
            "AMENT_PREFIX_PATH": str(tmp_path / "ros")}


def test_ros2_run_starts_each_node(tmp_path: Path) -> None:
    executables = package_executables(PACKAGE)
    environment = foreign_ros_environment(tmp_path)
    nodes = {
        "em-world": (ros_args(PARAMS), "world ready: 1 robots"),
        "em-robot": (ros_args({**PARAMS, "robot_id": 0, "use_sim_time": True}, "/robot_0"),
                     "robot 0 of 1 ready (planner CE)"),
        "em-evaluator": (ros_args({**PARAMS, "use_sim_time": True,
                                   "summary_path": str(tmp_path / "summary.json")}),
                         "evaluating 1 robots"),
    }
    with ProcessSet() as processes:
        # ros2 run runs the executable file with the arguments after the executable's name.
        started = {name: processes.add(NodeProcess([str(executables[name]), *args],
                                                   tmp_path / f"{name}.log", environment))
                   for name, (args, _line) in nodes.items()}
        for name, (_args, line) in nodes.items():
            started[name].wait_for_output(line, STARTUP_S)
        # They found each other: the world starts stepping the team.
        started["em-world"].wait_for_output("stepping", STARTUP_S)

