"""The team stream's wire form: what a receiver rebuilds, how the sender rounds, what it costs."""
import numpy as np
import pytest
from em_exploration_msgs.msg import TeamUpdate as TeamUpdateMsg
from rclpy.serialization import serialize_message

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      TeammateReading)
from em_exploration_ros.core.records.team_data import (FrontierType, RendezvousEvent,
                                                       RendezvousState, TargetRecord, TeamUpdate)
from em_exploration_ros.core.records.team_wire import (TeamWireFormat, cdr_size,
                                                       covariance_from_upper, covariance_upper,
                                                       to_float32)
from em_exploration_ros.core.records.wire_model import sim_time_s
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.core.world.sensors import SensorSimulator
from em_exploration_ros.nodes.conversions import team_update_to_msg

PARAMS = ExplorationParams()
WIRE = TeamWireFormat(PARAMS)


def raw_keyframe(index: int = 7) -> KeyframeMeasurements:
    """A keyframe as KeyframeBuilder cuts it: float64 numbers, sensor-reported noise."""
    covariance = np.array([[3.1e-4, 1.7e-6, -2.3e-5], [1.7e-6, 2.9e-4, 4.1e-5],
                           [-2.3e-5, 4.1e-5, 1.9e-5]])
    return KeyframeMeasurements(
        1, index, 0.1 + index * 2.0, False, index - 1, np.array([1.9876543211, 0.1234567891,
                                                                 -0.0987654321]), covariance,
        (LandmarkReading(4, 5.123456789, 0.987654321, 1.0, 2.0),),
        (TeammateReading(2, np.array([3.333333333, -1.111111111, 0.555555555]), np.eye(3)),))


def test_keyframe_rounding_is_float32_and_idempotent():
    kf = raw_keyframe()
    wired = WIRE.keyframe(kf)
    assert wired.stamp_s == sim_time_s(7 * PARAMS.slam.keyframe_interval_steps,
                                       PARAMS.motion.time_step_s)
    assert np.array_equal(wired.odom_delta, kf.odom_delta.astype(np.float32))
    assert np.array_equal(wired.odom_covariance, wired.odom_covariance.T)
    np.testing.assert_allclose(wired.odom_covariance, kf.odom_covariance, rtol=1e-7)
    assert not np.array_equal(wired.odom_delta, kf.odom_delta)  # it did round
    reading = wired.landmarks[0]
    assert (reading.range_m, reading.bearing_rad) == (to_float32(5.123456789),
                                                      to_float32(0.987654321))
    again = WIRE.keyframe(wired)
    assert again.landmarks == wired.landmarks and again.stamp_s == wired.stamp_s
    assert np.array_equal(again.odom_delta, wired.odom_delta)
    assert np.array_equal(again.odom_covariance, wired.odom_covariance)
    assert np.array_equal(again.teammates[0].relative_pose, wired.teammates[0].relative_pose)


def test_noise_that_is_not_sent_is_the_sensors_own():
    """Receivers rebuild reading noise from the shared parameters: exactly what the world's
    sensors report, so the sender's graph (which used the sensor's values) is unchanged."""
    world = TeamRunner(PARAMS.replace(run={"seed": 3})).simulation.world
    sensors = SensorSimulator(world, PARAMS.sensors, PARAMS.motion, np.random.SeedSequence(3))
    poses = np.array([[10.0, 10.0, 0.0], [12.0, 10.0, 0.5], [30.0, 30.0, 0.0]])
    teammate = sensors.teammates(0, poses)[0]
    wired = WIRE.keyframe(raw_keyframe())
    assert np.array_equal(wired.teammates[0].covariance, teammate.covariance)
    near_landmark = np.array([world.landmarks[0][0] + 2.0, world.landmarks[0][1], 0.0])
    landmark = sensors.sonar(0, near_landmark)[0]
    assert (wired.landmarks[0].range_variance, wired.landmarks[0].bearing_variance) == (
        landmark.range_variance, landmark.bearing_variance)


def test_first_keyframe_carries_no_odometry():
    kf = raw_keyframe()
    first = WIRE.keyframe(KeyframeMeasurements(1, 0, 0.0, True, -1, kf.odom_delta,
                                               kf.odom_covariance, (), ()))
    assert not first.odom_delta.any() and not first.odom_covariance.any()


def test_covariance_upper_triangle_round_trip():
    covariance = raw_keyframe().odom_covariance
    assert covariance_upper(covariance).tolist() == [3.1e-4, 1.7e-6, -2.3e-5, 2.9e-4, 4.1e-5,
                                                     1.9e-5]
    assert np.array_equal(covariance_from_upper(covariance_upper(covariance)), covariance)
    with pytest.raises(ValueError, match="6 elements"):
        covariance_from_upper(np.zeros(9))


def test_times_are_steps():
    assert WIRE.step_of(sim_time_s(1234, PARAMS.motion.time_step_s)) == 1234
    assert WIRE.step_time_s(1234) == sim_time_s(1234, PARAMS.motion.time_step_s)
    for off_grid in (0.1, -0.2):
        with pytest.raises(ValueError, match="not the time of a simulation step"):
            WIRE.step_of(off_grid)


def test_target_planning_time_is_float32():
    target = TargetRecord(0, 3, 4.0, np.array([1.0, 3.0]), FrontierType.REVISITING, None,
                          0.123456789)
    assert WIRE.target(target).planning_time_s == to_float32(0.123456789)
    assert np.array_equal(WIRE.target(target).position, target.position)


def test_an_agent_uses_what_it_sends():
    """Every keyframe and target a robot sent is already in wire form (rounding it again
    changes nothing), so its own graph holds what its teammates add to theirs."""
    runner = TeamRunner(PARAMS.replace(world={"width_m": 40.0, "height_m": 40.0,
                                              "num_landmarks": 4}, run={"seed": 1}))
    for _ in range(60):
        runner.step_once()
    agent = runner.agents[0]
    sent = agent.outbox.resend(1, 0)
    keyframes = [kf for update in sent for kf in update.keyframes]
    assert len(keyframes) >= 5 and any(update.targets for update in sent)
    for kf in keyframes:
        again = WIRE.keyframe(kf)
        assert np.array_equal(again.odom_delta, kf.odom_delta)
        assert np.array_equal(again.odom_covariance, kf.odom_covariance)
        assert again.landmarks == kf.landmarks
    for target in (t for update in sent for t in update.targets):
        assert WIRE.target(target) == target


def test_cdr_size_of_a_keyframe_update():
    """The layout the bandwidth figures rest on: an update with one keyframe without
    readings is 88 bytes of CDR (encapsulation 4, update 32 with its run_id, keyframe 52);
    each landmark reading adds 12, each teammate reading 16."""
    kf = WIRE.keyframe(raw_keyframe())
    bare = KeyframeMeasurements(1, kf.index, kf.stamp_s, False, kf.index - 1, kf.odom_delta,
                                kf.odom_covariance, (), ())
    stamp = WIRE.step_time_s(70)

    def size(keyframe: KeyframeMeasurements) -> int:
        message: TeamUpdateMsg = team_update_to_msg(TeamUpdate(1, 9, stamp, (keyframe,)), WIRE)
        return len(serialize_message(message))

    assert size(bare) == 88
    assert size(kf) == 88 + 12 + 16


def test_cdr_size_without_ros_equals_the_serialized_size():
    """``cdr_size`` (no rclpy) against rclpy's serialization, for updates of every shape:
    alignment padding differs with what precedes each float64."""
    kf = WIRE.keyframe(raw_keyframe())
    stamp = WIRE.step_time_s(70)
    event = RendezvousEvent(3, 1, 2, 1, RendezvousState.REQUEST, 13.2, np.array([4.0, 5.0]),
                            60.0)

    def target(index: int) -> TargetRecord:
        return TargetRecord(1, index, stamp, np.array([3.0, 7.0]), FrontierType.RENDEZVOUS, 2,
                            0.25, index % 2 == 0)

    shapes = [TeamUpdate(1, 1, stamp)]
    for keyframes in ((), (kf,), (kf, kf)):
        for targets in ((), (target(0),), (target(0), target(1), target(2))):
            for events in ((), (event,), (event, event)):
                shapes.append(TeamUpdate(1, 5, stamp, keyframes, targets, events, True))
    for update in shapes:
        assert cdr_size(update) == len(serialize_message(team_update_to_msg(update, WIRE)))
