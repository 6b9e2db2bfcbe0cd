"""What teammates share, as plain data, and the bookkeeping that keeps the stream whole.

Each robot publishes one ordered stream of ``TeamUpdate`` records: every record carries
what is new since the previous one (keyframes with their measurements, chosen targets,
rendezvous events) and a sequence number
(1, 2, 3, ...). A receiver applies records strictly in sequence order, buffers records
that arrive early, asks for the missing range again, and rejects malformed records
before they touch any state. These types mirror em_exploration_msgs/TeamUpdate; the
ROS nodes convert between the two (the wire form: ``team_wire``), em-sim passes them
directly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from em_exploration_ros.core.records.limits import MAX_ABS_VALUE, MAX_ID
from em_exploration_ros.core.records.readings import KeyframeMeasurements, LandmarkReading

#: Records further ahead of the expected sequence number than this are rejected as
#: implausible (a hostile or corrupted sender), instead of opening a huge gap. It also
#: bounds the records buffered per teammate and every range of sequence numbers looked at.
MAX_SEQUENCE_LEAD = 10_000
#: Most entries of each array in one record (a robot sends about one keyframe per update;
#: these bounds leave room for bulk re-sends and large teams and maps).
MAX_KEYFRAMES_PER_UPDATE = 1000
MAX_TARGETS_PER_UPDATE = 1000
MAX_RENDEZVOUS_PER_UPDATE = 1000
MAX_READINGS_PER_KEYFRAME = 1000
#: Most landmark estimates in one robot's /robot_<i>/landmarks message.
MAX_LANDMARKS_PER_UPDATE = 1000


class FrontierType(IntEnum):
    """Kind of a candidate target; same values as ``em_exploration_msgs/TargetRecord``."""

    EXPLORATION = 0
    REVISITING = 1
    RENDEZVOUS = 2


class RendezvousState(IntEnum):
    """Rendezvous coordination events (values of em_exploration_msgs/Rendezvous.state)."""

    REQUEST = 0
    ARRIVED = 1
    RELEASE = 2


@dataclass(frozen=True)
class LandmarkEstimate:
    """A landmark position estimate in the map frame with its 2x2 covariance [m^2]."""

    landmark_id: int
    position: np.ndarray  # (2,)
    covariance: np.ndarray  # (2, 2)


@dataclass(frozen=True)
class TargetRecord:
    """A target chosen by a robot's planner (map frame).

    ``partner_id``: the teammate to meet for a RENDEZVOUS target, None for every other
    target. ``planning_time_s``: wall time of the whole decision [s] (map rebuild,
    candidates and planner). ``stamp_s`` is the time of the update that carries it (the
    decision's step).
    """

    robot_id: int
    decision_index: int
    stamp_s: float
    position: np.ndarray  # (2,) [m]
    kind: FrontierType
    partner_id: int | None
    planning_time_s: float
    planner_failed: bool = False


@dataclass(frozen=True)
class RendezvousEvent:
    """One rendezvous coordination event (map frame meeting point)."""

    rendezvous_id: int
    requester_id: int
    partner_id: int
    sender_id: int
    state: RendezvousState
    stamp_s: float
    meeting_point: np.ndarray  # (2,) [m]
    timeout_s: float


@dataclass(frozen=True)
class TeamUpdate:
    """Everything new from one robot since its previous update."""

    robot_id: int
    sequence: int
    stamp_s: float
    keyframes: tuple[KeyframeMeasurements, ...] = ()
    targets: tuple[TargetRecord, ...] = ()
    rendezvous: tuple[RendezvousEvent, ...] = ()
    finished: bool = False


class InvalidTeamUpdate(ValueError):
    """A received team update that must be rejected; the message says why."""


def validate_team_update(update: TeamUpdate, num_robots: int) -> None:
    """Raise ``InvalidTeamUpdate`` if ``update`` is malformed for a team of ``num_robots``.

    Checks robot ids and other ids, sequence numbers, array sizes, that every number is
    finite and of plausible magnitude, shapes, and that covariances are symmetric with a
    non-negative diagonal.
    """
    _check_robot_id(update.robot_id, num_robots, "robot_id")
    if update.sequence < 1:
        raise InvalidTeamUpdate(f"sequence must be >= 1, got {update.sequence}")
    _check_finite(update.stamp_s, "stamp")
    check_record_sizes(len(update.keyframes), len(update.targets), len(update.rendezvous))
    for kf in update.keyframes:
        if kf.robot_id != update.robot_id:
            raise InvalidTeamUpdate(
                f"keyframe of robot {kf.robot_id} inside an update of robot {update.robot_id}")
        if not 0 <= kf.index <= MAX_ID or (
                not kf.is_first and not 0 <= kf.previous_index < kf.index):
            raise InvalidTeamUpdate(f"keyframe {kf.index}: bad previous index {kf.previous_index}")
        _check_size(len(kf.landmarks) + len(kf.teammates) + len(kf.late_landmarks),
                    MAX_READINGS_PER_KEYFRAME, "readings in a keyframe")
        _check_finite(kf.stamp_s, "keyframe stamp")
        _check_vector(kf.odom_delta, 3, "odometry")
        _check_covariance(kf.odom_covariance, 3, "odometry covariance")
        for reading in kf.landmarks:
            _check_landmark_reading(reading)
        for late in kf.late_landmarks:
            if not 0 <= late.keyframe_index < kf.index:
                raise InvalidTeamUpdate(f"keyframe {kf.index}: a late reading of keyframe "
                                        f"{late.keyframe_index}, not an earlier one")
            _check_landmark_reading(late.reading)
        for reading in kf.teammates:
            _check_robot_id(reading.robot_id, num_robots, "observed teammate id")
            if reading.robot_id == update.robot_id:
                raise InvalidTeamUpdate("a robot cannot observe itself")
            _check_vector(reading.relative_pose, 3, "teammate relative pose")
            _check_covariance(reading.covariance, 3, "teammate covariance")
    for target in update.targets:
        if target.robot_id != update.robot_id:
            raise InvalidTeamUpdate("target of another robot inside an update")
        _check_partner(target, num_robots)
        _check_id(target.decision_index, "decision index")
        _check_vector(target.position, 2, "target position")
        if target.stamp_s != update.stamp_s:
            raise InvalidTeamUpdate(f"target stamp {target.stamp_s} is not its update's "
                                    f"{update.stamp_s} (a decision travels at its step)")
    for event in update.rendezvous:
        for name in ("requester_id", "partner_id", "sender_id"):
            _check_robot_id(getattr(event, name), num_robots, f"rendezvous {name}")
        _check_id(event.rendezvous_id, "rendezvous id")
        if event.sender_id != update.robot_id:
            raise InvalidTeamUpdate("rendezvous event sent on behalf of another robot")
        _check_vector(event.meeting_point, 2, "meeting point")
        _check_finite(event.timeout_s, "rendezvous timeout")
        if event.timeout_s < 0.0:
            raise InvalidTeamUpdate(f"negative rendezvous timeout {event.timeout_s}")


def check_record_sizes(keyframes: int, targets: int, rendezvous: int) -> None:
    """Raise ``InvalidTeamUpdate`` if a record's arrays are longer than plausible (the
    ``MAX_*_PER_UPDATE`` bounds); cheap, so receivers call it before converting a message."""
    for size, limit, what in ((keyframes, MAX_KEYFRAMES_PER_UPDATE, "keyframes"),
                              (targets, MAX_TARGETS_PER_UPDATE, "targets"),
                              (rendezvous, MAX_RENDEZVOUS_PER_UPDATE, "rendezvous")):
        _check_size(size, limit, what)


def _check_landmark_reading(reading: LandmarkReading) -> None:
    """A landmark reading's id, finite range and bearing, positive variances."""
    _check_id(reading.landmark_id, "landmark id")
    _check_finite(reading.range_m, "landmark range")
    _check_finite(reading.bearing_rad, "landmark bearing")
    if reading.range_m < 0 or reading.range_variance <= 0 or reading.bearing_variance <= 0:
        raise InvalidTeamUpdate("landmark reading with negative range or variance <= 0")
    _check_finite(reading.range_variance + reading.bearing_variance, "landmark variance")


def _check_partner(target: TargetRecord, num_robots: int) -> None:
    """A RENDEZVOUS target names a teammate to meet; every other target has no partner."""
    if target.kind != FrontierType.RENDEZVOUS:
        if target.partner_id is not None:
            raise InvalidTeamUpdate(f"{target.kind.name} target with partner {target.partner_id}")
        return
    if target.partner_id is None:
        raise InvalidTeamUpdate("rendezvous target without a partner")
    _check_robot_id(target.partner_id, num_robots, "target partner id")
    if target.partner_id == target.robot_id:
        raise InvalidTeamUpdate("rendezvous target with the robot itself as partner")


def _check_robot_id(robot_id: int, num_robots: int, what: str) -> None:
    if not 0 <= robot_id < num_robots:
        raise InvalidTeamUpdate(
            f"{what} {robot_id} is not a robot of this team (0..{num_robots - 1})")


def _check_id(value: int, what: str) -> None:
    if not 0 <= value <= MAX_ID:
        raise InvalidTeamUpdate(f"{what} {value} is not in 0..{MAX_ID}")


def _check_size(size: int, limit: int, what: str) -> None:
    if size > limit:
        raise InvalidTeamUpdate(f"{size} {what} in one record (at most {limit})")


def _check_finite(value: float, what: str) -> None:
    if not math.isfinite(value):
        raise InvalidTeamUpdate(f"{what} is not finite ({value})")
    if abs(value) > MAX_ABS_VALUE:
        raise InvalidTeamUpdate(f"{what} is implausibly large ({value:g})")


def _check_vector(value: np.ndarray, size: int, what: str) -> None:
    array = np.asarray(value, dtype=float)
    if array.shape != (size,):
        raise InvalidTeamUpdate(f"{what} must have {size} elements, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidTeamUpdate(f"{what} is not finite: {array.tolist()}")
    if np.any(np.abs(array) > MAX_ABS_VALUE):
        raise InvalidTeamUpdate(f"{what} is implausibly large: {array.tolist()}")


def _check_covariance(value: np.ndarray, size: int, what: str) -> None:
    array = np.asarray(value, dtype=float)
    if array.shape != (size, size):
        raise InvalidTeamUpdate(f"{what} must be {size}x{size}, got shape {array.shape}")
    if not np.all(np.isfinite(array)) or np.any(np.abs(array) > MAX_ABS_VALUE):
        raise InvalidTeamUpdate(f"{what} is not finite or implausibly large")
    if np.any(np.diag(array) < 0) or not np.allclose(array, array.T, rtol=1e-6, atol=1e-12):
        raise InvalidTeamUpdate(f"{what} is not a covariance (asymmetric or negative variance)")


@dataclass
class _PeerStream:
    """Receive state of one teammate's update stream."""

    next_sequence: int = 1
    early: dict[int, TeamUpdate] = field(default_factory=dict)


@dataclass(frozen=True)
class MissingRange:
    """A range of a teammate's sequence numbers to ask for again (inclusive)."""

    robot_id: int
    first_sequence: int
    last_sequence: int


class TeamUpdateInbox:
    """Orders the teammates' update streams: in-sequence delivery, gaps detected.

    ``receive`` validates a record and files it; ``pop_ready(limits)`` returns, in robot
    id then sequence order, every record that is next in its stream (optionally only up
    to a per-robot sequence limit, the lockstep barrier); ``missing()`` lists the gaps
    to request again.
    """

    def __init__(self, own_robot_id: int | None, num_robots: int) -> None:
        """``own_robot_id``: the receiving robot (its own stream is refused), or None for an
        observer such as the evaluator that reads every robot's stream."""
        self._own = own_robot_id
        self._num_robots = num_robots
        self._streams = {robot: _PeerStream() for robot in range(num_robots)
                         if robot != own_robot_id}
        self._waived: dict[int, int] = {}

    def receive(self, update: TeamUpdate, sender: int | None = None) -> bool:
        """File one record, which arrived on robot ``sender``'s topic (if known).

        Returns False for a duplicate; raises InvalidTeamUpdate for a malformed record,
        one claiming another sender, or one from this robot itself.
        """
        if sender is not None and update.robot_id != sender:
            raise InvalidTeamUpdate(f"robot_id {update.robot_id} on robot {sender}'s topic")
        validate_team_update(update, self._num_robots)
        if update.robot_id == self._own:
            raise InvalidTeamUpdate(f"update claims to come from this robot ({self._own})")
        stream = self._streams[update.robot_id]
        if update.sequence < stream.next_sequence or update.sequence in stream.early:
            return False
        if update.sequence > stream.next_sequence + MAX_SEQUENCE_LEAD:
            raise InvalidTeamUpdate(
                f"sequence {update.sequence} of robot {update.robot_id} is implausibly far "
                f"ahead of the expected {stream.next_sequence}")
        stream.early[update.sequence] = update
        return True

    def pop_ready(self, limits: dict[int, int] | None = None) -> list[TeamUpdate]:
        """Records ready to apply, in robot id then sequence order.

        ``limits[robot]`` caps the sequence numbers released for that robot (lockstep
        barrier); robots missing from ``limits`` are not capped when ``limits`` is None
        and fully held back otherwise.
        """
        ready: list[TeamUpdate] = []
        for robot, stream in sorted(self._streams.items()):
            limit = None if limits is None else limits.get(robot, 0)
            while stream.next_sequence in stream.early and (
                    limit is None or stream.next_sequence <= limit):
                ready.append(stream.early.pop(stream.next_sequence))
                stream.next_sequence += 1
        return ready

    def holds_up_to(self, limits: dict[int, int]) -> bool:
        """True when every robot's records up to ``limits[robot]`` are received (a limit
        more than ``MAX_SEQUENCE_LEAD`` ahead can never be met), leaving out a robot while
        a gap ``waive`` gave up on is still open in its stream."""
        for robot, limit in limits.items():
            stream = self._streams.get(robot)
            if (stream is None or limit < stream.next_sequence
                    or stream.next_sequence <= self._waived.get(robot, 0)):
                continue
            needed = limit - stream.next_sequence + 1
            if needed > len(stream.early) or any(
                    seq not in stream.early for seq in range(stream.next_sequence, limit + 1)):
                return False
        return True

    def waive(self, limits: dict[int, int]) -> None:
        """Stop waiting for the records up to ``limits`` that are missing now (given up
        after a timeout: their sender may be dead): ``holds_up_to`` leaves that robot out
        until its stream has them, instead of waiting for them again at every step."""
        for robot, limit in limits.items():
            stream = self._streams.get(robot)
            if stream is not None and stream.next_sequence <= limit:
                self._waived[robot] = max(self._waived.get(robot, 0), limit)

    def waived(self) -> dict[int, int]:
        """Robot -> the limit of a gap ``waive`` gave up on that is still open (records to
        keep asking for)."""
        return {robot: limit for robot, limit in self._waived.items()
                if self._streams[robot].next_sequence <= limit}

    def held_back(self, robot_id: int) -> list[TeamUpdate]:
        """Records of ``robot_id`` received in sequence after the last one released but not
        released yet (the lockstep barrier holds them back until the world counts them), in
        order; empty for this robot or an unknown id. A robot that restarts after it
        published them and before the world counted them must get them back with its
        earlier records, or its new process numbers new records with their sequence numbers,
        and a teammate takes each new record for a duplicate of the one it holds."""
        stream = self._streams.get(robot_id)
        if stream is None:
            return []
        records = []
        sequence = stream.next_sequence
        while sequence in stream.early:
            records.append(stream.early[sequence])
            sequence += 1
        return records

    def next_expected(self, robot_id: int) -> int:
        """The next sequence number expected from ``robot_id``."""
        return self._streams[robot_id].next_sequence

    def missing(self, known_latest: dict[int, int] | None = None) -> list[MissingRange]:
        """Gaps to request again: before buffered early records, and up to ``known_latest``
        (capped at ``MAX_SEQUENCE_LEAD`` past the expected number, so that an implausible
        claim never makes a huge range). Costs O(buffered records), whatever the numbers."""
        gaps: list[MissingRange] = []
        for robot, stream in sorted(self._streams.items()):
            expected = stream.next_sequence
            latest = max(stream.early, default=expected - 1)
            if known_latest is not None:
                claimed = min(known_latest.get(robot, 0), expected + MAX_SEQUENCE_LEAD)
                latest = max(latest, claimed)
            first = expected
            for seq in sorted(stream.early):
                if seq > first:
                    gaps.append(MissingRange(robot, first, seq - 1))
                first = seq + 1
            if first <= latest:
                gaps.append(MissingRange(robot, first, latest))
        return gaps


class TeamUpdateOutbox:
    """Numbers this robot's outgoing updates and keeps them for re-sending on request."""

    def __init__(self, robot_id: int) -> None:
        self._robot_id = robot_id
        self._sent: list[TeamUpdate] = []

    @property
    def last_sequence(self) -> int:
        """Sequence number of the latest update (0 before the first)."""
        return len(self._sent)

    def publish(self, stamp_s: float, keyframes: tuple[KeyframeMeasurements, ...] = (),
                targets: tuple[TargetRecord, ...] = (),
                rendezvous: tuple[RendezvousEvent, ...] = (),
                finished: bool = False) -> TeamUpdate:
        """Create, number and remember the next update."""
        update = TeamUpdate(self._robot_id, self.last_sequence + 1, stamp_s, keyframes,
                            targets, rendezvous, finished)
        self._sent.append(update)
        return update

    def restore(self, history: list[TeamUpdate], through_sequence: int = 0) -> None:
        """Take back this robot's earlier records (sequence 1..n, in order, e.g. relayed by
        teammates after a restart): re-sending serves them and numbering continues at n+1.

        Records after n up to ``through_sequence`` were sent by the earlier process but no
        teammate gave them back: they are kept as empty records (no keyframes, targets or
        events; the last record's stamp), so that numbering continues after every sequence
        number already used and a teammate missing one gets an empty record instead of
        waiting for it for ever."""
        for expected, update in enumerate(history, start=1):
            if update.robot_id != self._robot_id or update.sequence != expected:
                raise ValueError(f"history record {update.robot_id}/{update.sequence} is not "
                                 f"record {expected} of robot {self._robot_id}")
        self._sent = list(history)
        stamp_s = history[-1].stamp_s if history else 0.0
        self._sent += [TeamUpdate(self._robot_id, sequence, stamp_s)
                       for sequence in range(len(history) + 1, through_sequence + 1)]

    def resend(self, first_sequence: int, last_sequence: int) -> list[TeamUpdate]:
        """Stored updates with sequence in [first, last] (last = 0: up to the latest)."""
        last = self.last_sequence if last_sequence == 0 else min(last_sequence,
                                                                 self.last_sequence)
        first = max(first_sequence, 1)
        return self._sent[first - 1:last]
