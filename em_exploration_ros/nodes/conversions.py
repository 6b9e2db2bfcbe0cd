"""Conversions between the core's plain data and ROS 2 messages.

Pure functions, no node needed: tests build and read messages without a running graph.
Frames follow REP-103/105: sensor data in ``robot_<i>/base_link``, dead reckoning in
``robot_<i>/odom``, estimates in ``map``, ground truth in ``world``.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Time
from em_exploration_msgs import msg as em_msg
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Quaternion
from nav_msgs.msg import Odometry, Path

from em_exploration_ros.core.evaluation.summary import GivenUpEntry, MeetingEntry
from em_exploration_ros.core.planning.progress import GivenUpTarget, GiveUpReason
from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      LateReading, TeammateReading)
from em_exploration_ros.core.records.team_data import (FrontierType, InvalidTeamUpdate,
                                                       LandmarkEstimate, RendezvousEvent,
                                                       RendezvousState, TargetRecord, TeamUpdate,
                                                       check_record_sizes)
from em_exploration_ros.core.records.team_wire import (TeamWireFormat, covariance_from_upper,
                                                       covariance_upper, late_groups)
from em_exploration_ros.core.records.wire_model import (NANOSECONDS_PER_SECOND,
                                                        nanoseconds_to_seconds,
                                                        planar_covariance_from_6x6,
                                                        planar_covariance_to_6x6, planar_quaternion,
                                                        planar_yaw, seconds_to_nanoseconds)
from em_exploration_ros.core.sessions.robot_effects import KeyframeEstimate
from em_exploration_ros.core.sessions.robot_session import ScanInput
from em_exploration_ros.core.world.simulation import SensorFrame
from em_exploration_ros.nodes.odometry_cdr import OdometryCodec, PlanarOdometry
from em_exploration_ros.nodes.path_cdr import DecodedPath, encode_path

if TYPE_CHECKING:  # the evaluator process does not load the robot's agent
    from em_exploration_ros.core.agent.robot_agent import MeetingEffect

MAP_FRAME = "map"
WORLD_FRAME = "world"
#: The world simulator's node name, and its stepping state topic (WorldStatus, latched).
WORLD_NODE_NAME = "em_world"
WORLD_STATUS_TOPIC = "/world/status"


def robot_namespace(robot_id: int) -> str:
    """Namespace of a robot's topics, ``robot_<i>``."""
    return f"robot_{robot_id}"


def time_parts(seconds: float) -> tuple[int, int]:
    """(sec, nanosec) of a simulation time [s] (rounded to the nanosecond)."""
    sec, nanosec = divmod(seconds_to_nanoseconds(seconds), NANOSECONDS_PER_SECOND)
    return int(sec), int(nanosec)


def seconds_to_time(seconds: float) -> Time:
    """A simulation time [s] as builtin_interfaces/Time (rounded to the nanosecond)."""
    sec, nanosec = time_parts(seconds)
    return Time(sec=sec, nanosec=nanosec)


def time_to_seconds(stamp: Time) -> float:
    """builtin_interfaces/Time as seconds (wire-exact, see core.records.wire_model)."""
    return nanoseconds_to_seconds(stamp.sec * NANOSECONDS_PER_SECOND + stamp.nanosec)


def yaw_to_quaternion(yaw: float) -> Quaternion:
    """Rotation about +z by ``yaw`` [rad]."""
    z, w = planar_quaternion(yaw)
    return Quaternion(x=0.0, y=0.0, z=z, w=w)


def quaternion_to_yaw(q: Quaternion) -> float:
    """Yaw [rad] of a planar rotation (0, 0, z, w); x and y are ignored."""
    return planar_yaw(q.z, q.w)


def _matrix(values, size: int) -> np.ndarray:
    return np.asarray(values, dtype=float).reshape(size, size)


def _flat(matrix: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(matrix, dtype=float).ravel()]


# -- sensors (world -> robot) -------------------------------------------------------------

def landmark_reading_to_msg(reading: LandmarkReading) -> em_msg.LandmarkDetection:
    return em_msg.LandmarkDetection(
        landmark_id=int(reading.landmark_id), range=float(reading.range_m),
        bearing=float(reading.bearing_rad), range_variance=float(reading.range_variance),
        bearing_variance=float(reading.bearing_variance))


def landmark_reading_from_msg(message: em_msg.LandmarkDetection) -> LandmarkReading:
    return LandmarkReading(int(message.landmark_id), float(message.range),
                           float(message.bearing), float(message.range_variance),
                           float(message.bearing_variance))


def teammate_reading_to_msg(reading: TeammateReading) -> em_msg.TeammateDetection:
    x, y, theta = (float(v) for v in reading.relative_pose)
    return em_msg.TeammateDetection(robot_id=int(reading.robot_id), x=x, y=y, theta=theta,
                                    covariance=_flat(reading.covariance))


def teammate_reading_from_msg(message: em_msg.TeammateDetection) -> TeammateReading:
    return TeammateReading(int(message.robot_id),
                           np.array([message.x, message.y, message.theta], dtype=float),
                           _matrix(message.covariance, 3))


def sonar_scan_to_msg(frame: SensorFrame, max_range_m: float,
                      team_sequences: list[int]) -> em_msg.SonarScan:
    """The sonar part of a sensor frame (body frame of the robot)."""
    message = em_msg.SonarScan(robot_id=frame.robot_id, step=frame.step,
                               max_range=float(max_range_m),
                               landmarks=[landmark_reading_to_msg(r) for r in frame.landmarks],
                               teammates=[teammate_reading_to_msg(r) for r in frame.teammates],
                               team_sequences=[int(s) for s in team_sequences])
    message.header.stamp = seconds_to_time(frame.stamp_s)
    message.header.frame_id = f"{robot_namespace(frame.robot_id)}/base_link"
    return message


def scan_input_from_msg(message: em_msg.SonarScan) -> ScanInput:
    """What a robot takes from a sonar scan (``sonar_scan_to_msg``'s inverse, with the
    barrier and, in relay mode, the deliveries so far): em-sim builds the same from the
    world's frame (``core.sessions.team_runner.sensor_inputs``)."""
    stamp = message.header.stamp
    return ScanInput(int(message.step), (stamp.sec, stamp.nanosec),
                     tuple(landmark_reading_from_msg(r) for r in message.landmarks),
                     tuple(teammate_reading_from_msg(r) for r in message.teammates),
                     tuple(int(s) for s in message.team_sequences),
                     (int(message.delivered_updates), int(message.delivered_requests)))


@functools.lru_cache(maxsize=256)
def odometry_codec(frame_id: str, child_frame_id: str) -> OdometryCodec:
    """The serialized form of nav_msgs/Odometry with these frames (``nodes.odometry_cdr``)."""
    return OdometryCodec(frame_id, child_frame_id)


def serialized_odometry(stamp_s: float, pose: np.ndarray, frame_id: str, child_frame_id: str,
                        twist_covariance: np.ndarray | None = None,
                        pose_covariance: np.ndarray | None = None) -> bytes:
    """A planar pose (x [m], y [m], theta [rad]) as serialized nav_msgs/Odometry, zero
    twist, 6x6 covariances (zero when None); publishers take the bytes as they are."""
    return odometry_codec(frame_id, child_frame_id).encode(time_parts(stamp_s), pose,
                                                           pose_covariance, twist_covariance)


def serialized_dead_reckoning(frame: SensorFrame) -> bytes:
    """The dead-reckoning part of a sensor frame as serialized Odometry, REP-105 odom ->
    base_link, with the covariance of its accumulated noise (pose) and of the last step's
    velocity (twist)."""
    namespace = robot_namespace(frame.robot_id)
    return serialized_odometry(frame.stamp_s, frame.odom_pose, f"{namespace}/odom",
                               f"{namespace}/base_link", frame.twist_covariance,
                               planar_covariance_to_6x6(frame.odom_pose_covariance))


def odometry_pose(message: Odometry) -> np.ndarray:
    """(x [m], y [m], theta [rad]) of an Odometry message's pose."""
    p = message.pose.pose
    return np.array([p.position.x, p.position.y, quaternion_to_yaw(p.orientation)])


def odometry_twist_covariance(message: Odometry) -> np.ndarray:
    """The 6x6 twist covariance of an Odometry message."""
    return _matrix(message.twist.covariance, 6)


def planar_odometry_from_msg(message: Odometry) -> PlanarOdometry:
    """An Odometry message in the form :meth:`OdometryCodec.decode` reads (no checks)."""
    stamp = message.header.stamp
    return PlanarOdometry((stamp.sec, stamp.nanosec), odometry_pose(message),
                          _matrix(message.pose.covariance, 6), odometry_twist_covariance(message))


# -- team data (robot <-> robot) ----------------------------------------------------------
# The wire form is compact (msg_schemas/msg/TeamUpdate.msg); ``TeamWireFormat`` holds the
# shared parameters a receiver rebuilds the rest from. A record the core made goes through
# ``to_msg`` and back unchanged: the sender already rounded it (core/records/team_wire.py).

def _landmarks_to_msg(readings: Iterable[LandmarkReading]) -> list[em_msg.KeyframeLandmark]:
    return [em_msg.KeyframeLandmark(landmark_id=int(r.landmark_id), range=float(r.range_m),
                                    bearing=float(r.bearing_rad)) for r in readings]


def _keyframe_to_msgs(kf: KeyframeMeasurements) -> list[em_msg.Keyframe]:
    """The keyframe's entry, then one ``LATE_READINGS`` entry per earlier keyframe its late
    readings are of (``team_wire.late_groups``)."""
    previous = em_msg.Keyframe.NO_PREVIOUS if kf.is_first else kf.previous_index
    entries = [em_msg.Keyframe(
        index=kf.index, previous_index=int(previous),
        odom_x=float(kf.odom_delta[0]), odom_y=float(kf.odom_delta[1]),
        odom_theta=float(kf.odom_delta[2]),
        odom_covariance=[float(v) for v in covariance_upper(kf.odom_covariance)],
        landmarks=_landmarks_to_msg(kf.landmarks),
        teammates=[em_msg.KeyframeTeammate(robot_id=int(r.robot_id),
                                           x=float(r.relative_pose[0]),
                                           y=float(r.relative_pose[1]),
                                           theta=float(r.relative_pose[2]))
                   for r in kf.teammates])]
    entries.extend(em_msg.Keyframe(index=group[0].keyframe_index,
                                   previous_index=em_msg.Keyframe.LATE_READINGS,
                                   landmarks=_landmarks_to_msg(late.reading for late in group))
                   for group in late_groups(kf))
    return entries


def _keyframes_from_msg(messages: Iterable[em_msg.Keyframe], robot_id: int,
                        wire: TeamWireFormat) -> tuple[KeyframeMeasurements, ...]:
    """The keyframes of an update's entries, each ``LATE_READINGS`` entry joined to the
    keyframe before it as its late readings; InvalidTeamUpdate if one comes first or holds
    more than landmarks."""
    keyframes: list[KeyframeMeasurements] = []
    for message in messages:
        if message.previous_index != em_msg.Keyframe.LATE_READINGS:
            keyframes.append(_keyframe_from_msg(message, robot_id, wire))
            continue
        if not keyframes:
            raise InvalidTeamUpdate("late readings before any keyframe of the update")
        if message.teammates:
            raise InvalidTeamUpdate(f"late readings of keyframe {message.index} with "
                                    "teammate readings")
        carrier = keyframes[-1]
        late = tuple(LateReading(int(message.index),
                                 wire.landmark_reading(r.landmark_id, r.range, r.bearing))
                     for r in message.landmarks)
        keyframes[-1] = replace(carrier, late_landmarks=carrier.late_landmarks + late)
    return tuple(keyframes)


def _keyframe_from_msg(message: em_msg.Keyframe, robot_id: int,
                       wire: TeamWireFormat) -> KeyframeMeasurements:
    is_first = message.previous_index == em_msg.Keyframe.NO_PREVIOUS
    return KeyframeMeasurements(
        robot_id=robot_id, index=int(message.index),
        stamp_s=wire.keyframe_time_s(int(message.index)), is_first=is_first,
        previous_index=-1 if is_first else int(message.previous_index),
        odom_delta=np.array([message.odom_x, message.odom_y, message.odom_theta], dtype=float),
        odom_covariance=covariance_from_upper(np.asarray(message.odom_covariance, dtype=float)),
        landmarks=tuple(wire.landmark_reading(r.landmark_id, r.range, r.bearing)
                        for r in message.landmarks),
        teammates=tuple(wire.teammate_reading(r.robot_id, np.array([r.x, r.y, r.theta]))
                        for r in message.teammates))


def landmark_estimate_to_msg(landmark: LandmarkEstimate) -> em_msg.LandmarkEstimate:
    return em_msg.LandmarkEstimate(landmark_id=int(landmark.landmark_id),
                                   x=float(landmark.position[0]), y=float(landmark.position[1]),
                                   covariance=_flat(landmark.covariance))


def target_to_msg(target: TargetRecord) -> em_msg.TargetRecord:
    """A target as carried in its robot's TeamUpdate (robot and time are the update's)."""
    partner = em_msg.TargetRecord.NO_PARTNER if target.partner_id is None else target.partner_id
    return em_msg.TargetRecord(
        decision_index=target.decision_index, partner_id=int(partner),
        x=float(target.position[0]), y=float(target.position[1]),
        planning_time=float(target.planning_time_s), frontier_type=int(target.kind),
        planner_failed=bool(target.planner_failed))


def target_from_msg(message: em_msg.TargetRecord, robot_id: int,
                    stamp_s: float) -> TargetRecord:
    """The core record of a target of robot ``robot_id`` carried by an update of time
    ``stamp_s`` [s]; ``partner_id`` NO_PARTNER becomes None."""
    try:
        kind = FrontierType(message.frontier_type)
    except ValueError:
        raise InvalidTeamUpdate(f"unknown frontier type {message.frontier_type}") from None
    partner = None if message.partner_id == em_msg.TargetRecord.NO_PARTNER else int(
        message.partner_id)
    return TargetRecord(robot_id, int(message.decision_index), stamp_s,
                        np.array([message.x, message.y]), kind, partner,
                        float(message.planning_time), bool(message.planner_failed))


#: GivenUpTarget.reason on the wire for each reason a robot gives a target up.
_GIVE_UP_REASON_CODES = {GiveUpReason.BLOCKED: em_msg.GivenUpTarget.BLOCKED,
                         GiveUpReason.NO_PROGRESS: em_msg.GivenUpTarget.NO_PROGRESS,
                         GiveUpReason.DEADLINE: em_msg.GivenUpTarget.DEADLINE}
_GIVE_UP_REASONS = {code: reason for reason, code in _GIVE_UP_REASON_CODES.items()}


def given_up_to_msg(given_up: GivenUpTarget) -> em_msg.GivenUpTarget:
    """A target the robot gave up, as carried in its MotionCommand (robot and time are the
    command's)."""
    return em_msg.GivenUpTarget(x=float(given_up.position[0]), y=float(given_up.position[1]),
                                reason=_GIVE_UP_REASON_CODES[given_up.reason])


def given_up_from_msg(message: em_msg.GivenUpTarget, stamp_s: float) -> GivenUpEntry:
    """The summary's entry of a target given up at ``stamp_s`` [s sim time] (the time of the
    command carrying it); ValueError for an unknown reason code."""
    reason = _GIVE_UP_REASONS.get(message.reason)
    if reason is None:
        raise ValueError(f"unknown give-up reason {message.reason}")
    return GivenUpEntry(float(message.x), float(message.y), stamp_s, reason.value)


def meeting_to_msg(meeting: MeetingEffect) -> em_msg.Meeting:
    """A rendezvous the robot requested that added an inter-robot factor, as carried in its
    MotionCommand (the requester is the command's robot)."""
    return em_msg.Meeting(rendezvous_id=meeting.rendezvous_id, partner_id=meeting.partner_id,
                          requested_at_s=meeting.requested_at_s, stamp_s=meeting.stamp_s,
                          trace_before_m2=meeting.trace_before_m2,
                          trace_after_m2=meeting.trace_after_m2)


def meeting_from_msg(message: em_msg.Meeting, requester_id: int) -> MeetingEntry:
    """The summary's entry of a meeting robot ``requester_id`` reported."""
    return MeetingEntry(requester_id, int(message.partner_id), int(message.rendezvous_id),
                        float(message.requested_at_s), float(message.stamp_s),
                        float(message.trace_before_m2), float(message.trace_after_m2))


def _rendezvous_to_msg(event: RendezvousEvent) -> em_msg.Rendezvous:
    message = em_msg.Rendezvous(
        rendezvous_id=event.rendezvous_id, requester_id=event.requester_id,
        partner_id=event.partner_id, sender_id=event.sender_id, state=int(event.state),
        x=float(event.meeting_point[0]), y=float(event.meeting_point[1]),
        timeout=float(event.timeout_s))
    message.stamp = seconds_to_time(event.stamp_s)
    return message


def rendezvous_from_msg(message: em_msg.Rendezvous) -> RendezvousEvent:
    """A Rendezvous message as a core event; InvalidTeamUpdate for an unknown state."""
    try:
        state = RendezvousState(message.state)
    except ValueError:
        raise InvalidTeamUpdate(f"unknown rendezvous state {message.state}") from None
    return RendezvousEvent(int(message.rendezvous_id), int(message.requester_id),
                           int(message.partner_id), int(message.sender_id), state,
                           time_to_seconds(message.stamp), np.array([message.x, message.y]),
                           float(message.timeout))


def team_update_to_msg(update: TeamUpdate, wire: TeamWireFormat) -> em_msg.TeamUpdate:
    """A core TeamUpdate as em_exploration_msgs/TeamUpdate. ValueError if the update cannot
    travel in that form: its time is no step's, or a target is stamped at another time (a
    decision travels in the update of its step)."""
    step = wire.step_of(update.stamp_s)
    if any(target.stamp_s != update.stamp_s for target in update.targets):
        raise ValueError(f"robot {update.robot_id}, update {update.sequence}: a target's "
                         "stamp is not the update's")
    return em_msg.TeamUpdate(
        step=step, sequence=update.sequence, robot_id=update.robot_id,
        finished=bool(update.finished),
        keyframes=[entry for k in update.keyframes for entry in _keyframe_to_msgs(k)],
        targets=[target_to_msg(t) for t in update.targets],
        rendezvous=[_rendezvous_to_msg(r) for r in update.rendezvous])


def team_update_from_msg(message: em_msg.TeamUpdate, wire: TeamWireFormat) -> TeamUpdate:
    """A received TeamUpdate as core data; raises InvalidTeamUpdate on malformed content
    (the caller validates the values with ``validate_team_update``; arrays longer than
    it allows are refused here, before they are converted)."""
    check_record_sizes(len(message.keyframes), len(message.targets), len(message.rendezvous))
    robot_id = int(message.robot_id)
    stamp_s = wire.step_time_s(int(message.step))
    try:
        return TeamUpdate(
            robot_id=robot_id, sequence=int(message.sequence), stamp_s=stamp_s,
            keyframes=_keyframes_from_msg(message.keyframes, robot_id, wire),
            targets=tuple(target_from_msg(t, robot_id, stamp_s) for t in message.targets),
            rendezvous=tuple(rendezvous_from_msg(r) for r in message.rendezvous),
            finished=bool(message.finished))
    except (ValueError, TypeError) as error:  # e.g. wrong covariance length
        raise InvalidTeamUpdate(f"malformed TeamUpdate: {error}") from None


# -- estimates for users (RViz, Foxglove, evaluator) ---------------------------------------

def path_to_msg(stamp_s: float, stamps_s: np.ndarray, poses: np.ndarray,
                frame_id: str = MAP_FRAME) -> Path:
    """A trajectory (K, 3) with per-pose stamps [s] as nav_msgs/Path."""
    message = Path()
    message.header.stamp = seconds_to_time(stamp_s)
    message.header.frame_id = frame_id
    for stamp, pose in zip(stamps_s, np.asarray(poses).reshape(-1, 3)):
        entry = PoseStamped()
        entry.header.stamp = seconds_to_time(float(stamp))
        entry.header.frame_id = frame_id
        entry.pose.position.x = float(pose[0])
        entry.pose.position.y = float(pose[1])
        entry.pose.orientation = yaw_to_quaternion(float(pose[2]))
        message.poses.append(entry)
    return message


def serialized_path(stamp_s: float, stamps_s: np.ndarray, poses: np.ndarray,
                    frame_id: str = MAP_FRAME) -> bytes:
    """``path_to_msg`` already serialized (CDR), built with NumPy (``nodes.path_cdr``):
    what a robot publishes at every keyframe."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    spatial = np.zeros((len(poses), 7))
    spatial[:, :2] = poses[:, :2]
    spatial[:, 5], spatial[:, 6] = np.sin(poses[:, 2] / 2.0), np.cos(poses[:, 2] / 2.0)
    nanoseconds = np.round(np.asarray(stamps_s, dtype=float) * NANOSECONDS_PER_SECOND)
    stamps = np.column_stack(np.divmod(nanoseconds.astype(np.int64), NANOSECONDS_PER_SECOND))
    stamp = divmod(seconds_to_nanoseconds(stamp_s), NANOSECONDS_PER_SECOND)
    return encode_path(stamp, frame_id, stamps, spatial)


def planar_path(decoded: DecodedPath) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [s] (K,), poses (K, 3)) of a path read by ``path_cdr.decode_path``, as
    ``path_from_msg`` gives them."""
    stamps = decoded.pose_stamps[:, 0] + decoded.pose_stamps[:, 1] * 1e-9
    z, w = decoded.poses[:, 5], decoded.poses[:, 6]
    # math.atan2, as planar_yaw: NumPy's arctan2 may differ in the last bit.
    yaw = list(map(math.atan2, (2.0 * w * z).tolist(), (1.0 - 2.0 * z * z).tolist()))
    return stamps, np.column_stack([decoded.poses[:, :2], np.array(yaw).reshape(-1)])


def path_from_msg(message: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [s] (K,), poses (K, 3)) of a nav_msgs/Path."""
    stamps = np.array([time_to_seconds(p.header.stamp) for p in message.poses])
    poses = np.array([[p.pose.position.x, p.pose.position.y, quaternion_to_yaw(p.pose.orientation)]
                      for p in message.poses]).reshape(-1, 3)
    return stamps, poses


def keyframe_estimate_to_msg(estimate: KeyframeEstimate) -> PoseWithCovarianceStamped:
    """A robot's latest keyframe (pose and marginal covariance, map frame) as
    geometry_msgs/PoseWithCovarianceStamped stamped with the keyframe's time; the 6x6 in
    REP-103 order (x, y, z, roll, pitch, yaw), zero for z, roll and pitch."""
    message = PoseWithCovarianceStamped()
    message.header.stamp = seconds_to_time(estimate.stamp_s)
    message.header.frame_id = MAP_FRAME
    pose = message.pose.pose
    pose.position.x, pose.position.y = float(estimate.pose[0]), float(estimate.pose[1])
    pose.orientation = yaw_to_quaternion(float(estimate.pose[2]))
    message.pose.covariance = _flat(planar_covariance_to_6x6(estimate.covariance))
    return message


def keyframe_covariance_from_msg(message: PoseWithCovarianceStamped) -> np.ndarray:
    """The (x, y, theta) covariance (3, 3) of a ``keyframe_estimate_to_msg`` message."""
    return planar_covariance_from_6x6(message.pose.covariance)


def landmark_array_to_msg(stamp_s: float, frame_id: str, landmarks: list[LandmarkEstimate],
                          radius_m: float = 0.0) -> em_msg.LandmarkArray:
    message = em_msg.LandmarkArray(radius=float(radius_m),
                                   landmarks=[landmark_estimate_to_msg(lm) for lm in landmarks])
    message.header.stamp = seconds_to_time(stamp_s)
    message.header.frame_id = frame_id
    return message


def landmark_positions_from_msg(message: em_msg.LandmarkArray) -> dict[int, np.ndarray]:
    """``{landmark_id: position (2,)}`` of a LandmarkArray."""
    return {int(lm.landmark_id): np.array([lm.x, lm.y]) for lm in message.landmarks}
