"""The ROS environment of a team run: what run_team.sh gives its processes (em_activate:
ROS_DISTRO=jazzy, planner plugins of EM_PLUGIN_PATH), what the ``ros2 run`` launchers
export, and the lines it prints before the first step for a second terminal, which give that
terminal the run's ROS environment."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

from ros_process import (REPO_ROOT, RUN_PROCESS_PATTERN, NodeProcess, ProcessSet,
                         finish_team_run, processes_in_domain, start_team_run, wait_until)

from em_exploration_ros.nodes.fastdds_shm import in_domain
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


SHARED_MEMORY = Path("/dev/shm")
#: A ROS participant that says when it is up, then waits to be stopped.
PARTICIPANT = """
import sys, time, rclpy
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("shm_probe")
node.create_publisher(String, "shm_probe", 10)
print("up", flush=True)
time.sleep(120)
"""
CLEANED = (r"^run_team\.sh: removed the shared-memory files of (\d+) port\(s\) of ROS domain "
           r"(\d+) and (\d+) segment\(s\) that dead Fast DDS processes left in /dev/shm$")


def _fast_dds_files() -> set[str]:
    return {path.name for path in SHARED_MEMORY.glob("*fastrtps_*")}


def _files_locked_by(pid: int) -> set[str]:
    """The Fast DDS files (segments, ports) whose lock file ``pid`` holds (/proc/locks)."""
    inodes = {line.split()[5].rsplit(":", 1)[1] for line in
              Path("/proc/locks").read_text().splitlines() if line.split()[4] == str(pid)}
    return {path.name[:-3] for path in SHARED_MEMORY.glob("fastrtps_*_el")
            if str(path.stat().st_ino) in inodes}


def _participant(processes: ProcessSet, domain: int, log_path: Path
                 ) -> tuple[NodeProcess, set[str]]:
    """A live participant in ``domain`` (stopped with ``processes``) and the shared-memory
    files it owns (a segment, ports), once it owns a port of the domain."""
    process = processes.add(NodeProcess([sys.executable, "-c", PARTICIPANT], log_path,
                                        env={"ROS_DOMAIN_ID": str(domain)}))
    process.wait_for_output("up", 60)
    wait_until(lambda: _domain_ports(_files_locked_by(process.pid), domain), 30,
               f"a shared-memory port of domain {domain} locked by the participant")
    return process, _files_locked_by(process.pid)


def _domain_ports(files: set[str], domain: int) -> set[str]:
    return {name for name in files if (port := re.fullmatch(r"fastrtps_port(\d+)", name))
            and in_domain(int(port[1]), domain)}


def _clean_shared_memory(domain: int, venv: str = "$EM_VENV") -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", "-c", f"source {COMMON} && em_activate && ROS_DOMAIN_ID={domain} "
                       f"EM_VENV={venv} em_clean_shared_memory run_team.sh"],
        capture_output=True, text=True, timeout=60)


def test_shared_memory_dead_processes_left_is_removed_in_the_run_s_domain_only(tmp_path):
    """run_team.sh and run_tests.sh start with this: files piled up by killed processes
    made a new run's processes miss some of each other's data. A dead port of another
    domain stays: there, it tells a restart not to take the dead one's participant id. (A
    live port in the run's domain: tests/test_fastdds_shm.py.)"""
    domain = int(os.environ["ROS_DOMAIN_ID"])
    # Each participant alone in its domain: a live one that had written to the killed one's
    # port may remove that port itself (Fast DDS does, now and then).
    other, third = domain % 101 + 1, (domain + 1) % 101 + 1
    with ProcessSet() as processes:
        try:
            killed, killed_files = _participant(processes, domain, tmp_path / "killed.log")
            elsewhere, elsewhere_files = _participant(processes, other,
                                                      tmp_path / "elsewhere.log")
            _, live_files = _participant(processes, third, tmp_path / "live.log")
            for process in (killed, elsewhere):
                process.signal_group(signal.SIGKILL)
                process.wait(30)
            assert killed_files | elsewhere_files <= _fast_dds_files()  # a killed one's stay
            result = _clean_shared_memory(domain)
            assert result.returncode == 0 and result.stderr == "", result.stderr
            removed = re.match(CLEANED, result.stdout.strip())
            assert removed, result.stdout
            assert int(removed[1]) >= 1 and int(removed[2]) == domain and int(removed[3]) >= 2
            left = _fast_dds_files()
            assert not _domain_ports(killed_files, domain) & left
            assert _domain_ports(elsewhere_files, other) <= left  # another domain's stays
            assert not {name for name in killed_files | elsewhere_files
                        if re.fullmatch(r"fastrtps_[0-9a-z]{16}", name)} & left  # segments go
            assert live_files <= left  # a live process's segment (and port) stay
            again = _clean_shared_memory(domain)
            assert again.returncode == 0 and again.stdout == "" and again.stderr == ""
        finally:
            _clean_shared_memory(other)


def test_a_failed_clean_of_shared_memory_is_a_warning_not_a_failure():
    result = _clean_shared_memory(int(os.environ["ROS_DOMAIN_ID"]), venv="/nonexistent")
    assert result.returncode == 0 and result.stdout == ""
    assert result.stderr.startswith("run_team.sh: warning: could not remove Fast DDS's "
                                    "leftover shared-memory files ("), result.stderr
    assert len(result.stderr.splitlines()) == 1
