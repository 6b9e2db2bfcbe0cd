"""Robots on separate hosts (em_exploration_ros.tools.separate_hosts): the world and each robot
in its own network namespace, joined by veth pairs to a bridge, DDS over UDPv4 with multicast
discovery; the lockstep team chooses em-sim's targets (the one-host run's), every host's
traffic crossed the bridge, and nothing is left behind, with 1 packet in 10 lost at each end of
every robot's link. Needs root and ``ip netns``; skips with the reason otherwise."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from em_exploration_ros.tools.separate_hosts import (cannot_run_reason, loss_problem,
                                                      subnet_problem)
from ros_process import REPO_ROOT

#: Bound of the whole tool run: set-up check, discovery, a 30 m exploration, em-sim [s].
RUN_TIMEOUT_S = 150.0

REASON = cannot_run_reason()


@pytest.mark.skipif(REASON is not None, reason=f"separate hosts: {REASON}")
def test_team_on_separate_hosts_with_lossy_links_chooses_the_one_host_targets(tmp_path):
    """Every team topic is reliable, so lost packets are sent again once the writer's
    heartbeat shows the gap; with Fast DDS's default 3 s heartbeat this team crawled (no
    lossy run of a 60 m mission finished in 600 s), with the team's profile (100 ms) it
    finishes with the same decisions."""
    result_path = tmp_path / "result.json"
    command = [sys.executable, "-m", "em_exploration_ros.tools.separate_hosts",
               "--robots", "3", "--map-size", "30", "--landmarks", "4", "--seed", "1",
               "--loss", "10",
               "--out", str(tmp_path / "run"), "--json", str(result_path),
               "--timeout", "120", "--domain-id", os.environ.get("ROS_DOMAIN_ID", "0")]
    tool = subprocess.Popen(command, cwd=REPO_ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        output, _ = tool.communicate(timeout=RUN_TIMEOUT_S)
    finally:
        if tool.poll() is None:
            tool.terminate()  # the tool removes its namespaces on SIGTERM
            tool.wait(timeout=30)
    assert tool.returncode == 0, output
    result = json.loads(result_path.read_text())
    assert result["exit_code"] == 0 and result["same_targets"], output
    assert len(result["hosts_targets"]) == 3 and all(result["hosts_targets"])
    assert result["hosts_targets"] == result["em_sim_targets"]
    assert 0.07 < result["drop_ratio"] < 0.13, result["drop_ratio"]
    # Every host talked through the bridge (the world's host carries the most: it serves all).
    traffic = result["bridge_bytes"]
    assert sorted(traffic) == ["robot_0", "robot_1", "robot_2", "world"]
    assert min(traffic.values()) > 10_000 and traffic["world"] == max(traffic.values())
    namespaces = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert f"emh{tool.pid}_" not in namespaces


@pytest.mark.parametrize("subnet, problem", [
    ("10.0.0.0/24", None),
    ("garbage", "does not appear to be an IPv4 or IPv6 network"),
    ("10.0.0.1/24", "has host bits set"),
    ("10.0.0.0/30", "must be a private IPv4 network with room for 4 hosts"),
    ("8.8.8.0/24", "must be a private IPv4 network"),
    ("fe80::/120", "must be a private IPv4 network"),  # discovery is IPv4 multicast
])
def test_a_subnet_that_cannot_hold_the_team_is_named(subnet, problem):
    """Checked before any namespace is made (a bad one gave a traceback, an IPv6 one a
    team that never started)."""
    found = subnet_problem(subnet, 4)
    assert found is None if problem is None else problem in found


@pytest.mark.parametrize("one_in, fine", [(0, True), (1, False), (-3, False), (2, True),
                                          (2 ** 32 - 1, True), (2 ** 32, False)])
def test_a_loss_the_filter_cannot_draw_is_named(one_in, fine):
    """--loss N is the modulus of a 32-bit BPF constant: tc silently truncated a larger one
    (99999999999 dropped nothing) instead of refusing it."""
    assert (loss_problem(one_in) is None) == fine
