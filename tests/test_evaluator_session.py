"""EvaluatorSession without ROS: the outside observer's protocol, input by input.

The session is driven as em-evaluator drives it (true landmarks, true poses per step,
stamped estimates, commands, liveliness, ticks of wall time) and its effects are checked:
truth recorded in order and metrics at the interval, finishing only once the update
streams are complete, the exit codes of a lost team (5) and of a silent world (3), and a
summary with every key of em-sim's.
"""
from __future__ import annotations

import dataclasses
from dataclasses import asdict
from typing import Any

import numpy as np
from ros_process import REPO_ROOT
from summary_keys import key_paths

from em_exploration_ros.core.evaluation.association_stats import (association_line,
                                                                  team_association)
from em_exploration_ros.core.evaluation.run_monitor import EXIT_ROBOTS_LOST
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, MeetingEntry, check_summary
from em_exploration_ros.core.node_settings import EvaluatorNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.core.records.readings import (UNIDENTIFIED, KeyframeMeasurements,
                                                      LandmarkReading)
from em_exploration_ros.core.records.team_data import (FrontierType, MissingRange,
                                                     TargetRecord, TeamUpdate)
from em_exploration_ros.core.records.wire_model import seconds_to_nanoseconds, sim_time_s
from em_exploration_ros.core.sessions.effects import Dropped, Level, LogLine
from em_exploration_ros.core.sessions.evaluator_effects import (CommandReport, Finished,
                                                                KeepSoFar, PublishMetrics,
                                                                RequestUpdates)
from em_exploration_ros.core.sessions.evaluator_session import (EVALUATOR_LOST_PREFIX,
                                                                EXIT_SILENCE, SO_FAR_INTERVAL_S,
                                                                EvaluatorSession)
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.core.slam.team_slam import owned_landmark_id
from em_exploration_ros.core.world.sensors import CLUTTER

PARAMS = ExplorationParams().replace(
    world={"num_robots": 2, "width_m": 40.0, "height_m": 40.0, "num_landmarks": 2},
    run={"seed": 1, "max_steps": 100})
STEP_S = PARAMS.motion.time_step_s
KEYFRAME_STEPS = PARAMS.slam.keyframe_interval_steps
#: Evaluations every 4 steps; the team waits 5 wall seconds for estimates and streams.
SETTINGS = EvaluatorNodeSettings(metrics_interval_s=4 * STEP_S, estimate_wait_s=5.0,
                                 silence_timeout_s=60.0, liveliness_grace_s=2.0)
WORLD_NODE = "em_world"


def started(settings: EvaluatorNodeSettings = SETTINGS) -> EvaluatorSession:
    session = EvaluatorSession(PARAMS, settings, 0.0, 3.0, WORLD_NODE)
    assert session.true_landmarks([7, 3], np.array([[10.0, 10.0], [30.0, 30.0]]), 0.5,
                                  0.0) == []
    return session


def stamp_ns(step: int) -> int:
    return seconds_to_nanoseconds(sim_time_s(step, STEP_S))


def pose(robot: int, step: int) -> np.ndarray:
    return np.array([5.0 + 0.1 * step, 5.0 + 10.0 * robot, 0.0])


def truth(session: EvaluatorSession, step: int, wall_s: float = 0.0) -> list[Any]:
    effects = []
    for robot in range(PARAMS.world.num_robots):
        effects += session.true_pose(robot, step, pose(robot, step), wall_s)
    return effects


def estimates(session: EvaluatorSession, step: int, wall_s: float = 0.0) -> list[Any]:
    """Every robot's estimates of keyframe ``step`` (its true path so far, no landmarks)."""
    effects = []
    keyframes = np.arange(0, step + 1, KEYFRAME_STEPS)
    for robot in range(PARAMS.world.num_robots):
        stamps = np.array([sim_time_s(k, STEP_S) for k in keyframes])
        poses = np.array([pose(robot, k) for k in keyframes])
        effects += session.path_estimate(robot, stamp_ns(step), stamps, poses, wall_s)
        effects += session.landmark_estimate(robot, stamp_ns(step), {}, wall_s)
    return effects


def command(robot: int, step: int, sequence: int = 0, finished: bool = False,
            **fields: Any) -> CommandReport:
    return CommandReport(robot, step, stamp_ns(step), finished, sequence, 0.0, 0, **fields)


def update(robot: int, sequence: int, step: int) -> TeamUpdate:
    target = TargetRecord(robot, sequence - 1, sim_time_s(step, STEP_S), np.array([1.0, 2.0]),
                          FrontierType.EXPLORATION, None, 0.01)
    return TeamUpdate(robot, sequence, sim_time_s(step, STEP_S), targets=(target,))


def of(effects: list[Any], kind: type) -> list[Any]:
    return [effect for effect in effects if isinstance(effect, kind)]


def test_truth_is_recorded_in_order_and_metrics_come_at_the_interval():
    session = started()
    for robot in range(2):
        session.liveliness(robot, True, False, 0.0)
    # A step is recorded once every robot's true pose is in, and steps only go forward.
    assert session.true_pose(0, 0, pose(0, 0), 0.0) == [] and session.recorded_step == -1
    assert session.true_pose(1, 0, pose(1, 0), 0.0) == [] and session.recorded_step == 0
    assert truth(session, 1) == [] and session.recorded_step == 1
    assert of(truth(session, 1), Dropped) == [Dropped("step 1 is stale (next expected 2)")] * 2
    assert of(truth(session, 0), Dropped) == [Dropped("step 0 is stale (next expected 2)")] * 2
    assert truth(session, 2) + truth(session, 3) == []
    # Step 4 is an evaluation step: it waits for the estimates of keyframe 0 (as of step 3).
    assert truth(session, 4, wall_s=1.0) == []
    published = of(estimates(session, 0, wall_s=1.5), PublishMetrics)
    assert [p.metrics.stamp_s for p in published] == [sim_time_s(4, STEP_S)]
    distance = sum(np.linalg.norm(pose(r, 4)[:2] - pose(r, 0)[:2]) for r in range(2))
    assert published[0].metrics.distance_m == distance
    assert published[0].metrics.loc_rmse_m == 0.0
    # Later estimates stamped at a step that is not a keyframe step are dropped.
    assert of(session.path_estimate(0, stamp_ns(1), np.zeros(1), np.zeros((1, 3)), 2.0),
              Dropped) == [Dropped("step 1 is not a keyframe step")]
    # An evaluation whose estimates never come goes on after estimate_wait_s, and says so.
    late = (KEYFRAME_STEPS // 4 + 1) * 4  # the first evaluation after keyframe 1
    effects = []
    for step in range(5, late + 1):
        effects += truth(session, step, wall_s=3.0)
    assert len(of(effects, PublishMetrics)) == late // 4 - 2
    assert session.tick(4.0, True, frozenset({WORLD_NODE})) == []
    effects = session.tick(8.5, True, frozenset({WORLD_NODE}))
    assert [p.metrics.stamp_s for p in of(effects, PublishMetrics)] == [
        sim_time_s(late, STEP_S)]
    assert any("with older estimates of robots [0, 1]" in line.text
               for line in of(effects, LogLine)), effects


def test_finishing_waits_for_complete_update_streams_and_the_last_commands():
    session = started(EvaluatorNodeSettings(metrics_interval_s=4 * STEP_S, estimate_wait_s=5.0,
                                            max_sim_time_s=4 * STEP_S))
    for step in range(4):
        truth(session, step)
        for robot in range(2):
            session.command(robot, command(robot, step, sequence=2 if robot == 0 else 0), 0.0)
    estimates(session, 0)
    # The final step's evaluation stops the run; robot 0 reported 2 updates, none arrived.
    effects = truth(session, 4, wall_s=1.0)
    assert of(effects, PublishMetrics) and not of(effects, Finished)
    assert of(effects, RequestUpdates) == [RequestUpdates((MissingRange(0, 1, 2),))]
    assert session.team_update(0, update(0, 1, 2), 1.5) == []
    effects = session.team_update(0, update(0, 2, 3), 2.0)
    finished = of(effects, Finished)
    assert len(finished) == 1 and finished[0].exit_code == 0
    summary = finished[0].summary
    assert summary.stop_reason.startswith("final step 4") and summary.decisions == 2
    assert [len(r.targets) for r in summary.robots] == [2, 0]
    assert session.tick(3.0, True, frozenset({WORLD_NODE})) == []  # the run is over


def test_streams_that_never_complete_are_waited_for_estimate_wait_s_then_named():
    session = started(EvaluatorNodeSettings(metrics_interval_s=4 * STEP_S, estimate_wait_s=5.0,
                                            max_sim_time_s=4 * STEP_S))
    for step in range(4):
        truth(session, step)
        for robot in range(2):
            session.command(robot, command(robot, step, sequence=1 if robot == 1 else 0), 0.0)
    estimates(session, 0)
    assert not of(truth(session, 4, wall_s=1.0), Finished)
    assert not of(session.tick(5.9, True, frozenset({WORLD_NODE})), Finished)
    effects = session.tick(6.1, True, frozenset({WORLD_NODE}))
    assert len(of(effects, Finished)) == 1
    assert any("without team updates that never arrived: robot 1 #1-1" in line.text
               for line in of(effects, LogLine))


def test_a_lost_robot_and_every_live_robot_finished_end_the_run_with_exit_5():
    session = started()
    session.liveliness(0, True, False, 0.1)
    session.liveliness(1, True, False, 0.1)
    for step in range(3):
        truth(session, step, wall_s=0.5)
    estimates(session, 0, wall_s=0.5)
    session.liveliness(1, False, False, 1.0)
    lost = session.tick(3.5, True, frozenset({WORLD_NODE}))  # after the 2 s grace
    assert any("robot 1 lost: no liveliness for 2 s" in line.text for line in of(lost, LogLine))
    assert session.liveness.status(1) == "lost"
    # Robot 0 finishes at step 2, whose truth is in: the run ends at that step.
    effects = []
    for step in range(3):
        effects += session.command(0, command(0, step, finished=step == 2), 3.6)
    finished = of(effects, Finished)
    assert len(finished) == 1 and finished[0].exit_code == EXIT_ROBOTS_LOST
    assert finished[0].summary.stop_reason == "every live robot finished; robots [1] lost"
    assert [r.status for r in finished[0].summary.robots] == ["finished", "lost"]


def test_the_worlds_silence_ends_the_run_with_exit_3_and_the_summary_so_far():
    session = started()
    for step in range(3):
        truth(session, step, wall_s=1.0)
    assert not of(session.tick(60.5, True, frozenset({WORLD_NODE})), Finished)
    effects = session.tick(61.5, False, frozenset())
    assert any("the world left the ROS graph" in line.text for line in of(effects, LogLine))
    finished = of(effects, Finished)
    assert len(finished) == 1 and finished[0].exit_code == EXIT_SILENCE
    summary = finished[0].summary
    assert summary.stop_reason == "no ground truth for 60 s (world or robots stopped)"
    assert summary.sim_time_s == sim_time_s(2, STEP_S)  # the last complete step, evaluated


def test_the_summary_so_far_is_kept_at_evaluations_every_few_wall_seconds():
    """What an evaluator killed mid-run leaves (issue 40, point 3): the summary of its latest
    evaluations, marked "evaluator lost: ...", at most every SO_FAR_INTERVAL_S wall seconds;
    em-sim's observer (``keep_so_far`` False) keeps none."""
    session = EvaluatorSession(PARAMS, SETTINGS, 0.0, 3.0, WORLD_NODE, keep_so_far=True)
    session.true_landmarks([7, 3], np.array([[10.0, 10.0], [30.0, 30.0]]), 0.5, 0.0)
    kept, published = [], []
    for step in range(13):
        wall_s = 0.15 * step * SO_FAR_INTERVAL_S  # evaluations at steps 4, 8, 12
        effects = truth(session, step, wall_s)
        if step % KEYFRAME_STEPS == 0:
            effects += estimates(session, step, wall_s)
        kept += of(effects, KeepSoFar)
        published += of(effects, PublishMetrics)
    assert len(published) == 3
    # The first evaluation (at 0.6 intervals of wall time) and the third (1.8) are kept.
    assert [k.summary.sim_time_s for k in kept] == [sim_time_s(4, STEP_S),
                                                    sim_time_s(12, STEP_S)]
    latest = kept[-1].summary
    assert latest.stop_reason == (f"{EVALUATOR_LOST_PREFIX}the run so far, to t = "
                                  f"{sim_time_s(12, STEP_S):g} s (the evaluator ended before "
                                  f"the run)")
    assert len(latest.history) == 3 and check_summary(latest.to_dict()) == []
    assert session.exit_code is None and not session.monitor.stop_reason
    without = started()
    for step in range(5):
        assert of(truth(without, step) + estimates(without, 0), KeepSoFar) == []


def test_a_world_that_stepped_over_ends_the_run_once_only_it_says_so():
    session = started()
    for step in range(3):
        truth(session, step, wall_s=1.0)
    assert session.world_status(2, 2, True, "every robot finished or stopped")[0].text == \
        "the world stepped over at step 2 (every robot finished or stopped)"
    forged = session.tick(7.0, True, frozenset({WORLD_NODE, "forger"}))
    assert any("not trusted" in line.text for line in of(forged, LogLine))
    assert not of(forged, Finished)
    finished = of(session.tick(7.0, True, frozenset({WORLD_NODE})), Finished)
    assert len(finished) == 1 and finished[0].exit_code == EXIT_SILENCE


def test_the_summary_of_a_short_scripted_run_has_every_key_of_em_sims():
    session = started(EvaluatorNodeSettings(metrics_interval_s=4 * STEP_S,
                                            max_sim_time_s=4 * STEP_S))
    given_up = GivenUpEntry(3.0, 4.0, sim_time_s(2, STEP_S), "blocked")
    meeting = MeetingEntry(0, 1, 5, sim_time_s(1, STEP_S), sim_time_s(2, STEP_S), 0.5, 0.2)
    for step in range(4):
        truth(session, step)
        for robot in range(2):
            extra = dict(given_up=(given_up,), meetings=(meeting,)) if (robot, step) == (
                0, 2) else {}
            report = command(robot, step, sequence=step // 2, slam_recoveries=robot, **extra)
            assert not of(session.command(robot, report, 0.0), Dropped)
    session.team_update(0, update(0, 1, 1), 0.0)
    session.team_update(1, update(1, 1, 2), 0.0)
    estimates(session, 0)
    finished = of(truth(session, 4, wall_s=1.0), Finished)
    assert len(finished) == 1
    ours = finished[0].summary.to_dict()
    assert ours["meetings"] == [asdict(meeting)]
    assert [(r["given_up"], r["slam_recoveries"]) for r in ours["robots"]] == [
        ([asdict(given_up)], 0), ([], 1)]
    em_sim = TeamRunner(PARAMS.replace(run={"max_steps": 12})).run().to_dict()
    # Every key of em-sim's summary, at every level (entries of lists em-sim's short run
    # leaves empty are the session's only); team_updates is null here: no link counts came.
    assert set(ours) == set(em_sim)
    assert key_paths(em_sim) - key_paths(ours) == {
        ".team_updates.sent", ".team_updates.on_time", ".team_updates.late",
        ".team_updates.never"}


def test_a_command_reporting_an_implausible_meeting_is_dropped():
    session = started()
    truth(session, 0)
    for meeting, reason in (
            (MeetingEntry(0, 0, 5, 0.0, 0.0, 0.5, 0.2), "a meeting with itself"),
            (MeetingEntry(0, 2, 5, 0.0, 0.0, 0.5, 0.2), "meeting partner id 2"),
            (MeetingEntry(0, 1, 5, 0.0, 1.0, 0.5, 0.2),
             "a meeting at 1 s, after its command's 0 s"),
            (MeetingEntry(0, 1, 5, 0.0, 0.0, -0.5, 0.2), "negative covariance trace")):
        dropped = of(session.command(0, command(0, 0, meetings=(meeting,)), 0.0), Dropped)
        assert len(dropped) == 1 and reason in dropped[0].reason, dropped


#: The field's sonar: no landmark identities, misses and clutter.
FIELD_SONAR = {"landmark_ids": False, "detection_probability": 0.9, "clutter_rate": 1.0}


def keyframe_update(robot: int, readings: tuple[LandmarkReading, ...]) -> TeamUpdate:
    """Robot ``robot``'s first record: keyframe 0 with these landmark readings."""
    keyframe = KeyframeMeasurements(robot, 0, 0.0, True, -1, np.zeros(3), np.zeros((3, 3)),
                                    readings, ())
    return TeamUpdate(robot, 1, 0.0, keyframes=(keyframe,))


def test_the_association_waits_for_the_truth_of_the_scans_and_counts_the_ties():
    params = PARAMS.replace(sensors=FIELD_SONAR)
    session = EvaluatorSession(params, EvaluatorNodeSettings(
        metrics_interval_s=4 * STEP_S, estimate_wait_s=5.0, max_sim_time_s=4 * STEP_S),
        0.0, 3.0, WORLD_NODE)
    session.true_landmarks([7, 3], np.array([[10.0, 10.0], [30.0, 30.0]]), 0.5, 0.0)
    # Each robot saw landmark 3 and named it its own landmark 0; robot 1 saw clutter too.
    seen = LandmarkReading(UNIDENTIFIED, 4.0, 0.5, 0.01, 0.001)
    clutter = LandmarkReading(UNIDENTIFIED, 2.5, -1.0, 0.01, 0.001)
    scans = {0: ((seen,), (3,)), 1: ((seen, clutter), (3, CLUTTER))}
    named = dataclasses.replace(seen, landmark_id=0)
    mine, theirs = owned_landmark_id(0, 0), owned_landmark_id(1, 0)
    for step in range(4):
        truth(session, step)
        for robot in range(2):
            session.command(robot, command(robot, step, sequence=1), 0.0)
    for robot in range(2):
        assert session.team_update(robot, keyframe_update(robot, (named,)), 0.0) == []
    estimates(session, 0)
    # Implausible truths and ties are dropped.
    assert session.sonar_truth(0, stamp_ns(1), 1, (seen,), (3,), 0.0) == [
        Dropped("step 1 is not a keyframe step")]
    assert session.sonar_truth(0, stamp_ns(0), 0, (seen,), (), 0.0) == [
        Dropped("0 sources of 1 readings")]
    assert session.correspondences(0, stamp_ns(2), 2, [(theirs, mine)], 0.0) == [
        Dropped(f"landmarks {theirs} and {mine} are not robot 0's and a teammate's")]
    assert session.correspondences(0, stamp_ns(2), 2, [(mine, theirs)], 0.0) == []
    assert session.sonar_truth(0, stamp_ns(0), 0, *scans[0], 0.0) == []
    # The run stopped at step 4 waits for the truth of robot 1's scan of step 0.
    assert not of(truth(session, 4, wall_s=1.0), Finished)
    effects = session.sonar_truth(1, stamp_ns(0), 0, *scans[1], 1.5)
    finished = of(effects, Finished)
    assert len(finished) == 1
    association = finished[0].summary.association
    assert [(r["correct"], r["wrong"], r["missed"], r["correspondences_correct"])
            for r in association["robots"]] == [(1, 0, 0, 1), (1, 0, 0, 0)]
    assert (association["precision"], association["recall"]) == (1.0, 1.0)
    assert LogLine(Level.INFO, association_line(association)) in of(effects, LogLine)


def test_the_association_counts_what_each_robot_s_own_graph_held():
    """em-sim's observer counts from what em-evaluator also gets (the truth of the scans, the
    streams, the robots' ties and paths): the counts of the robots' own graphs at the end."""
    params = load_params(REPO_ROOT / "config" / "exploration.yaml").replace(
        world={"num_robots": 3, "width_m": 40.0, "height_m": 40.0, "num_landmarks": 8},
        planner={"name": "NEAREST"}, run={"seed": 0}, sensors=FIELD_SONAR)
    runner = TeamRunner(params)
    association = runner.run().association
    assert association["correspondences_correct"] > 0  # ties to count
    assert association == team_association([agent.slam for agent in runner.agents],
                                            runner.observer.association.scans,
                                            params.slam.keyframe_interval_steps)
