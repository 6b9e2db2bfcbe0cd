"""Replay for debugging: the world's topics of a lockstep recording drive fresh robots, which
then choose exactly the targets the recorded robots chose.

bags/sample_3robots/ (a bag directory) is a 3-robot lockstep run;
bags/sample_3robots.params.yaml holds the parameters its nodes ran with. Fresh em-robot
processes with those parameters receive only what the world published (/clock,
/mission/anchor_pose, /robot_i/sonar, /robot_i/odom) through em-replay; they exchange their
own team updates, which reproduce the recorded sequence numbers that the recorded scans name
in their lockstep barrier (SonarScan.team_sequences). em-record records the fresh robots'
team updates; every recorded update's targets (decision index, x, y, frontier type) must
come out the same, in the same updates, in the same order. The fresh robots are given the
recording's run identity (``run_id``, read from its updates): a robot drops what another run
publishes. All processes are bounded in time and stopped.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from rclpy.serialization import deserialize_message
from ros_process import REPO_ROOT, NodeProcess, ProcessSet, ros_args, wait_until

from em_exploration_ros.bag_format.bag_reader import BagScanner
from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.tools.bag_ros import import_message_class

SAMPLE = REPO_ROOT / "bags" / "sample_3robots"
PARAMS_FILE = REPO_ROOT / "bags" / "sample_3robots.params.yaml"
NUM_ROBOTS = load_params(PARAMS_FILE).world.num_robots
WORLD_TOPICS = ["/clock", "/mission/anchor_pose",
                *[f"/robot_{i}/{name}" for i in range(NUM_ROBOTS) for name in ("sonar", "odom")]]
#: Replay speed (sim seconds per wall second): the robots' sensor queues hold 50 steps
#: (10 s of sim time, 5 s of wall time), far more than a CE decision takes on a loaded machine.
REPLAY_RATE = 2.0
#: Wall-time bounds [s]: process start-up, and the replay of the ~31 s recording (~16 s).
STARTUP_TIMEOUT_S = 30.0
REPLAY_TIMEOUT_S = 50.0
TEAM_UPDATE_TYPE = "em_exploration_msgs/msg/TeamUpdate"

#: One target: (decision index, x [m], y [m], frontier type).
Target = tuple[int, float, float, int]


def team_targets(path: Path) -> dict[int, dict[int, list[Target]]]:
    """``{robot: {sequence: targets}}`` of the team updates in a (possibly still open)
    recording; an update resent on request is the same update and counted once."""
    message_class = import_message_class(TEAM_UPDATE_TYPE)
    updates: dict[int, dict[int, list[Target]]] = {}
    for channel, message in BagScanner(path, tolerant=True).messages():
        if not channel.topic.endswith("/team/updates"):
            continue
        update = deserialize_message(message.data, message_class)
        updates.setdefault(update.robot_id, {})[update.sequence] = [
            (t.decision_index, t.x, t.y, t.frontier_type) for t in update.targets]
    return updates


def recorded_run_id(path: Path) -> int:
    """The run identity of the recorded team (the ``run_id`` of its first team update)."""
    message_class = import_message_class(TEAM_UPDATE_TYPE)
    for channel, message in BagScanner(path, tolerant=True).messages():
        if channel.topic.endswith("/team/updates"):
            return int(deserialize_message(message.data, message_class).run_id)
    raise AssertionError(f"no team update in {path}")


def tails(processes: list[NodeProcess]) -> str:
    """The end of each process's log, for a failure message."""
    return "\n".join(f"--- {p.log_path.name}\n{p.output()[-1500:]}" for p in processes)


def test_world_topics_replayed_into_fresh_robots_reproduce_the_targets(tmp_path: Path) -> None:
    recorded = team_targets(SAMPLE)
    assert sorted(recorded) == list(range(NUM_ROBOTS))
    last_sequence = {robot: max(updates) for robot, updates in recorded.items()}
    decisions = sum(len(targets) for updates in recorded.values() for targets in updates.values())
    assert decisions >= 3 * NUM_ROBOTS
    for robot, updates in recorded.items():  # the recording holds every update
        assert sorted(updates) == list(range(1, last_sequence[robot] + 1)), robot

    fresh_bag = tmp_path / "fresh_team_updates"
    run_id = recorded_run_id(SAMPLE)
    assert run_id != 0  # run_team.sh gave the recorded run its own
    with ProcessSet() as processes:
        recorder = processes.start_module(
            "em_exploration_ros.tools.record",
            ["-o", str(fresh_bag), "--regex", r"^/robot_\d+/team/updates$", "--poll-interval",
             "0.2", "--chunk-interval", "0.5"], tmp_path / "record.log")
        robots = [processes.start_module(
            "em_exploration_ros.nodes.robot_node",
            ros_args({"robot_id": robot, "use_sim_time": True, "run_id": run_id},
                     f"/robot_{robot}", PARAMS_FILE),
            tmp_path / f"robot_{robot}.log") for robot in range(NUM_ROBOTS)]
        for robot in robots:
            robot.wait_for_output("waiting for the mission anchor", STARTUP_TIMEOUT_S)
        for robot in range(NUM_ROBOTS):
            recorder.wait_for_output(f"recording /robot_{robot}/team/updates [",
                                     STARTUP_TIMEOUT_S)
        replay = processes.start_module(
            "em_exploration_ros.tools.replay",
            [str(SAMPLE), "--topics", *WORLD_TOPICS, "--rate", str(REPLAY_RATE),
             "--delay", "1.0", "--wait-for-subscribers", "10"], tmp_path / "replay.log")

        def caught_up() -> bool:
            fresh = team_targets(fresh_bag) if fresh_bag.exists() else {}
            return all(max(fresh.get(robot, {0: []})) >= last
                       for robot, last in last_sequence.items())

        try:
            wait_until(caught_up, REPLAY_TIMEOUT_S, "the fresh robots' team updates", poll_s=1.0)
        except TimeoutError as error:
            pytest.fail(f"{error}\n{tails([replay, *robots])}")
        assert recorder.stop() == 0, recorder.output()[-2000:]
        # No robot had to give up waiting for a teammate: the barrier was met every step.
        assert not any("going on without them" in robot.output() for robot in robots), tails(
            robots)

    fresh = team_targets(fresh_bag)
    for robot, updates in recorded.items():
        replayed = {sequence: fresh[robot][sequence] for sequence in updates}
        assert replayed == updates, robot
