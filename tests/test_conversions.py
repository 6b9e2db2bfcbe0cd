"""Message conversions, without a running graph: values survive the wire bit for bit."""
import numpy as np
import pytest
from em_exploration_msgs.msg import TeamUpdate as TeamUpdateMsg
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message

from em_exploration_ros.core.evaluation.summary import GivenUpEntry
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.progress import GivenUpTarget, GiveUpReason
from em_exploration_ros.core.records.team_data import (FrontierType, InvalidTeamUpdate,
                                                       LandmarkEstimate, TargetRecord, TeamUpdate)
from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      LateReading)
from em_exploration_ros.core.records.team_wire import TeamWireFormat, cdr_size
from em_exploration_ros.core.records.wire_model import sim_time_s
from em_exploration_ros.core.sessions.team_runner import TeamRunner, sensor_inputs
from em_exploration_ros.nodes import conversions as conv

PARAMS = ExplorationParams().replace(world={"width_m": 50.0, "height_m": 50.0,
                                            "num_landmarks": 5},
                                     planner={"name": "NEAREST"}, run={"seed": 4})


def through_dds(message):
    """The message as a subscriber receives it (CDR round trip)."""
    return deserialize_message(serialize_message(message), type(message))


@pytest.fixture(scope="module")
def running_team() -> TeamRunner:
    runner = TeamRunner(PARAMS)
    for _ in range(120):
        runner.step_once()
    return runner


def test_sensor_frame_over_the_wire_equals_em_sim_input(running_team):
    """em-robot's session gets from the world's messages what em-sim's gets from the frame."""
    dt = PARAMS.motion.time_step_s
    for robot in range(PARAMS.world.num_robots):
        frame = running_team.simulation.sense(robot)
        message = conv.sonar_scan_to_msg(frame, 7.5, [3, 0, 5])
        message.delivered_updates, message.delivered_requests = 4, 2
        scan = through_dds(message)
        odom = deserialize_message(conv.serialized_dead_reckoning(frame), Odometry)
        odometry, expected = sensor_inputs(frame, (4, 2))
        got = conv.scan_input_from_msg(scan)
        assert (got.step, got.stamp, got.delivered) == (expected.step, expected.stamp, (4, 2))
        assert got.team_sequences == (3, 0, 5) and expected.team_sequences == ()
        assert conv.time_to_seconds(scan.header.stamp) == frame.stamp_s == sim_time_s(
            frame.step, dt)
        assert np.array_equal(conv.odometry_pose(odom), odometry.pose)
        assert np.array_equal(conv.odometry_twist_covariance(odom), odometry.twist_covariance)
        assert got.landmarks == expected.landmarks
        for mine, want in zip(got.teammates, expected.teammates):
            assert mine.robot_id == want.robot_id
            assert np.array_equal(mine.relative_pose, want.relative_pose)
            assert np.array_equal(mine.covariance, want.covariance)
        assert scan.header.frame_id == f"robot_{robot}/base_link"
        assert (odom.header.frame_id, odom.child_frame_id) == (f"robot_{robot}/odom",
                                                               f"robot_{robot}/base_link")
        # The pose covariance is the dead reckoning's accumulated noise: grown by the motion.
        pose_covariance = np.asarray(odom.pose.covariance).reshape(6, 6)
        planar = pose_covariance[np.ix_([0, 1, 5], [0, 1, 5])]
        np.testing.assert_array_equal(planar, frame.odom_pose_covariance)
        assert np.all(np.linalg.eigvalsh(planar) > 0.0)
        assert np.count_nonzero(pose_covariance) == np.count_nonzero(planar)


def _assert_same_update(a, b):
    assert (a.robot_id, a.sequence, a.stamp_s, a.finished) == (b.robot_id, b.sequence,
                                                               b.stamp_s, b.finished)
    assert len(a.keyframes) == len(b.keyframes)
    for mx, my in zip(a.keyframes, b.keyframes):
        assert (mx.robot_id, mx.index, mx.stamp_s, mx.is_first, mx.previous_index) == \
            (my.robot_id, my.index, my.stamp_s, my.is_first, my.previous_index)
        for name in ("odom_delta", "odom_covariance"):
            assert np.array_equal(getattr(mx, name), getattr(my, name))
        assert mx.landmarks == my.landmarks and mx.late_landmarks == my.late_landmarks
        assert [t.robot_id for t in mx.teammates] == [t.robot_id for t in my.teammates]
        for tx, ty in zip(mx.teammates, my.teammates):
            assert np.array_equal(tx.relative_pose, ty.relative_pose)
            assert np.array_equal(tx.covariance, ty.covariance)
    assert len(a.targets) == len(b.targets)
    for x, y in zip(a.targets, b.targets):
        assert (x.robot_id, x.decision_index, x.stamp_s, x.kind, x.partner_id,
                x.planning_time_s, x.planner_failed) == (y.robot_id, y.decision_index,
                                                         y.stamp_s, y.kind, y.partner_id,
                                                         y.planning_time_s, y.planner_failed)
        assert np.array_equal(x.position, y.position)
    assert len(a.rendezvous) == len(b.rendezvous)


def test_team_updates_survive_the_wire(running_team):
    """What a robot sent arrives bit for bit, although the wire form is compact: the agent
    rounded it before using it itself."""
    wire = TeamWireFormat(PARAMS)
    agent = running_team.agents[1]
    sent = agent.outbox.resend(1, 0)
    assert len(sent) > 5 and any(u.targets for u in sent)
    assert any(kf.landmarks for u in sent for kf in u.keyframes)
    assert any(kf.teammates for u in sent for kf in u.keyframes)
    for update in sent:
        message = through_dds(conv.team_update_to_msg(update, wire))
        _assert_same_update(conv.team_update_from_msg(message, wire), update)


def test_late_readings_travel_as_entries_after_their_keyframe():
    """A keyframe's late readings go as one LATE_READINGS entry per earlier keyframe after
    it, and come back joined to it; such an entry before any keyframe is refused."""
    wire = TeamWireFormat(PARAMS)
    stamp = wire.step_time_s(70)

    def reading(landmark: int, range_m: float) -> LandmarkReading:
        return wire.landmark_reading(landmark, range_m, 0.25)

    keyframes = tuple(wire.keyframe(KeyframeMeasurements(
        1, index, wire.keyframe_time_s(index), False, index - 1, np.zeros(3), np.eye(3) * 1e-4,
        (reading(5, 3.0),), (), late)) for index, late in (
            (6, (LateReading(3, reading(5, 3.5)), LateReading(4, reading(5, 3.25)),
                 LateReading(3, reading(6, 7.0)))),
            (7, ())))
    assert [late.keyframe_index for late in keyframes[0].late_landmarks] == [3, 3, 4]
    update = TeamUpdate(1, 9, stamp, keyframes)
    message = through_dds(conv.team_update_to_msg(update, wire))
    late = conv.em_msg.Keyframe.LATE_READINGS
    assert [(k.index, k.previous_index, len(k.landmarks)) for k in message.keyframes] == [
        (6, 5, 1), (3, late, 2), (4, late, 1), (7, 6, 1)]
    _assert_same_update(conv.team_update_from_msg(message, wire), update)
    assert cdr_size(update) == len(serialize_message(message))
    message.keyframes = message.keyframes[1:]
    with pytest.raises(InvalidTeamUpdate, match="late readings before any keyframe"):
        conv.team_update_from_msg(message, wire)


def test_an_update_off_the_step_grid_cannot_be_sent():
    wire = TeamWireFormat(PARAMS)
    with pytest.raises(ValueError, match="not the time of a simulation step"):
        conv.team_update_to_msg(TeamUpdate(0, 1, 0.3), wire)
    target = TargetRecord(0, 0, 0.2, np.zeros(2), FrontierType.EXPLORATION, None, 0.1)
    with pytest.raises(ValueError, match="stamp is not the update's"):
        conv.team_update_to_msg(TeamUpdate(0, 1, 0.4, targets=(target,)), wire)


def test_no_partner_is_explicit_on_the_wire():
    def target(kind, partner):
        return TargetRecord(1, 0, 2.0, np.array([1.0, 2.0]), kind, partner, 0.125)

    exploring = conv.target_to_msg(target(FrontierType.EXPLORATION, None))
    assert exploring.partner_id == conv.em_msg.TargetRecord.NO_PARTNER
    assert conv.target_from_msg(through_dds(exploring), 1, 2.0).partner_id is None
    meeting = conv.target_to_msg(target(FrontierType.RENDEZVOUS, 2))
    assert conv.target_from_msg(through_dds(meeting), 1, 2.0).partner_id == 2
    assert conv.em_msg.TargetRecord().partner_id == conv.em_msg.TargetRecord.NO_PARTNER


def test_malformed_team_update_messages_are_rejected():
    wire = TeamWireFormat(PARAMS)
    message = TeamUpdateMsg(robot_id=1, sequence=1)
    message.targets.append(conv.em_msg.TargetRecord(frontier_type=9))
    with pytest.raises(InvalidTeamUpdate, match="frontier type"):
        conv.team_update_from_msg(message, wire)
    message = TeamUpdateMsg(robot_id=1, sequence=1)
    message.rendezvous.append(conv.em_msg.Rendezvous(state=7))
    with pytest.raises(InvalidTeamUpdate, match="rendezvous state"):
        conv.team_update_from_msg(message, wire)


def test_targets_given_up_reach_the_evaluator_as_the_summary_lists_them():
    for reason in GiveUpReason:
        given_up = GivenUpTarget(np.array([12.5, -3.25]), 40.2, reason)
        command = conv.em_msg.MotionCommand(given_up=[conv.given_up_to_msg(given_up)])
        received = through_dds(command).given_up[0]
        assert conv.given_up_from_msg(received, 40.2) == GivenUpEntry(12.5, -3.25, 40.2,
                                                                      reason.value)
    with pytest.raises(ValueError, match="unknown give-up reason 7"):
        conv.given_up_from_msg(conv.em_msg.GivenUpTarget(reason=7), 1.0)


def test_path_and_landmarks_round_trip(running_team):
    indices, poses = running_team.agents[0].slam.trajectory(0)
    stamps = np.array([sim_time_s(int(i) * 10, 0.2) for i in indices])
    got_stamps, got_poses = conv.path_from_msg(through_dds(conv.path_to_msg(9.0, stamps, poses)))
    assert np.array_equal(got_stamps, stamps)
    np.testing.assert_allclose(got_poses, poses, atol=1e-12)
    estimates = running_team.agents[0].slam.landmark_estimates()
    array = conv.landmark_array_to_msg(1.0, "map", [LandmarkEstimate(k, v, np.eye(2))
                                                    for k, v in estimates.items()], 1.0)
    got = conv.landmark_positions_from_msg(through_dds(array))
    assert got.keys() == estimates.keys()
    assert all(np.array_equal(got[k], estimates[k]) for k in got)
