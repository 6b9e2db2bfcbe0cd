"""em-world over the real middleware, driven by a scripted fake team in the test process.

The world node runs as its own OS process (tests/ros_process.py); the test plays every robot
with one rclpy node: it listens to each robot's sonar and odometry, answers each step with a
scripted MotionCommand and also listens to the team-update topics (the world's start-up
condition). An in-process ``WorldSimulation`` with the same parameters, driven by the same
commands, must produce exactly the numbers that arrive over DDS.
"""
from __future__ import annotations

import math
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import rclpy
from em_exploration_msgs.msg import LandmarkArray, MotionCommand, SonarScan, TeamUpdate
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from ros_process import NodeProcess, ros_args, wait_until
from rosgraph_msgs.msg import Clock

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.wire_model import pose_through_wire, sim_time_s
from em_exploration_ros.core.world.simulation import WorldSimulation
from em_exploration_ros.nodes.conversions import (landmark_positions_from_msg,
                                                  landmark_reading_from_msg, odometry_pose,
                                                  odometry_twist_covariance, quaternion_to_yaw,
                                                  seconds_to_time, teammate_reading_from_msg,
                                                  time_to_seconds)
from em_exploration_ros.nodes.qos import CLOCK_QOS, LATCHED_QOS, SENSOR_QOS, STREAM_QOS, TEAM_QOS

WORLD_MODULE = "em_exploration_ros.nodes.world_node"
NUM_ROBOTS = 2
STARTUP_S = 30.0     # process start-up and discovery, generous for a loaded machine
STEP_S = 10.0        # one lockstep exchange
QUIET_S = 0.6        # how long "nothing happens" is observed
EXPLORATION = {"world.num_robots": NUM_ROBOTS, "world.width_m": 40.0, "world.height_m": 40.0,
               "world.num_landmarks": 6}


def local_params(seed: int) -> ExplorationParams:
    """The parameters the world process gets, as a core object."""
    nested: dict[str, dict] = {}
    for name, value in EXPLORATION.items():
        group, field = name.split(".")
        nested.setdefault(group, {})[field] = value
    nested["run"] = {"seed": seed}
    return ExplorationParams().replace(**nested)


def scripted_command(robot: int, step: int) -> tuple[float, float]:
    """A deterministic, varied velocity command (m/s, rad/s) for a robot at a step."""
    return 1.0, 0.9 * math.sin(0.7 * step + 1.3 * robot)


class FakeTeam:
    """Every robot's side of the protocol, in one in-test rclpy node with its own context."""

    def __init__(self, num_robots: int) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("fake_team", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.scans: list[dict[int, SonarScan]] = [{} for _ in range(num_robots)]
        self.scan_arrivals: list[Counter[int]] = [Counter() for _ in range(num_robots)]
        self.odometry: list[dict[float, Odometry]] = [{} for _ in range(num_robots)]
        self.truth: list[dict[float, Odometry]] = [{} for _ in range(num_robots)]
        self.clock_stamps: list[float] = []
        self.anchor: PoseStamped | None = None
        self.landmarks: LandmarkArray | None = None
        self.command_pubs = []
        node = self.node
        node.create_subscription(PoseStamped, "/mission/anchor_pose",
                                 lambda m: setattr(self, "anchor", m), LATCHED_QOS)
        node.create_subscription(LandmarkArray, "/world/landmarks",
                                 lambda m: setattr(self, "landmarks", m), LATCHED_QOS)
        node.create_subscription(Clock, "/clock", lambda m: self.clock_stamps.append(
            time_to_seconds(m.clock)), CLOCK_QOS)
        for robot in range(num_robots):
            ns = f"/robot_{robot}"
            node.create_subscription(SonarScan, f"{ns}/sonar",
                                     lambda m, r=robot: self._on_scan(r, m), SENSOR_QOS)
            node.create_subscription(Odometry, f"{ns}/odom", lambda m, r=robot: self.odometry[r]
                                     .__setitem__(time_to_seconds(m.header.stamp), m), SENSOR_QOS)
            node.create_subscription(Odometry, f"/world/ground_truth/robot_{robot}",
                                     lambda m, r=robot: self.truth[r].__setitem__(
                                         time_to_seconds(m.header.stamp), m), STREAM_QOS)
            node.create_subscription(TeamUpdate, f"{ns}/team/updates", lambda m: None, TEAM_QOS)
            self.command_pubs.append(node.create_publisher(MotionCommand, f"{ns}/motion_command",
                                                           SENSOR_QOS))

    def _on_scan(self, robot: int, message: SonarScan) -> None:
        self.scans[robot][int(message.step)] = message
        self.scan_arrivals[robot][int(message.step)] += 1

    def spin(self) -> None:
        self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.spin()

    def has_step(self, step: int, robots: range) -> bool:
        """True when sonar, odometry and ground truth of ``step`` arrived for ``robots``."""
        for robot in robots:
            scan = self.scans[robot].get(step)
            if scan is None:
                return False
            stamp = time_to_seconds(scan.header.stamp)
            if stamp not in self.odometry[robot] or stamp not in self.truth[robot]:
                return False
        return True

    def wait_step(self, step: int, timeout_s: float = STEP_S) -> None:
        wait_until(lambda: self.has_step(step, range(len(self.scans))), timeout_s,
                   f"step {step}", while_waiting=self.spin)

    def answer(self, robot: int, step: int, linear_x: float, angular_z: float,
               team_sequence: int = 0, finished: bool = False) -> None:
        message = MotionCommand(robot_id=robot, step=step, team_sequence=team_sequence,
                                finished=finished)
        message.header.stamp = seconds_to_time(sim_time_s(step, 0.2))  # as a robot answers
        message.header.frame_id = f"robot_{robot}/base_link"
        message.twist.linear.x, message.twist.angular.z = linear_x, angular_z
        self.command_pubs[robot].publish(message)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def assert_step_matches(team: FakeTeam, sim: WorldSimulation, step: int,
                        team_sequences: list[int]) -> None:
    """What arrived for ``step`` equals what ``sim`` (at that step) senses, bit for bit."""
    assert sim.step == step
    for robot in range(sim.params.world.num_robots):
        frame = sim.sense(robot)
        scan = team.scans[robot][step]
        assert scan.robot_id == robot and scan.header.frame_id == f"robot_{robot}/base_link"
        assert time_to_seconds(scan.header.stamp) == frame.stamp_s
        assert list(scan.team_sequences) == team_sequences
        assert scan.max_range == sim.params.sensors.sonar_max_range_m
        assert [landmark_reading_from_msg(m) for m in scan.landmarks] == list(frame.landmarks)
        received = [teammate_reading_from_msg(m) for m in scan.teammates]
        assert [r.robot_id for r in received] == [r.robot_id for r in frame.teammates]
        for got, expected in zip(received, frame.teammates):
            np.testing.assert_array_equal(got.relative_pose, expected.relative_pose)
            np.testing.assert_array_equal(got.covariance, expected.covariance)
        odometry = team.odometry[robot][frame.stamp_s]
        assert (odometry.header.frame_id, odometry.child_frame_id) == (
            f"robot_{robot}/odom", f"robot_{robot}/base_link")
        np.testing.assert_array_equal(odometry_pose(odometry), pose_through_wire(frame.odom_pose))
        np.testing.assert_array_equal(odometry_twist_covariance(odometry), frame.twist_covariance)
        truth = team.truth[robot][frame.stamp_s]
        assert truth.header.frame_id == "world"
        np.testing.assert_array_equal(odometry_pose(truth),
                                      pose_through_wire(sim.true_pose(robot)))


@pytest.fixture
def team():
    fake = FakeTeam(NUM_ROBOTS)
    yield fake
    fake.close()


def start_world(tmp_path: Path, seed: int, **settings: object) -> NodeProcess:
    params = dict(EXPLORATION, **{"run.seed": seed}, **settings)
    return NodeProcess.start_module(WORLD_MODULE, ros_args(params=params),
                                    log_path=tmp_path / "world.log")


def test_lockstep_waits_for_every_robot_and_matches_world_simulation(tmp_path, team):
    seed, last_step = 5, 8
    sim = WorldSimulation(local_params(seed))
    with start_world(tmp_path, seed, max_sim_time_s=last_step * 0.2,
                     robot_timeout_s=30.0) as world:
        team.wait_step(0, STARTUP_S)
        # Mission set-up: robot 0's launch pose in "map", the true landmarks under /world.
        wait_until(lambda: team.anchor is not None and team.landmarks is not None, STEP_S,
                   "anchor and landmarks", while_waiting=team.spin)
        anchor = team.anchor.pose
        assert team.anchor.header.frame_id == "map"
        np.testing.assert_allclose([anchor.position.x, anchor.position.y,
                                    quaternion_to_yaw(anchor.orientation)],
                                   sim.world.start_poses[0], atol=1e-12)
        truth_landmarks = landmark_positions_from_msg(team.landmarks)
        assert team.landmarks.header.frame_id == "world"
        assert sorted(truth_landmarks) == sorted(int(i) for i in sim.world.landmark_ids)
        for landmark_id, position in zip(sim.world.landmark_ids, sim.world.landmarks):
            np.testing.assert_array_equal(truth_landmarks[int(landmark_id)], position)
        assert_step_matches(team, sim, 0, [0, 0])

        # No step 1 until both robots answered step 0 (a command for a later step is ignored).
        team.answer(1, 3, 1.0, 0.0)
        team.spin_for(QUIET_S)
        team.answer(0, 0, *scripted_command(0, 0), team_sequence=7)
        team.spin_for(QUIET_S)
        assert 1 not in team.scans[0] and 1 not in team.scans[1]
        team.answer(1, 0, *scripted_command(1, 0), team_sequence=2)
        team.wait_step(1)
        for robot in range(NUM_ROBOTS):
            sim.apply_command(robot, *scripted_command(robot, 0))
        sim.advance()
        # The barrier carries each robot's team_sequence of the previous step.
        assert_step_matches(team, sim, 1, [7, 2])

        for step in range(1, last_step):
            for robot in range(NUM_ROBOTS):
                team.answer(robot, step, *scripted_command(robot, step), team_sequence=7 + step)
            team.wait_step(step + 1)
            for robot in range(NUM_ROBOTS):
                sim.apply_command(robot, *scripted_command(robot, step))
            sim.advance()
            assert_step_matches(team, sim, step + 1, [7 + step] * NUM_ROBOTS)
        # The clock followed the steps; max_sim_time_s ends the stepping at the last step.
        step_stamps = [sim_time_s(k, 0.2) for k in range(last_step + 1)]
        assert team.clock_stamps and set(team.clock_stamps) <= set(step_stamps)
        assert team.clock_stamps[-1] == step_stamps[-1]
        for robot in range(NUM_ROBOTS):
            team.answer(robot, last_step, 1.0, 0.0)
        team.spin_for(QUIET_S)
        assert last_step + 1 not in team.scans[0]
        assert world.running()
        assert "final step 8 reached" in world.output()


def test_silent_robot_gets_the_step_again_is_lost_and_rejoins(tmp_path, team):
    seed, timeout_s, resend_s = 9, 1.5, 0.4
    sim = WorldSimulation(local_params(seed))
    with start_world(tmp_path, seed, robot_timeout_s=timeout_s, step_resend_s=resend_s) as world:
        team.wait_step(0, STARTUP_S)
        assert_step_matches(team, sim, 0, [0, 0])
        for robot in range(NUM_ROBOTS):
            team.answer(robot, 0, *scripted_command(robot, 0), team_sequence=robot + 1)
        team.wait_step(1)
        for robot in range(NUM_ROBOTS):
            sim.apply_command(robot, *scripted_command(robot, 0))
        sim.advance()
        assert_step_matches(team, sim, 1, [1, 2])

        # Robot 1 falls silent on step 1: the world sends it the step again (the same
        # messages), then, after robot_timeout_s, goes on without it.
        asked = time.monotonic()
        team.answer(0, 1, *scripted_command(0, 1), team_sequence=5)
        team.wait_step(2, timeout_s + STEP_S)
        assert time.monotonic() - asked >= timeout_s * 0.9
        assert "robot 1 lost: no answer to step 1 in time" in world.output()
        assert team.scan_arrivals[1][1] >= 3   # sent, then re-sent every 0.4 s
        # ... each time after the step's /clock: a robot that was stopped missed the ticks
        # (best effort) and resumes only at a step the world's clock reached.
        assert team.clock_stamps.count(sim_time_s(1, 0.2)) >= 2
        sim.apply_command(0, *scripted_command(0, 1))
        sim.apply_command(1, 0.0, 0.0)
        sim.advance()
        assert_step_matches(team, sim, 2, [5, 2])

        # While lost it stands still and is not waited for.
        team.answer(0, 2, *scripted_command(0, 2), team_sequence=5)
        team.wait_step(3, STEP_S)
        sim.apply_command(0, *scripted_command(0, 2))
        sim.apply_command(1, 0.0, 0.0)
        sim.advance()
        assert_step_matches(team, sim, 3, [5, 2])

        # It answers again: it rejoins where its vehicle stopped and is waited for again.
        team.answer(1, 3, *scripted_command(1, 3), team_sequence=7)
        wait_until(lambda: "robot 1 rejoined at step 3" in world.output(), STEP_S,
                   "robot 1 rejoining", while_waiting=team.spin)
        team.spin_for(QUIET_S)
        assert 4 not in team.scans[0]  # robot 0 has not answered yet
        team.answer(0, 3, *scripted_command(0, 3), team_sequence=5)
        team.wait_step(4, STEP_S)
        for robot in range(NUM_ROBOTS):
            sim.apply_command(robot, *scripted_command(robot, 3))
        sim.advance()
        assert_step_matches(team, sim, 4, [5, 7])

        # Every robot finishes: the stepping ends.
        team.answer(0, 4, 0.0, 0.0, team_sequence=5, finished=True)
        team.answer(1, 4, 0.0, 0.0, team_sequence=7, finished=True)
        team.spin_for(QUIET_S * 2)
        assert 5 not in team.scans[0]
        assert "every robot finished or stopped" in world.output()
        assert world.running()
        assert world.stop() == 0
