"""Rejoining after a restart: teammates keep a robot's stream, the restarted robot takes it
back and continues it (core: StreamArchive, OwnHistoryRecovery, RobotAgent.resume); and a
robot the world went on without skips to the world's step (step_to_resume_at,
RobotAgent.skip_steps)."""
from __future__ import annotations

import numpy as np
import pytest

from em_exploration_ros.core.agent.rejoin import (OwnHistoryRecovery, StreamArchive,
                                                  keyframe_ranges, records_beyond_the_team,
                                                  step_to_resume_at)
from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import (InvalidTeamUpdate, TeamUpdate,
                                                       TeamUpdateInbox, TeamUpdateOutbox)
from em_exploration_ros.core.records.wire_model import (pose_through_wire,
                                                        twist_to_increment_covariance)
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.core.world.sensors import odometry_covariance_per_step
from em_exploration_ros.core.world.simulation import SensorFrame

PARAMS = ExplorationParams().replace(
    planner={"name": "NEAREST"}, world={"width_m": 50.0, "height_m": 50.0, "num_landmarks": 5},
    run={"seed": 3, "max_steps": 1500})


def stream(robot: int, count: int):
    outbox = TeamUpdateOutbox(robot)
    return [outbox.publish(float(i)) for i in range(count)]


def test_archive_keeps_teammates_streams_in_order():
    archive = StreamArchive(own_robot_id=0, num_robots=3)
    one, two = stream(1, 3), stream(2, 2)
    assert archive.keep([one[0], two[0], one[1]]) == [one[0], two[0], one[1]]
    # a repeated record is not kept twice; what was filed comes back (for the team journal)
    assert archive.keep([one[1], two[1], one[2]]) == [two[1], one[2]]
    assert archive.held(1) == one and archive.held(2) == two
    assert archive.held(0) == [] and archive.held(7) == []


def test_journaled_records_beyond_the_teams_copy_are_another_runs():
    """The same mission run again into the same folder leaves journals of the same identity:
    more of a robot's stream than the team holds (+1 the world has not counted yet) cannot
    be this run's. (A full disk kept an earlier run's 42 records where a restarted robot
    read them as its own, with the team at 27.)"""
    records = stream(1, 42) + stream(2, 3)
    assert "42 records of robot 1, more than the 27" in records_beyond_the_team(records,
                                                                                [0, 27, 3])
    assert records_beyond_the_team(records, [0, 41, 2]) is None      # one not counted yet
    assert "3 records of robot 2, more than the 1" in records_beyond_the_team(records,
                                                                               [0, 42, 1])


def test_recovery_waits_for_the_needed_records_then_settles():
    records = stream(1, 4)
    recovery = OwnHistoryRecovery(1, 3, needed_sequence=3, started_s=0.0, settle_s=1.0,
                                  give_up_s=20.0)
    with pytest.raises(InvalidTeamUpdate):
        recovery.receive(stream(2, 1)[0])
    assert recovery.receive(records[1]) and recovery.receive(records[0])
    assert not recovery.receive(records[0])
    assert recovery.history() == records[:2] and recovery.short_of == 1
    assert not recovery.complete(5.0)
    recovery.receive(records[3])
    recovery.receive(records[2])
    assert recovery.history() == records and recovery.short_of == 0
    assert not recovery.complete(0.5) and recovery.complete(1.0)
    lonely = OwnHistoryRecovery(1, 3, needed_sequence=2, started_s=0.0, settle_s=1.0,
                                give_up_s=20.0)
    assert not lonely.complete(19.9) and lonely.complete(20.0) and lonely.short_of == 2


def test_a_restarted_robot_gets_back_the_records_the_barrier_held_back():
    """Robot 1 published records 4 and 5, then died before the world counted them: its
    barrier entry stayed 3 (seen in a 200 m run: a robot lost to the world published while
    it caught up, and was restarted). Robot 0 holds 4 and 5 back for the barrier. Served
    only the records it had applied, the new process numbered its next record 4, and robot
    0 dropped that as a duplicate of the old 4, and with it the new process's first
    keyframe, which every later one chains from."""
    old = stream(1, 5)
    inbox, archive = TeamUpdateInbox(0, 3), StreamArchive(own_robot_id=0, num_robots=3)
    for update in old:
        inbox.receive(update)
    archive.keep(inbox.pop_ready({1: 3, 2: 0}))
    assert inbox.held_back(1) == old[3:] and inbox.held_back(2) == [] and inbox.held_back(0) == []
    served = archive.held(1) + inbox.held_back(1)
    assert served == old
    recovery = OwnHistoryRecovery(1, 3, needed_sequence=3, started_s=0.0, settle_s=1.0,
                                  give_up_s=20.0)
    for update in served:
        recovery.receive(update)
    assert recovery.complete(1.0) and recovery.history() == old
    outbox = TeamUpdateOutbox(1)
    outbox.restore(recovery.history(), through_sequence=3)
    assert inbox.receive(outbox.publish(9.0))  # sequence 6: new to robot 0
    applied_only = TeamUpdateOutbox(1)
    applied_only.restore(archive.held(1), through_sequence=3)
    assert not inbox.receive(applied_only.publish(9.0))  # 4: taken for the old record 4


def test_outbox_restore_continues_numbering_and_refuses_a_gap():
    records = stream(1, 3)
    outbox = TeamUpdateOutbox(1)
    outbox.restore(records)
    assert outbox.last_sequence == 3 and outbox.resend(2, 0) == records[1:]
    assert outbox.publish(9.0).sequence == 4
    with pytest.raises(ValueError):
        TeamUpdateOutbox(1).restore([records[0], records[2]])


def test_outbox_restore_numbers_after_records_no_teammate_gave_back():
    records = stream(1, 2)
    outbox = TeamUpdateOutbox(1)
    outbox.restore(records, through_sequence=5)
    assert outbox.last_sequence == 5 and outbox.resend(1, 2) == records
    empty = outbox.resend(3, 5)
    assert [u.sequence for u in empty] == [3, 4, 5]
    assert all(u.robot_id == 1 and u.stamp_s == records[-1].stamp_s and not u.keyframes
               and not u.targets and not u.rendezvous for u in empty)
    assert outbox.publish(9.0).sequence == 6


def test_keyframe_ranges():
    assert keyframe_ranges(np.array([0, 1, 2, 5, 6, 9])) == "6 [0-2 5-6 9-9]"
    assert keyframe_ranges(np.array([], dtype=int)) == "0 []"


def crashed_team(robot: int = 1) -> tuple[TeamRunner, RobotAgent]:
    """A team whose robot ``robot`` crashed between two keyframes (the motion since is
    unrecorded) and stood still for a while; returns the runner and its crashed agent."""
    runner = TeamRunner(PARAMS)
    interval = PARAMS.slam.keyframe_interval_steps
    for _ in range(12 * interval + 3):
        runner.step_once()
    sim = runner.simulation
    for _ in range(2 * interval + 4):     # downtime: the vehicle stands still
        for vehicle in range(PARAMS.world.num_robots):
            sim.apply_command(vehicle, 0.0, 0.0)
        sim.advance()
    return runner, runner.agents[robot]


def step_input(frame: SensorFrame, time_step_s: float) -> StepInput:
    """A world sensor frame as a RobotAgent's step takes it, through the wire's numbers (what
    a robot's session hands its agent)."""
    return StepInput(frame.step, frame.stamp_s, pose_through_wire(frame.odom_pose),
                     twist_to_increment_covariance(frame.twist_covariance, time_step_s),
                     frame.landmarks, frame.teammates)


def step_to_next_keyframe(agent: RobotAgent, runner: TeamRunner) -> TeamUpdate:
    """Step robot ``agent`` (the vehicle standing still) up to its next keyframe; the update
    carrying it."""
    sim, interval = runner.simulation, PARAMS.slam.keyframe_interval_steps
    robot = agent.robot_id
    while sim.step % interval:
        agent.step(step_input(sim.sense(robot), PARAMS.motion.time_step_s))
        sim.apply_command(robot, 0.0, 0.0)
        sim.advance()
    agent.step(step_input(sim.sense(robot), PARAMS.motion.time_step_s))
    return agent.take_outgoing()


def test_a_robot_resumes_at_the_newest_complete_step_the_worlds_clock_reached():
    assert step_to_resume_at(10, [], 500) is None             # nothing later held: wait
    assert step_to_resume_at(10, [10], 500) is None           # the awaited step itself
    assert step_to_resume_at(10, [300, 450, 451], 500) == 451
    assert step_to_resume_at(10, [300, 450, 900], 500) == 450  # 900: not the world's yet
    assert step_to_resume_at(10, [900], 500) is None


def test_a_robot_that_skipped_steps_links_them_with_one_moving_steps_covariance():
    """Robot 1 stopped answering after a moving step and the world held its vehicle still:
    the next keyframe's odometry gets that one step's covariance on top of what the still
    steps' readings (exact) carry, and the estimate stays with the vehicle."""
    interval = PARAMS.slam.keyframe_interval_steps
    skipped_runner, skipped = crashed_team()
    plain_runner, plain = crashed_team()
    skipped.skip_steps()
    with_skip = step_to_next_keyframe(skipped, skipped_runner).keyframes[0]
    without = step_to_next_keyframe(plain, plain_runner).keyframes[0]
    assert with_skip.index == without.index == skipped_runner.simulation.step // interval
    assert with_skip.previous_index == with_skip.index - 3
    motion = PARAMS.motion
    per_step = odometry_covariance_per_step(motion.speed_mps * motion.time_step_s, True,
                                            PARAMS.sensors)
    np.testing.assert_allclose(np.diag(with_skip.odom_covariance - without.odom_covariance),
                               np.diag(per_step), rtol=1e-6)
    sim = skipped_runner.simulation
    assert np.linalg.norm(skipped.current_pose()[:2] - sim.true_pose(1)[:2]) < 1.0


def test_restarted_agent_resumes_its_stream_graph_and_odometry():
    runner, old = crashed_team()
    sim, interval = runner.simulation, PARAMS.slam.keyframe_interval_steps
    history = old.outbox.resend(1, 0)
    old_indices, old_poses = old.slam.trajectory(1)

    new = RobotAgent(1, PARAMS, sim.world.start_poses[0])
    new.resume(history, old.outbox.last_sequence, sim.step)
    # Its teammates' streams come back through the ordinary re-send protocol.
    new.apply_team_updates([update for robot in (0, 2)
                            for update in runner.agents[robot].outbox.resend(1, 0)])
    indices, poses = new.slam.trajectory(1)
    np.testing.assert_array_equal(indices, old_indices)
    np.testing.assert_allclose(poses, old_poses, atol=0.05)
    assert new.outbox.last_sequence == old.outbox.last_sequence
    assert [d.decision_index for d in new.decisions] == [d.decision_index for d in old.decisions]
    assert [t.position.tolist() for t in new.team_targets[1]] == \
        [t.position.tolist() for t in old.team_targets[1]]

    # The first keyframe after the restart links to the last one before the crash, and the
    # robot knows where it stands.
    update = step_to_next_keyframe(new, runner)
    assert update.sequence == old.outbox.last_sequence + 1
    keyframe = update.keyframes[0]
    assert not keyframe.is_first and keyframe.previous_index == int(old_indices[-1])
    assert keyframe.index == sim.step // interval
    assert np.linalg.norm(new.current_pose()[:2] - sim.true_pose(1)[:2]) < 1.0


def test_an_agent_resumed_without_its_latest_records_numbers_after_them_and_bridges_the_gap():
    """Under poor links its teammates may give back only the start of a restarted robot's
    stream. It must not number new records with sequence numbers its earlier process used
    (the world refused its commands as behind its barrier entry until the new numbers
    caught up, and teammates took them for duplicates), and the motion from its last
    recovered keyframe, measured by the dead reckoning, needs the odometry covariance of
    all those steps, not of one keyframe interval."""
    runner, old = crashed_team()
    sim, interval = runner.simulation, PARAMS.slam.keyframe_interval_steps
    history = old.outbox.resend(1, 0)
    kept = [u for u in history if u.sequence <= 3]
    last_kept = max(k.index for u in kept for k in u.keyframes)
    assert last_kept < max(old.slam.trajectory(1)[0]) - 5  # many keyframes are missing

    new = RobotAgent(1, PARAMS, sim.world.start_poses[0])
    new.resume(kept, old.outbox.last_sequence, sim.step)
    new.apply_team_updates([update for robot in (0, 2)
                            for update in runner.agents[robot].outbox.resend(1, 0)])
    assert new.outbox.last_sequence == old.outbox.last_sequence
    update = step_to_next_keyframe(new, runner)
    assert update.sequence == old.outbox.last_sequence + 1
    keyframe = update.keyframes[0]
    assert keyframe.previous_index == last_kept
    motion = PARAMS.motion
    per_step = odometry_covariance_per_step(motion.speed_mps * motion.time_step_s, True,
                                            PARAMS.sensors)
    bridged = keyframe.index * interval - last_kept * interval
    assert np.all(np.diag(keyframe.odom_covariance) >= np.diag(per_step) * (bridged - interval))
    # The dead reckoning measured the unrecorded motion: the robot still knows where it is.
    assert np.linalg.norm(new.current_pose()[:2] - sim.true_pose(1)[:2]) < 1.0


def test_robot_0_resumed_with_none_of_its_records_continues_its_stream_from_the_start():
    """Teammates out of range gave back none of robot 0's records (seen in a relay-mode run
    with three kills: the team's SLAM diverged to 40 m RMSE and the mission stalled). Its
    next keyframe must not start a new stream: robot 0's first keyframe is anchored at the
    mission's start pose, far from where the vehicle is now. It continues from its first
    keyframe, which the teammates hold, with the dead reckoning of every step since."""
    runner, old = crashed_team(robot=0)
    sim, interval = runner.simulation, PARAMS.slam.keyframe_interval_steps
    new = RobotAgent(0, PARAMS, sim.world.start_poses[0])
    new.resume([], old.outbox.last_sequence, sim.step)
    new.apply_team_updates([update for robot in (1, 2)
                            for update in runner.agents[robot].outbox.resend(1, 0)])
    update = step_to_next_keyframe(new, runner)
    assert update.sequence == old.outbox.last_sequence + 1
    keyframe = update.keyframes[0]
    assert not keyframe.is_first and keyframe.previous_index == 0
    # Record 1 is rebuilt with that first keyframe for a teammate that lost its copy too.
    assert [k.index for k in new.outbox.resend(1, 1)[0].keyframes] == [0]
    assert [u.keyframes for u in new.outbox.resend(2, old.outbox.last_sequence)] == [()] * (
        old.outbox.last_sequence - 1)
    motion = PARAMS.motion
    per_step = odometry_covariance_per_step(motion.speed_mps * motion.time_step_s, True,
                                            PARAMS.sensors)
    bridged = keyframe.index * interval
    assert np.all(np.diag(keyframe.odom_covariance) >= np.diag(per_step) * (bridged - interval))
    true_position = sim.true_pose(0)[:2]
    assert np.linalg.norm(sim.world.start_poses[0][:2] - true_position) > 5.0  # it moved
    assert np.linalg.norm(new.current_pose()[:2] - true_position) < 2.0
    # A teammate that holds robot 0's whole earlier stream takes the new keyframe where the
    # vehicle is, without a jump of its graph.
    teammate = runner.agents[1]
    teammate.apply_team_updates([update])
    estimate = teammate.slam.pose(0, keyframe.index)
    assert np.linalg.norm(estimate[:2] - true_position) < 2.0


def test_a_robot_restarted_before_the_world_counted_any_record_continues_from_keyframe_0():
    """A robot wedged at the start (its process never answered a step the world counted)
    and restarted later recovered no record and had none to number after. Its next keyframe
    started a new stream, and a robot other than 0 anchors a first keyframe only through a
    teammate's reading at the same keyframe index: it stayed unanchored and stood still for
    the rest of the mission (seen in separate-host runs with wedged robots). It continues
    from keyframe 0 at the odometry origin, which its teammates' readings of it anchor."""
    runner, _ = crashed_team(robot=2)
    sim, interval = runner.simulation, PARAMS.slam.keyframe_interval_steps
    new = RobotAgent(2, PARAMS, sim.world.start_poses[0])
    new.resume([], 0, sim.step)
    new.apply_team_updates([update for robot in (0, 1)
                            for update in runner.agents[robot].outbox.resend(1, 0)])
    update = step_to_next_keyframe(new, runner)
    keyframe = update.keyframes[0]
    assert not keyframe.is_first and keyframe.previous_index == 0
    assert update.sequence == 2 and [k.index for k in new.outbox.resend(1, 1)[0].keyframes] == [0]
    motion = PARAMS.motion
    per_step = odometry_covariance_per_step(motion.speed_mps * motion.time_step_s, True,
                                            PARAMS.sensors)
    bridged = keyframe.index * interval
    assert np.all(np.diag(keyframe.odom_covariance) >= np.diag(per_step) * (bridged - interval))
    assert np.linalg.norm(new.current_pose()[:2] - sim.true_pose(2)[:2]) < 2.0


def test_a_robot_whose_graph_ties_nothing_to_the_map_counts_its_steps_without_a_pose():
    """Restarted with none of its records while no teammate's records had come back yet
    (as when the whole team was restarted): nothing ties robot 2's stream to the map, so it
    has no pose and stands still; ``steps_unanchored`` counts those steps (the node warns
    on it), and a teammate's reading of it ends the count."""
    runner, _ = crashed_team(robot=2)
    sim = runner.simulation
    new = RobotAgent(2, PARAMS, sim.world.start_poses[0])
    new.resume([], 0, sim.step)
    for _ in range(3):
        command = new.step(step_input(sim.sense(2), PARAMS.motion.time_step_s))
        sim.apply_command(2, 0.0, 0.0)
        sim.advance()
    assert new.current_pose() is None and new.steps_unanchored == 3
    assert (command.turn_rad, command.forward_m) == (0.0, 0.0)
    new.apply_team_updates([update for robot in (0, 1)
                            for update in runner.agents[robot].outbox.resend(1, 0)])
    step_to_next_keyframe(new, runner)
    assert new.current_pose() is not None and new.steps_unanchored == 0
