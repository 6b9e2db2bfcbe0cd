"""The world's protocol without ROS (core/sessions/world_session.py): start-up, the lockstep
barrier with its re-sends and lost and rejoining robots, the relay's hand-over, the end of
the stepping. Wall times are given; nothing here sleeps."""
from __future__ import annotations

import dataclasses
from xml.etree import ElementTree

import numpy as np

from em_exploration_ros.core.links.link_model import Delivery
from em_exploration_ros.core.node_settings import REALTIME, WorldNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.sessions.effects import Level, LogLine
from em_exploration_ros.core.sessions.lockstep import StepAnswer
from em_exploration_ros.core.sessions.world_effects import (Dropped, PublishClock,
                                                            PublishLinkCounts, PublishSensors,
                                                            PublishStatus, PublishTruth,
                                                            StartTicking)
from em_exploration_ros.core.sessions.world_session import TeamConnections, WorldSession
from em_exploration_ros.core.world.simulation import WorldSimulation

from ros_process import REPO_ROOT

PARAMS = ExplorationParams().replace(world={"num_robots": 2, "width_m": 40.0, "height_m": 40.0,
                                            "num_landmarks": 6})
SETTINGS = WorldNodeSettings(robot_timeout_s=1.5, step_resend_s=0.4, liveliness_grace_s=0.8,
                             startup_settle_s=0.5, startup_timeout_s=5.0)
LEASE_S = 3.0
ALL = TeamConnections((True, True), (True, True), True)


def session(params: ExplorationParams = PARAMS, relayed: bool | None = None,
            **settings: object) -> WorldSession:
    return WorldSession(params, dataclasses.replace(SETTINGS, **settings), 0.0, LEASE_S,
                        relayed)


def started(world: WorldSession, now_s: float = 1.0) -> list:
    assert world.poll(now_s - SETTINGS.startup_settle_s, ALL) == []
    return world.poll(now_s, ALL)


def of(effects: list, kind: type) -> list:
    return [e for e in effects if type(e) is kind]


def lines(effects: list, level: Level | None = None) -> list[str]:
    return [e.text for e in of(effects, LogLine) if level is None or e.level == level]


def move(robot: int, step: int, sequence: int = 0, finished: bool = False,
         messages: int = 0) -> StepAnswer:
    return StepAnswer(1.0, 0.3 * (robot + 1) - 0.1 * step, sequence, finished, messages)


def test_start_waits_for_the_team_to_settle_and_publishes_step_0():
    world = session()
    # Not connected: nothing, until the start-up timeout.
    assert world.poll(0.5, TeamConnections((True, False), (True, False), True)) == []
    assert world.poll(1.0, ALL) == []          # connected from now: settles for 0.5 s
    assert world.poll(1.4, ALL) == []
    effects = world.poll(1.5, ALL)
    assert world.running and not world.stepping_over
    assert "all set after 1.5 s: stepping (lockstep)" in lines(effects)
    assert of(effects, PublishStatus) == [PublishStatus(0, 0.0, False, "stepping (lockstep)")]
    assert of(effects, PublishClock) == [PublishClock(0.0)]
    sensors = of(effects, PublishSensors)
    assert [s.robot for s in sensors] == [0, 1]
    assert all(s.team_sequences == (0, 0) and s.delivered is None for s in sensors)
    reference = WorldSimulation(PARAMS)
    for effect in sensors:
        frame = reference.sense(effect.robot)
        assert effect.frame.step == 0 and effect.frame.landmarks == frame.landmarks
        np.testing.assert_array_equal(effect.frame.odom_pose, frame.odom_pose)
    [truth] = of(effects, PublishTruth)
    np.testing.assert_array_equal(np.array(truth.poses), reference.world.start_poses)
    # The barrier is open: step 0 waits for both answers.
    assert world.barrier.step == 0 and world.barrier.waiting_for() == [0, 1]


def test_a_robot_not_started_by_the_timeout_is_lost_and_the_team_starts_without_it():
    world = session()
    late = TeamConnections((True, False), (False, False), False)
    assert world.poll(4.9, late) == []
    effects = world.poll(5.0, late)
    warnings = lines(effects, Level.WARN)
    assert warnings[0].startswith("robot 1 lost: not connected after 5 s (treated as stopped)")
    assert "the evaluator or the recorder does not listen yet; starting anyway" in warnings
    assert world.running and world.barrier.stopped == {1}
    # Only robot 0 is waited for; its answer closes the step.
    effects = world.on_command(0, 0, move(0, 0), 5.1)
    assert world.sim.step == 1 and [s.robot for s in of(effects, PublishSensors)] == [0, 1]


def test_a_silent_robot_gets_the_step_again_then_is_lost_then_rejoins():
    world = session()
    effects = started(world)
    step_0 = of(effects, PublishSensors)
    assert world.on_command(0, 0, move(0, 0, sequence=5), 1.1) == []
    # Robot 1 is silent: a re-send of the same messages after step_resend_s, /clock first.
    assert world.poll(1.3) == []
    resent = world.poll(1.4)
    assert resent == [PublishClock(0.0), step_0[1]]
    assert world.poll(1.5) == []
    assert world.poll(1.8) == [PublishClock(0.0), step_0[1]]
    # Given up after robot_timeout_s: a WARN line, and the step closes without it.
    effects = world.poll(2.5)
    assert lines(effects, Level.WARN) == [
        "robot 1 lost: no answer to step 0 in time; the team goes on without it (zero motion) "
        "until it answers again"]
    assert world.sim.step == 1
    step_1 = [e for e in of(effects, PublishSensors) if e.frame.step == 1]
    assert [e.team_sequences for e in step_1] == [(5, 0), (5, 0)]
    reference = WorldSimulation(PARAMS)
    reference.apply_command(0, move(0, 0).linear_x, move(0, 0).angular_z)
    reference.apply_command(1, 0.0, 0.0)  # the lost robot stands still
    reference.advance()
    np.testing.assert_array_equal(world.sim.true_pose(1), reference.true_pose(1))
    np.testing.assert_array_equal(world.sim.true_pose(0), reference.true_pose(0))
    # While lost it is not waited for.
    world.on_command(0, 1, move(0, 1, sequence=5), 2.6)
    assert world.sim.step == 2
    # It answers an earlier step: it rejoins and the open step waits for it again.
    effects = world.on_command(1, 1, move(1, 1, sequence=2), 2.7)
    assert lines(effects) == ["robot 1 rejoined at step 2 (answered step 1)"]
    world.on_command(0, 2, move(0, 2, sequence=6), 2.8)
    assert world.sim.step == 2 and world.barrier.waiting_for() == [1]
    effects = world.on_command(1, 2, move(1, 2, sequence=3), 2.9)
    assert world.sim.step == 3 and of(effects, PublishSensors)[1].team_sequences == (6, 3)


def test_a_robot_whose_liveliness_is_lost_gets_the_grace_only():
    world = session()
    started(world)
    assert lines(world.on_liveliness(1, False, False, 1.1), Level.WARN)[0].startswith(
        "robot 1: liveliness lost")
    world.on_command(0, 0, move(0, 0), 1.2)
    assert not lines(world.poll(1.8))  # re-sends only
    effects = world.poll(2.0)  # 1.1 + liveliness_grace_s passed
    assert lines(effects, Level.WARN)[0].startswith(
        "robot 1 lost: no answer to step 0 in time (liveliness lost)")
    assert world.sim.step == 1


def test_a_second_different_answer_is_dropped_and_commands_are_checked():
    world = session()
    started(world)
    world.on_command(0, 0, move(0, 0), 1.1)
    assert world.on_command(0, 0, move(0, 0, sequence=1), 1.2) == [Dropped(
        "a second, different answer of robot 0 to step 0: the first stands (another "
        "publisher on its topic?)")]
    assert world.command_problem(0, 1, 1.0, 0.0, 0) == "robot_id 1 on robot 0's topic"
    assert "exceeds" in world.command_problem(0, 0, 50.0, 0.0, 0)
    world.on_command(1, 0, move(1, 0, sequence=4), 1.3)
    assert world.sim.step == 1
    assert world.command_problem(1, 1, 1.0, 0.0, 3) == "team_sequence 3 is behind 4"
    assert world.command_problem(1, 1, 1.0, 0.0, 4) is None


def test_a_robot_never_seen_alive_is_suspect_a_lease_into_the_run():
    world = session(robot_timeout_s=30.0, step_resend_s=100.0)
    started(world)
    world.on_liveliness(0, True, False, 1.5)
    effects = world.poll(1.0 + LEASE_S)
    assert lines(effects, Level.WARN) == [
        "robot 1: no liveliness seen 3 s into the run; given 0.8 s to answer until it is"]
    assert world.barrier.suspects == {1}


def test_relay_mode_closes_a_step_only_once_every_counted_message_was_heard():
    world = session(relayed=True)
    effects = started(world)
    assert of(effects, PublishLinkCounts) and of(effects, PublishSensors)[0].delivered == (0, 0)
    world.on_command(1, 0, move(1, 0), 1.1)
    # Robot 0's answer counts one message on its update topic the relay has not heard.
    assert world.on_command(0, 0, move(0, 0, sequence=1, messages=1), 1.2) == []
    assert world.sim.step == 0
    effects = world.update_heard(0, 1, 120, "record 1 of robot 0", None, 1.3)
    assert world.sim.step == 1
    # Transmitted at step 0, delivered to the teammate before step 1, counted in its scan.
    assert of(effects, Delivery)[0].receiver == 1
    assert of(effects, Delivery)[0].frame.payload == "record 1 of robot 0"
    assert [s.delivered for s in of(effects, PublishSensors)] == [(0, 0), (1, 0)]
    # A counted message that never comes is waited for robot_timeout_s, once.
    world.on_command(1, 1, move(1, 1), 1.4)
    world.on_command(0, 1, move(0, 1, sequence=1, messages=2), 1.5)
    assert world.poll(2.9) == [] and world.sim.step == 1
    effects = world.poll(3.0)
    assert "step 1: team messages of robots [0] counted in their answers never reached " \
           "the relay; going on without them (not waited for again)" in lines(effects)
    assert world.sim.step == 2


def test_relay_requests_and_history_copies_are_checked():
    world = session(relayed=True)
    assert world.request_problem(0, 5, 1, 2, 255) == "robot ids 0 -> 5 are not robots of " \
                                                     "this team"
    assert world.request_problem(1, 1, 1, 0, 255) is None  # a restarted robot's own stream
    assert world.request_problem(0, 1, 1, 2, 255) is None
    assert world.history_problem(0, 0) == "a record of robot 0 is no teammate's of robot 0"
    assert world.history_problem(0, 1) is None


def test_stepping_ends_at_the_final_step():
    world = session(max_sim_time_s=0.4)
    started(world)
    for step in range(2):
        for robot in range(2):
            effects = world.on_command(robot, step, move(robot, step), 1.1 + step)
    assert world.sim.step == 2 and world.stepping_over and not world.polling
    assert of(effects, PublishStatus) == [PublishStatus(2, 0.4, True, "final step 2 reached")]
    assert any(line.startswith("stepping over at step 2") for line in lines(effects))
    assert world.on_command(0, 2, move(0, 2), 3.0) == []


def test_stepping_ends_when_every_robot_finished():
    world = session()
    started(world)
    world.on_command(0, 0, move(0, 0, finished=True), 1.1)
    effects = world.on_command(1, 0, move(1, 0, finished=True), 1.2)
    assert world.stepping_over and world.sim.step == 0
    assert of(effects, PublishStatus) == [
        PublishStatus(0, 0.0, True, "every robot finished or stopped")]


def test_a_lost_team_is_waited_for_lost_team_wait_s():
    world = session(lost_team_wait_s=10.0)
    started(world)
    effects = world.poll(2.5)  # both silent: both lost, the team is waited for
    assert any(line.startswith("every robot that has not finished is lost; waiting up to 10 s")
               for line in lines(effects, Level.WARN))
    assert not world.stepping_over and world.sim.step == 0
    world.poll(12.4)
    assert not world.stepping_over
    effects = world.poll(12.5)
    assert world.stepping_over and of(effects, PublishStatus) == [
        PublishStatus(0, 0.0, True, "every robot finished or stopped")]


def test_real_time_ticks_advance_with_the_latest_commands():
    world = session(clock_mode=REALTIME)
    effects = started(world)
    assert of(effects, StartTicking) == [StartTicking(0.2)]
    assert of(effects, PublishSensors)[0].team_sequences == ()
    world.on_command(0, 7, move(0, 0), 1.1)  # any step: the latest command counts
    world.tick(1.2)
    reference = WorldSimulation(PARAMS)
    reference.apply_command(0, 1.0, 0.3)
    reference.apply_command(1, 0.0, 0.0)
    reference.advance()
    assert world.sim.step == 1
    np.testing.assert_array_equal(world.sim.true_pose(0), reference.true_pose(0))


def test_the_start_up_settle_outlasts_the_team_profile_s_re_announcement_period():
    """em-world's settle covers a participant whose first announcements were missed: the
    team's Fast DDS profile (config/fastdds_profiles.xml, the default participant) announces
    again within it, and its first announcements span at least the settle (both are
    changed together or not at all)."""
    namespace = {"dds": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ElementTree.parse(REPO_ROOT / "config" / "fastdds_profiles.xml").getroot()
    participants = [p for p in root.iterfind("dds:participant", namespace)
                    if p.get("is_default_profile") == "true"]
    assert len(participants) == 1
    discovery = participants[0].find("dds:rtps/dds:builtin/dds:discovery_config", namespace)

    def seconds(element) -> float:
        return (float(element.findtext("dds:sec", namespaces=namespace))
                + float(element.findtext("dds:nanosec", namespaces=namespace)) * 1e-9)

    period_s = seconds(discovery.find("dds:leaseAnnouncement", namespace))
    initial = discovery.find("dds:initialAnnouncements", namespace)
    initial_span_s = (int(initial.findtext("dds:count", namespaces=namespace))
                      * seconds(initial.find("dds:period", namespace)))
    settle_s = WorldNodeSettings().startup_settle_s
    assert period_s < settle_s <= initial_span_s
