"""A robot's team protocol without ROS (core.sessions.robot_session.RobotSession): the
lockstep barrier and its timeout, a step sent again, a restart with journals and teammates'
copies, skip-ahead, the world gone, relay mode. Inputs are core data built from the
simulated world; effects are checked as returned."""
from __future__ import annotations

import dataclasses

from em_exploration_ros.core.links.link_model import FrameKind
from em_exploration_ros.core.node_settings import RobotNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import TeamUpdateOutbox
from em_exploration_ros.core.records.wire_model import pose_through_wire
from em_exploration_ros.core.sessions import robot_effects as fx
from em_exploration_ros.core.sessions.effects import Level, LogLine
from em_exploration_ros.core.sessions.robot_session import (JournalRecords, OdometryInput,
                                                            RobotSession, ScanInput)
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.core.world.simulation import WorldSimulation

PARAMS = ExplorationParams().replace(
    planner={"name": "NEAREST"}, world={"width_m": 50.0, "height_m": 50.0, "num_landmarks": 5},
    run={"seed": 3, "max_steps": 1500})
SETTINGS = RobotNodeSettings(barrier_timeout_s=1.0, request_period_s=0.5,
                             world_lost_timeout_s=120.0, rejoin_settle_s=1.0)


def feed(session: RobotSession, sim: WorldSimulation, step: int, now_s: float,
         barrier: tuple[int, ...] = (), delivered: tuple[int, int] = (0, 0),
         world_step: int | None = None) -> list:
    """Hand the session robot ``session.robot_id``'s odometry and scan of the world's
    current sensing, numbered ``step``; the effects of both."""
    frame = sim.sense(session.robot_id)
    world_step = step if world_step is None else world_step
    effects = session.odometry(step, OdometryInput(pose_through_wire(frame.odom_pose),
                                                   frame.twist_covariance), now_s, world_step)
    return effects + session.scan(ScanInput(step, (0, 0), frame.landmarks, frame.teammates,
                                            barrier, delivered), now_s, world_step)


def commands(effects: list) -> list[fx.SendCommand]:
    return [e for e in effects if isinstance(e, fx.SendCommand)]


def lines(effects: list, level: Level) -> list[str]:
    return [e.text for e in effects if isinstance(e, LogLine) and e.level == level]


def started(robot: int = 0, settings: RobotNodeSettings = SETTINGS, **options
            ) -> tuple[RobotSession, WorldSimulation]:
    sim = WorldSimulation(PARAMS)
    session = RobotSession(robot, PARAMS, settings, **options)
    effects = session.anchor(sim.world.start_poses[0], 0.0, 0)
    assert session.agent is not None and "map anchored" in lines(effects, Level.INFO)[0]
    return session, sim


def test_a_step_waits_for_the_barrier_asks_again_and_goes_on_after_the_timeout():
    session, sim = started(relay_mode=False)
    assert len(commands(feed(session, sim, 0, 0.0, barrier=(0, 0, 0)))) == 1
    # Step 1: the world's barrier names records 1..2 of robot 1, which never arrive.
    assert commands(feed(session, sim, 1, 0.1, barrier=(0, 2, 0))) == []
    assert session.tick(0.2, 1, None) == []                   # within the request period
    asked = session.tick(0.7, 1, None)
    assert fx.PublishRequest(1, 1, 2) in asked and commands(asked) == []
    timed_out = session.tick(1.2, 1, None)
    warning = lines(timed_out, Level.WARN)
    assert len(warning) == 1 and "step 1: teammates' updates robot 1 #1-2 still missing" in \
        warning[0] and "going on without them" in warning[0]
    assert [c.reply.step for c in commands(timed_out)] == [1]
    # Waived: the next step naming the same records is not held up again ...
    assert [c.reply.step for c in commands(feed(session, sim, 2, 1.3, (0, 2, 0)))] == [2]
    # ... but they are still asked for, until they arrive.
    assert fx.PublishRequest(1, 1, 2) in session.tick(1.9, 2, None)
    outbox = TeamUpdateOutbox(1)
    for record in (outbox.publish(0.0), outbox.publish(0.2)):
        session.team_update(record, 1, 2.0, 2)
    assert not any(isinstance(e, fx.PublishRequest) for e in session.tick(2.6, 2, None))


def test_a_step_the_world_sends_again_is_answered_with_the_same_command():
    session, sim = started()
    [answer] = commands(feed(session, sim, 0, 0.0, barrier=(0, 0, 0)))
    assert session.processed(0) and not session.processed(1)
    assert session.scan_again(0) == [dataclasses.replace(answer, again=True)]
    assert session.scan_again(1) == []
    # Its odometry again changes nothing.
    frame = sim.sense(0)
    assert session.odometry(0, OdometryInput(frame.odom_pose, frame.twist_covariance),
                            0.1, 0) == []


def test_a_restarted_robot_reads_its_journals_asks_for_its_stream_and_resumes():
    runner = TeamRunner(PARAMS)
    for _ in range(3 * PARAMS.slam.keyframe_interval_steps + 1):
        runner.step_once()
    own = runner.agents[1].outbox.resend(1, 0)
    team = runner.agents[0].outbox.resend(1, 0)
    assert len(own) >= 3 and team
    barrier = (len(team), len(own), 0)
    step = runner.simulation.step
    session = RobotSession(1, PARAMS, SETTINGS, relay_mode=False, journaled=True)
    session.anchor(runner.simulation.world.start_poses[0], 0.0, step)
    effects = feed(session, runner.simulation, step, 10.0, barrier=barrier)
    assert any(f"first step is {step}, not 0" in line for line in lines(effects, Level.WARN))
    assert effects[-1] == fx.ReadJournals() and commands(effects) == []
    # The journal lost the last record of its own stream; the team journal is whole.
    effects = session.journals_read(
        JournalRecords("stream journal", "robot_1.journal", None, own[:-1]),
        JournalRecords("team journal", "robot_1.team.journal", None, team), 10.1, step)
    assert fx.StartJournal(fx.Journal.TEAM, tuple(team), fresh=False) in effects
    assert effects[-1] == fx.PublishRequest(1, 1, 0)
    assert f"read {len(own) - 1} records of this robot's stream" in \
        lines(effects, Level.INFO)[0]
    assert commands(effects) == []
    # A teammate's copy of the missing record; after the settle time it resumes.
    assert session.own_history(own[-1]) == []
    assert commands(session.tick(10.5, step, None)) == []
    resumed = session.tick(11.2, step, None)
    assert fx.StartJournal(fx.Journal.OWN, tuple(own), fresh=False) in resumed
    assert any(f"rejoined: recovered {len(own)} records" in line
               for line in lines(resumed, Level.INFO))
    [answer] = commands(resumed)
    assert answer.reply.step == step and answer.reply.team_sequence >= len(own)
    assert session.agent.outbox.resend(1, len(own)) == own


def test_a_robot_the_world_went_on_without_skips_to_the_worlds_step():
    session, sim = started()
    feed(session, sim, 0, 0.0, barrier=(0, 0, 0))
    # Step 1's data is lost; step 5 arrives, but the world's clock is still at step 1.
    assert commands(feed(session, sim, 5, 1.0, barrier=(0, 0, 0), world_step=1)) == []
    effects = session.tick(1.1, 5, None)                      # the clock reached step 5
    assert any("resuming at step 5, 4 steps after step 1" in line
               for line in lines(effects, Level.WARN))
    assert [c.reply.step for c in commands(effects)] == [5]
    assert session.processed(4) and not session.processed(5 + 1)


def test_the_world_gone_for_the_timeout_ends_the_robot_with_code_4():
    session, _ = started()
    assert session.world_check_due(0.0)
    assert session.tick(0.0, 0, True) == []
    assert not session.world_check_due(0.5) and session.world_check_due(1.0)
    lost = session.tick(1.0, 0, False)
    assert "the world left the ROS graph" in lines(lost, Level.WARN)[0]
    assert session.tick(60.0, 0, False) == []
    gone = session.tick(121.0, 0, False)
    assert "exiting (code 4)" in lines(gone, Level.ERROR)[0]
    assert gone[-1] == fx.Exit(4)


def test_relay_mode_sends_frames_at_steps_and_waits_for_the_deliveries():
    session, sim = started(relay_mode=True)
    first = feed(session, sim, 0, 0.0)
    frames = [e.frame for e in first if isinstance(e, fx.SendFrame)]
    assert [f.kind for f in frames] == [FrameKind.UPDATE] and frames[0].sent_step == 0
    [answer] = commands(first)
    assert answer.reply.team_messages == 1 and answer.reply.team_sequence == 1
    assert first.index(answer) > first.index(next(e for e in first
                                                  if isinstance(e, fx.SendFrame)))
    # Step 1: the relay counts one record and one request delivered; neither is held yet.
    assert commands(feed(session, sim, 1, 0.1, delivered=(1, 1))) == []
    teammate = TeamUpdateOutbox(1).publish(0.0)
    assert commands(session.delivered_update(1, teammate, 1, 0.2, 1)) == []
    effects = session.delivered_request(1, 0, 1, 1, 1, 0.3, 1)   # robot 1 asks for record 1
    assert [c.reply.step for c in commands(effects)] == [1]
    resent = [e.frame for e in effects if isinstance(e, fx.SendFrame)]
    assert [(f.kind, f.key, f.sent_step, f.payload.robot_id) for f in resent] == \
        [(FrameKind.RESEND, 1, 1, 0)]
    for step in range(2, 6):
        effects = feed(session, sim, step, 0.1 * step, delivered=(1, 1))
        assert len(commands(effects)) == 1
    # Nothing is published outside steps, and no request goes to the shared topic.
    assert session.tick(5.0, 11, None) == []
