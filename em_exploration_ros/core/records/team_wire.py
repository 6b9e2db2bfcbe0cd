"""What the team stream carries, and how precisely: the wire form of team data.

The team stream (em_exploration_msgs/TeamUpdate) is what a real team sends over its radio
or acoustic modem, so it carries nothing a receiver can derive and no number more
precisely than it needs (see msg_schemas/msg/TeamUpdate.msg):

- times are simulation steps: an update's time is ``step * time_step_s``, a keyframe's is
  ``index * keyframe_interval_steps * time_step_s``, a target's is its update's;
- keyframe numbers (odometry, its covariance, readings) are float32, whose relative error
  (6e-8) lies far below the sensors' noise (e.g. a 7.5 m range is rounded by < 5e-7 m,
  its noise sigma is 1e-3 m);
- a reading's noise (sonar variances, teammate covariance) is the shared sensor
  parameters', exactly as the world's sensors report it, so it is not sent;
- a decision's planning time (statistics only) is float32.

The sender must use exactly what its teammates receive, or the graphs drift apart: the
robot passes each new keyframe and target through ``TeamWireFormat`` before using it
itself (``RobotAgent``), em-sim does the same by running the same agent, and the ROS
conversions (``nodes/conversions.py``) then carry these values without loss.

``cdr_size`` gives the bytes one update takes on the wire (its serialized CDR payload)
without ROS, for bandwidth budgets in process.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      LateReading,
                                                      TeammateReading, sonar_variances,
                                                      teammate_covariance)
from em_exploration_ros.core.records.team_data import TargetRecord, TeamUpdate
from em_exploration_ros.core.records.wire_model import sim_time_s

#: Row and column of each element of a symmetric 3x3 covariance sent as its upper triangle
#: (xx, xy, xtheta, yy, ytheta, thetatheta).
UPPER_TRIANGLE_3 = np.triu_indices(3)


def to_float32(value: float) -> float:
    """``value`` rounded to the nearest float32 (as a Python float, exactly representable)."""
    return float(np.float32(value))


def float32_vector(values: np.ndarray) -> np.ndarray:
    """An array rounded element-wise to float32, as float64."""
    return np.asarray(values, dtype=np.float64).astype(np.float32).astype(np.float64)


def covariance_upper(covariance: np.ndarray) -> np.ndarray:
    """The upper triangle ``(6,)`` of a symmetric 3x3 covariance, row by row."""
    return np.asarray(covariance, dtype=float).reshape(3, 3)[UPPER_TRIANGLE_3]


def covariance_from_upper(upper: np.ndarray) -> np.ndarray:
    """The symmetric 3x3 covariance of its upper triangle ``(6,)`` (``covariance_upper``)."""
    values = np.asarray(upper, dtype=float)
    if values.shape != (6,):
        raise ValueError(f"a 3x3 covariance's upper triangle has 6 elements, got {values.shape}")
    covariance = np.zeros((3, 3))
    covariance[UPPER_TRIANGLE_3] = values
    return covariance + np.triu(covariance, 1).T


class TeamWireFormat:
    """The team's shared parameters that let a receiver rebuild what is not sent, and the
    rounding of what is (module docstring)."""

    def __init__(self, params: ExplorationParams) -> None:
        self.time_step_s = params.motion.time_step_s
        self.keyframe_interval_steps = params.slam.keyframe_interval_steps
        self.range_variance, self.bearing_variance = sonar_variances(params.sensors)
        self.teammate_covariance = teammate_covariance(params.sensors)

    # -- times ---------------------------------------------------------------------------

    def step_time_s(self, step: int) -> float:
        """Simulation time [s] of ``step`` (wire-exact, as the world stamps it)."""
        return sim_time_s(step, self.time_step_s)

    def step_of(self, stamp_s: float) -> int:
        """The step whose time is ``stamp_s`` [s]; ValueError if it is no step's time."""
        step = round(stamp_s / self.time_step_s)
        if step < 0 or self.step_time_s(step) != stamp_s:
            raise ValueError(f"{stamp_s!r} s is not the time of a simulation step "
                             f"(time step {self.time_step_s} s)")
        return step

    def keyframe_time_s(self, index: int) -> float:
        """Simulation time [s] of keyframe ``index``."""
        return self.step_time_s(index * self.keyframe_interval_steps)

    # -- readings ------------------------------------------------------------------------

    def landmark_reading(self, landmark_id: int, range_m: float,
                         bearing_rad: float) -> LandmarkReading:
        """A sonar reading as received: float32 range and bearing, the shared variances."""
        return LandmarkReading(int(landmark_id), to_float32(range_m), to_float32(bearing_rad),
                               self.range_variance, self.bearing_variance)

    def teammate_reading(self, robot_id: int, relative_pose: np.ndarray) -> TeammateReading:
        """A teammate reading as received: float32 pose, the shared covariance."""
        return TeammateReading(int(robot_id), float32_vector(relative_pose),
                               self.teammate_covariance.copy())

    # -- records -------------------------------------------------------------------------

    def keyframe(self, keyframe: KeyframeMeasurements) -> KeyframeMeasurements:
        """``keyframe`` exactly as its receivers rebuild it from the wire (its late readings
        in the order the wire carries them: grouped by the keyframe they are of)."""
        if keyframe.is_first:
            delta, covariance = np.zeros(3), np.zeros((3, 3))
        else:
            delta = float32_vector(keyframe.odom_delta)
            covariance = covariance_from_upper(float32_vector(
                covariance_upper(keyframe.odom_covariance)))
        return replace(
            keyframe, stamp_s=self.keyframe_time_s(keyframe.index), odom_delta=delta,
            odom_covariance=covariance,
            landmarks=tuple(self.landmark_reading(r.landmark_id, r.range_m, r.bearing_rad)
                            for r in keyframe.landmarks),
            teammates=tuple(self.teammate_reading(r.robot_id, r.relative_pose)
                            for r in keyframe.teammates),
            late_landmarks=tuple(LateReading(late.keyframe_index, self.landmark_reading(
                late.reading.landmark_id, late.reading.range_m, late.reading.bearing_rad))
                for group in late_groups(keyframe) for late in group))

    @staticmethod
    def target(target: TargetRecord) -> TargetRecord:
        """``target`` exactly as its receivers rebuild it from the wire (float32 planning
        time; its stamp is the update's, which the sender publishes at the same step)."""
        return replace(target, planning_time_s=to_float32(target.planning_time_s))


def late_groups(keyframe: KeyframeMeasurements) -> list[list[LateReading]]:
    """The keyframe's late readings grouped by the keyframe they are of, in the order of
    first appearance: on the wire each group is one more entry of the update's keyframes
    (``Keyframe.LATE_READINGS`` as its previous index), after the keyframe that carries it."""
    groups: dict[int, list[LateReading]] = {}
    for late in keyframe.late_landmarks:
        groups.setdefault(late.keyframe_index, []).append(late)
    return list(groups.values())


#: The encapsulation header in front of every serialized ROS 2 message [bytes].
CDR_ENCAPSULATION_BYTES = 4


class _CdrLayout:
    """Offset bookkeeping of classic CDR: every primitive is aligned to its own size,
    counted from the start of the payload (after the encapsulation header)."""

    def __init__(self) -> None:
        self.offset = 0

    def add(self, size: int, count: int = 1) -> None:
        """``count`` primitives of ``size`` bytes each (an array of them)."""
        self.offset += -self.offset % size + size * count


def cdr_size(update: TeamUpdate) -> int:
    """Bytes of ``update`` as a serialized em_exploration_msgs/TeamUpdate (CDR with its
    encapsulation header): what DDS carries per update, without RTPS and UDP/IP headers.
    Equal to ``len(rclpy.serialization.serialize_message(team_update_to_msg(update)))``."""
    cdr = _CdrLayout()
    cdr.add(8)  # run_id
    cdr.add(4, 2)  # step, sequence
    cdr.add(1, 2)  # robot_id, finished
    cdr.add(4)  # keyframes length
    for keyframe in update.keyframes:
        for landmarks, teammates in ((len(keyframe.landmarks), len(keyframe.teammates)),
                                     *((len(group), 0) for group in late_groups(keyframe))):
            cdr.add(4, 2 + 3 + 6)  # index, previous_index, odometry, covariance upper triangle
            cdr.add(4, 1 + 3 * landmarks)  # length; id, range, bearing each
            cdr.add(4, 1 + 4 * teammates)  # length; id, x, y, theta each
    cdr.add(4)  # targets length
    for _ in update.targets:
        cdr.add(4, 2)  # decision_index, partner_id
        cdr.add(8, 2)  # x, y
        cdr.add(4)  # planning_time
        cdr.add(1, 2)  # frontier_type, planner_failed
    cdr.add(4)  # rendezvous length
    for _ in update.rendezvous:
        cdr.add(4, 2 + 4)  # stamp (sec, nanosec); rendezvous, requester, partner, sender ids
        cdr.add(1)  # state
        cdr.add(8, 3)  # x, y, timeout
    return CDR_ENCAPSULATION_BYTES + cdr.offset


def request_cdr_size() -> int:
    """Bytes of a serialized em_exploration_msgs/TeamUpdateRequest as robots send it (empty
    ``header.frame_id``), encapsulation header included: what one gap request costs a
    link's budget (``core/links/link_model.py``)."""
    cdr = _CdrLayout()
    cdr.add(4, 2)  # header.stamp (sec, nanosec)
    cdr.add(4)  # header.frame_id length
    cdr.add(1)  # its terminating NUL
    cdr.add(8)  # run_id
    cdr.add(4, 2)  # requester_id, robot_id
    cdr.add(8, 2)  # first_sequence, last_sequence
    return CDR_ENCAPSULATION_BYTES + cdr.offset
