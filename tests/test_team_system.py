"""The running team over DDS: decentralization, robustness to hostile messages and to a
robot that dies.

- The ROS graph of a running team shows that no robot node subscribes to any ground-truth
  topic (everything under /world); each robot node is its own OS process, and killing one
  of them mid-run leaves the others to finish the exploration.
- An outside process publishing malformed or stale team updates on the team topics
  causes logged rejections, no crash, and the same run result as without it.
"""
from __future__ import annotations

import json
import os
import re
import signal
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from em_exploration_msgs.msg import TeamUpdate
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from em_exploration_ros.nodes.qos import TEAM_QOS

from ros_process import (REPO_ROOT, RUN_PROCESS_PATTERN, NodeProcess, ProcessSet,
                         graph_reader, processes_in_domain, robot_pid, start_team_run,
                         wait_for_liveliness, wait_until)

#: Bound of one team run in these tests [s].
RUN_TIMEOUT_S = 180.0
SMALL_TEAM = ("--robots", "3", "--map-size", "60", "--landmarks", "6", "--seed", "2",
              "--max-sim-time", "600")


@pytest.fixture
def graph_node():
    """An rclpy node in this test run's domain, to read the ROS graph."""
    with graph_reader() as node:
        yield node


def robot_nodes(node: Node) -> set[str]:
    return {f"{ns.rstrip('/')}/{name}" for name, ns in node.get_node_names_and_namespaces()
            if name == "em_robot"}


def test_robots_are_separate_processes_blind_to_ground_truth_and_survive_a_dead_teammate(
        tmp_path, graph_node):
    params = tmp_path / "params.yaml"
    params.write_text((REPO_ROOT / "config" / "exploration.yaml").read_text()
                      + "/em_world:\n  ros__parameters:\n    robot_timeout_s: 3.0\n")
    summary_path = tmp_path / "summary.json"
    run, domain = start_team_run(tmp_path, *SMALL_TEAM, "--planner", "EM_3",
                                 "--until-explored", "0.85", "--params", str(params),
                                 "--summary", str(summary_path))
    with run:
        expected = {f"/robot_{i}/em_robot" for i in range(3)}
        wait_until(lambda: robot_nodes(graph_node) >= expected, 60.0, "three robot nodes")

        def subscribed(robot: int) -> set[str]:
            topics = graph_node.get_subscriber_names_and_types_by_node("em_robot",
                                                                       f"/robot_{robot}")
            return {name for name, _ in topics}

        # a node is discovered before all of its subscriptions are
        def needed(robot: int) -> set[str]:
            return {f"/robot_{robot}/sonar", f"/robot_{robot}/odom"} | {
                f"/robot_{j}/team/updates" for j in range(3) if j != robot}

        wait_until(lambda: all(needed(r) <= subscribed(r) for r in range(3)), 60.0,
                   "the robots' sensor and team subscriptions")
        for robot in range(3):
            names = subscribed(robot)
            assert not any(name.startswith("/world") for name in names), names
            assert f"/robot_{robot}/sonar" in names and f"/robot_{robot}/odom" in names
            teammates = {f"/robot_{j}/team/updates" for j in range(3) if j != robot}
            assert teammates <= names
            # Besides their updates, only their liveliness (a topic that carries no data).
            liveliness = {f"/robot_{j}/alive" for j in range(3) if j != robot}
            assert not any(name.startswith(f"/robot_{j}/") and name not in teammates | liveliness
                           for j in range(3) if j != robot for name in names)
        pids = {robot: robot_pid(domain, robot) for robot in range(3)}
        assert len(set(pids.values())) == 3  # one OS process per robot

        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)  # mid-run
        os.kill(pids[1], signal.SIGKILL)
        code = run.wait(RUN_TIMEOUT_S)
    output = run.output()
    assert code == 0, output[-3000:]
    assert "robot_1 exited with code 137; the team goes on" in output
    summary = json.loads(summary_path.read_text())
    assert summary["explored_ratio"] >= 0.85, summary["stop_reason"]
    assert "explored ratio" in summary["stop_reason"]
    assert summary["sim_time_s"] > 60.0  # the survivors explored for long after the kill
    assert all(r["distance_m"] > 1.0 for r in summary["robots"] if r["id"] != 1)
    world_log = (summary_path.parent / "logs" / "world.log").read_text()
    assert "robot 1 lost:" in world_log
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []


HOSTILE_PUBLISHER = r'''
import math, sys, time
from pathlib import Path
import rclpy
from em_exploration_msgs.msg import Keyframe, KeyframeTeammate, TeamUpdate, TargetRecord
from rclpy.node import Node
from rclpy.serialization import serialize_message

from em_exploration_ros.nodes.qos import TEAM_QOS

rclpy.init()
node = Node("intruder")
pubs = {r: node.create_publisher(TeamUpdate, f"/robot_{r}/team/updates", TEAM_QOS)
        for r in range(3)}
# An intruder inside the run: it takes the run's identity from what robot 0 publishes (the
# nodes drop any other run's messages before they look at them).
heard = []
node.create_subscription(TeamUpdate, "/robot_0/team/updates", heard.append, TEAM_QOS)
# Matched first (two teammates and the evaluator read each topic, and its own reader robot
# 0's), so that nothing it sends after the go file appears is lost to discovery, which can
# take seconds.
until = time.monotonic() + 60.0
while any(pub.get_subscription_count() < 3 + (r == 0) for r, pub in pubs.items()):
    if time.monotonic() > until:
        sys.exit("the team's readers were not discovered within 60 s")
    time.sleep(0.01)
print("matched", flush=True)
go_file = Path(sys.argv[2])
while not go_file.exists() or not heard:
    if time.monotonic() > until + 120.0:
        sys.exit("no update of robot 0 heard")
    rclpy.spin_once(node, timeout_sec=0.01)
run_id = heard[0].run_id

def update(robot, sequence, **fields):
    message = TeamUpdate(run_id=run_id, robot_id=robot, sequence=sequence)
    for key, value in fields.items():
        setattr(message, key, value)
    return message

nan_keyframe = Keyframe(index=3, previous_index=2, odom_x=math.nan)
bad_target = TargetRecord(x=math.inf, frontier_type=1)
stranger = Keyframe(index=4, previous_index=3, teammates=[KeyframeTeammate(robot_id=9)])
deadline = time.monotonic() + float(sys.argv[1])
count = 0
while time.monotonic() < deadline:
    for robot in range(3):
        pubs[robot].publish(update(robot, 1))                        # duplicate / stale
        pubs[robot].publish(update((robot + 1) % 3, 5))              # id of another robot
        pubs[robot].publish(update(robot, 10**9))                    # implausible sequence
    pubs[1].publish(update(1, 2, keyframes=[nan_keyframe]))          # NaN pose
    pubs[1].publish(update(7, 3))                                    # unknown robot id
    pubs[1].publish(update(1, 4, targets=[bad_target]))              # infinite target
    pubs[1].publish(update(1, 5, keyframes=[stranger]))              # unknown teammate id
    pubs[2].publish(serialize_message(update(2, 6))[:13])            # truncated CDR
    count += 1
    time.sleep(0.05)
print(f"published {count} rounds", flush=True)
'''


def run_summary(tmp_path, name: str, with_intruder: bool,
                beside: ProcessSet | None = None) -> tuple[dict, str]:
    """One CE team run, attacked or not (``beside`` another one: ``start_team_run``)."""
    summary_path = tmp_path / name / "summary.json"
    run, domain = start_team_run(tmp_path / name, *SMALL_TEAM, "--planner", "CE",
                                 "--until-explored", "0.8", "--summary", str(summary_path),
                                 beside=beside)
    intruder = None
    with run:
        try:
            if with_intruder:
                # Started with the team and matched to its readers; it sends from mid-run on
                # (when the go file appears), so its stale sequence numbers really are stale.
                # Started mid-run instead, it was discovered in CI only as the run ended.
                go_file = tmp_path / name / "intruder.go"
                intruder = NodeProcess([sys.executable, "-c", HOSTILE_PUBLISHER, "30",
                                        str(go_file)], tmp_path / name / "intruder.out")
                run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
                wait_until(lambda: evaluator_heard_every_robot(
                    summary_path.parent / "logs" / "evaluator.log", robots=3,
                    evaluations_after=3), RUN_TIMEOUT_S, "the evaluator hearing every robot")
                intruder.wait_for_output("matched", RUN_TIMEOUT_S)
                go_file.touch()
            code = run.wait(RUN_TIMEOUT_S)
        finally:  # also when the test is interrupted before the attack
            if intruder is not None:
                intruder.stop()
    assert code == 0, run.output()[-3000:]
    logs = "".join(p.read_text() for p in (summary_path.parent / "logs").glob("robot_*.log"))
    return json.loads(summary_path.read_text()), logs


def evaluator_heard_every_robot(log_path, robots: int, evaluations_after: int) -> bool:
    """Whether the evaluator saw the liveliness of all ``robots`` robots and then evaluated
    ``evaluations_after`` more times (time for a gap in a stream to be asked for and
    re-sent). Until then a robot's first team updates may not have reached it: when Fast
    DDS misses a participant's first announcements, discovery waits for the next one (1 s
    with config/fastdds_profiles.xml), and at 25x the team passes t = 20 s within a second.
    A forged update with the next sequence number is well-formed and cannot be told from
    the robot's own; sent before the real one, it takes its place (this test once lost
    robot 0's first target so)."""
    lines = log_path.read_text().splitlines() if log_path.exists() else []
    heard = [i for i, line in enumerate(lines) if "liveliness asserted" in line]
    seen = {re.search(r"robot (\d+): liveliness", lines[i]).group(1) for i in heard}
    if len(seen) < robots:
        return False
    return sum("t=" in line for line in lines[max(heard) + 1:]) >= evaluations_after


def test_hostile_team_messages_are_rejected_and_change_nothing(tmp_path):
    # The clean run goes on beside the attacked one, in a domain of its own (stopped at
    # once if the attacked one fails).
    with ThreadPoolExecutor(max_workers=1) as thread, ProcessSet() as beside:
        clean_run = thread.submit(run_summary, tmp_path, "clean", with_intruder=False,
                                  beside=beside)
        attacked, logs = run_summary(tmp_path, "attacked", with_intruder=True)
        clean, _ = clean_run.result()
    assert "rejected a team update" in logs
    for reason in ("not finite", "not a robot of this team", "implausibly far",
                   "on robot"):
        assert reason in logs, reason
    assert [r["targets"] for r in attacked["robots"]] == [r["targets"] for r in clean["robots"]]
    for key in ("explored_ratio", "loc_rmse_m", "landmark_rmse_m", "sim_time_s", "decisions"):
        assert attacked[key] == clean[key], key


def keyframes_in_graph(log: str, robot: int) -> set[int]:
    """Robot ``robot``'s keyframe indices in the last "team graph keyframes" line of a log."""
    line = [text for text in log.splitlines() if "team graph keyframes:" in text][-1]
    ranges = re.search(rf"robot {robot}: \d+ \[([0-9 -]*)\]", line).group(1).split()
    return {i for r in ranges for i in range(int(r.split("-")[0]), int(r.split("-")[1]) + 1)}


def test_killed_and_wedged_robots_are_restarted_and_rejoin_without_losing_keyframes(
        tmp_path, graph_node):
    """--respawn: robot 1 is SIGKILLed mid-run, later robot 2 is SIGSTOPped (alive but off
    the graph, as in the Fast DDS deadlock); both are noticed, restarted and rejoin: their
    earlier keyframes are all in every robot's graph at the end and the summary shows the
    downtimes."""
    summary_path = tmp_path / "summary.json"
    published: dict[int, set[int]] = {1: set(), 2: set()}
    for robot in published:
        graph_node.create_subscription(
            TeamUpdate, f"/robot_{robot}/team/updates",
            lambda m, r=robot: published[r].update(k.index for k in m.keyframes), TEAM_QOS)
    run, domain = start_team_run(tmp_path, "--robots", "3", "--map-size", "80", "--landmarks",
                                 "8", "--seed", "2", "--max-sim-time", "900", "--respawn",
                                 "--summary", str(summary_path))
    evaluator_log = summary_path.parent / "logs" / "evaluator.log"

    executor = SingleThreadedExecutor(context=graph_node.context)
    executor.add_node(graph_node)

    def spin_until(condition, what: str) -> None:
        wait_until(condition, RUN_TIMEOUT_S, what,
                   while_waiting=lambda: executor.spin_once(timeout_sec=0.05))

    with run:
        # Mid-run, and this observer has heard both robots (a fast lockstep team reaches
        # 20 simulated seconds within about a second, before discovery may have matched it).
        spin_until(lambda: "t=   20.0 s" in run.output() and published[1] and published[2],
                   "mid-run, with team updates of robots 1 and 2 heard")
        os.kill(robot_pid(domain, 1), signal.SIGKILL)
        before_crash = set(published[1])
        spin_until(lambda: "robot 1 rejoined" in evaluator_log.read_text(), "robot 1 rejoining")
        before_wedge = set(published[2])
        wedged = robot_pid(domain, 2)
        os.kill(wedged, signal.SIGSTOP)
        spin_until(lambda: "robot 2 rejoined" in evaluator_log.read_text(), "robot 2 rejoining")
        code = run.wait(RUN_TIMEOUT_S)
    output = run.output()
    assert code == 0, output[-3000:]
    assert "robot_1 exited with code 137; restarting it" in output
    assert "robot_2 is alive but lost to the world (wedged or silent); restarting it" in output
    summary = json.loads(summary_path.read_text())
    assert summary["explored_ratio"] >= 0.85, summary["stop_reason"]
    logs = summary_path.parent / "logs"
    for name in ("world", "evaluator", "robot_0"):
        log = (logs / f"{name}.log").read_text()
        # Robot 1's new process may assert its liveliness before the killed one's lease (3 s)
        # runs out: then no loss is reported, only the restart.
        assert ("1: liveliness lost" in log
                or "1: liveliness asserted by a new process (restarted)" in log), name
        assert "2: liveliness lost" in log, name  # wedged: restarted only once found lost
    assert before_crash and before_wedge
    log = (logs / "evaluator.log").read_text()
    assert "robot 1 lost:" in log and "robot 2 lost:" in log
    assert "robot 2 lost:" in (logs / "world.log").read_text()  # it waited for robot 2
    for robot in range(3):
        log = (logs / f"robot_{robot}.log").read_text()
        assert before_crash <= keyframes_in_graph(log, 1), robot   # 0 keyframes lost
        assert before_wedge <= keyframes_in_graph(log, 2), robot
        # a restarted robot hears its own request for its stream: not a dropped message
        assert "which is not a teammate" not in log, robot
    for robot in (1, 2):
        entry = summary["robots"][robot]
        lost, rejoined = entry["status_changes"][:2]
        assert (lost["status"], rejoined["status"]) == ("lost", "rejoined")
        # The world may have waited for it (no simulated time lost), but it was down.
        assert rejoined["wall_s"] > lost["wall_s"] and entry["downtime_wall_s"] > 0.0
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []


def test_a_robot_killed_and_restarted_by_hand_rejoins_on_a_participant_id_of_its_own(
        tmp_path):
    """No --respawn: robot 1 is SIGKILLed mid-run and started again by hand, with its
    command line and environment (as ``ros2 run`` with the same arguments would). Fast DDS
    would give it the dead process's participant id, whose shared-memory port the others
    may still write into; it takes one of its own, gets its stream back and rejoins."""
    summary_path = tmp_path / "summary.json"
    run, domain = start_team_run(tmp_path, *SMALL_TEAM, "--until-explored", "0.93",
                                 "--summary", str(summary_path))
    logs = summary_path.parent / "logs"
    with run, ProcessSet() as by_hand:
        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
        for log in ("world.log", "evaluator.log"):
            wait_for_liveliness(logs / log, 1, RUN_TIMEOUT_S)
        pid = robot_pid(domain, 1)
        command = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")[:-1]
        environment = dict(item.split("=", 1) for item in Path(
            f"/proc/{pid}/environ").read_bytes().decode().split("\0") if "=" in item)
        os.kill(pid, signal.SIGKILL)
        restarted = by_hand.add(NodeProcess(command, tmp_path / "robot_1_by_hand.log",
                                            env=environment))
        wait_until(lambda: "robot 1 rejoined" in (logs / "evaluator.log").read_text(),
                   RUN_TIMEOUT_S, "robot 1 rejoining")
        code = run.wait(RUN_TIMEOUT_S)
    output = run.output()
    assert code == 0, output[-3000:]
    assert "robot_1 exited with code 137; the team goes on" in output
    assert re.search(r"participant id \d+ instead of (\d+): a process that died held id \1 ",
                     restarted.output()), restarted.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    assert summary["explored_ratio"] >= 0.93, summary["stop_reason"]
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []


def test_a_robot_wedged_early_in_the_run_is_restarted(tmp_path):
    """--respawn: a robot SIGSTOPped a few seconds after the run started (a fast lockstep
    team is 20 simulated seconds in by then) is restarted and rejoins. run_team.sh ignored
    a robot's "lost" report for 15 s after its start, meant for a restarted robot's previous
    process, and so left a robot wedged early in the run down for good."""
    summary_path = tmp_path / "summary.json"
    # Explored ratio 0.93, not 0.85: the restart takes several seconds of wall time, in which
    # a 20x team explores a lot; the run must still be on when the robot answers again.
    run, domain = start_team_run(tmp_path, "--robots", "3", "--map-size", "60", "--landmarks",
                                 "6", "--seed", "2", "--max-sim-time", "600",
                                 "--until-explored", "0.93", "--respawn",
                                 "--summary", str(summary_path))
    with run:
        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
        for log in ("world.log", "evaluator.log"):
            wait_for_liveliness(summary_path.parent / "logs" / log, 2, RUN_TIMEOUT_S)
        os.kill(robot_pid(domain, 2), signal.SIGSTOP)
        code = run.wait(RUN_TIMEOUT_S)
    output = run.output()
    assert code == 0, output[-3000:]
    assert "robot_2 is alive but lost to the world (wedged or silent); restarting it" in output
    assert "robot 2 rejoined" in (summary_path.parent / "logs" / "evaluator.log").read_text()


def test_a_team_restarted_whole_takes_its_streams_back_from_the_robots_journals(tmp_path):
    """--respawn: every robot wedged at once (SIGSTOP), so all are found lost, killed and
    restarted. The world waits for the team instead of ending the mission (it stepped over
    at once: every robot was stopped). No teammate holds a robot's earlier stream then; each
    restarted robot reads it back from its own journals (run_team.sh gives them
    <run>/state), with the teammates' records it had applied, rejoins with all of it, and
    the team explores on. Without the journals they resumed with none of it after 20 s, and
    robots 1 and 2 stood still for the rest of the run (nothing tied them to the map)."""
    summary_path = tmp_path / "summary.json"
    run, domain = start_team_run(tmp_path, *SMALL_TEAM, "--respawn",
                                 "--summary", str(summary_path))
    with run:
        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
        for robot in range(3):
            os.kill(robot_pid(domain, robot), signal.SIGSTOP)
        code = run.wait(RUN_TIMEOUT_S)
    output = run.output()
    assert code == 0, output[-3000:]
    logs = summary_path.parent / "logs"
    assert "waiting up to 60 s for one to come back" in (summary_path.parent / "logs"
                                                         / "world.log").read_text()
    # Each was restarted once: a process that rejoins within a second has the world's "lost"
    # (about its restart) and "rejoined" lines in one look of run_team.sh, which took the
    # lost line for one about the new process and restarted it again.
    assert "(respawn 2)" not in output, output[-3000:]
    for robot in range(3):
        assert (f"robot_{robot} is alive but lost to the world (wedged or silent); "
                f"restarting it") in output
        log = (logs / f"robot_{robot}.log").read_text()
        read = re.search(r"read (\d+) records of this robot's stream from its journal .*"
                         r"the team holds it up to sequence (\d+)\) and (\d+) of its "
                         r"teammates'", log)
        assert read and int(read.group(1)) >= int(read.group(2)) > 0, log[-2000:]
        assert int(read.group(3)) > 0  # and the teammates' records it had applied
        assert "resuming without" not in log and "no estimate of this robot's own pose" \
            not in log, robot
    summary = json.loads(summary_path.read_text())
    assert summary["explored_ratio"] >= 0.85, summary["stop_reason"]
    final = (logs / "robot_0.log").read_text()
    for robot in range(3):
        changes = [change["status"] for change in summary["robots"][robot]["status_changes"]]
        assert "rejoined" in changes, (robot, changes)
        rejoined = re.search(r"rejoined: recovered \d+ records of this robot's stream "
                             r"\(keyframes \d+ \[0-(\d+)\]",
                             (logs / f"robot_{robot}.log").read_text())
        assert rejoined, robot
        # It explored on: robot 0's final graph holds many keyframes it made after it.
        assert max(keyframes_in_graph(final, robot)) > int(rejoined.group(1)) + 10, robot
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
