"""The team update stream: validation, in-order delivery, gaps, duplicates, re-sending."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      LateReading, TeammateReading)
from em_exploration_ros.core.records.team_data import (MAX_SEQUENCE_LEAD, MAX_TARGETS_PER_UPDATE,
                                                       FrontierType, InvalidTeamUpdate,
                                                       MissingRange, TargetRecord, TeamUpdate,
                                                       TeamUpdateInbox,
                                                       TeamUpdateOutbox, validate_team_update)

NUM_ROBOTS = 3


def keyframe(robot_id: int = 1, index: int = 2, odom=(2.0, 0.0, 0.1),
             covariance=np.diag([1e-4, 1e-4, 1e-5]), landmark_id: int = 3) -> KeyframeMeasurements:
    return KeyframeMeasurements(
        robot_id=robot_id, index=index, stamp_s=4.0, is_first=False, previous_index=index - 1,
        odom_delta=np.array(odom), odom_covariance=covariance,
        landmarks=(LandmarkReading(landmark_id, 5.0, 0.2, 1e-6, 1e-5),),
        teammates=(TeammateReading((robot_id + 1) % NUM_ROBOTS, np.array([3.0, 1.0, 0.2]),
                                   np.eye(3) * 1e-6),))


def updates_from(robot_id: int, count: int) -> list:
    outbox = TeamUpdateOutbox(robot_id)
    return [outbox.publish(float(i), keyframes=(keyframe(robot_id, i + 1),)) for i in range(count)]


def test_outbox_numbers_from_one_and_resends_ranges():
    outbox = TeamUpdateOutbox(2)
    sent = [outbox.publish(float(i)) for i in range(5)]
    assert [u.sequence for u in sent] == [1, 2, 3, 4, 5]
    assert outbox.last_sequence == 5
    assert [u.sequence for u in outbox.resend(2, 3)] == [2, 3]
    assert [u.sequence for u in outbox.resend(4, 0)] == [4, 5]
    assert outbox.resend(9, 12) == []


def test_inbox_delivers_in_order_and_ignores_duplicates():
    inbox = TeamUpdateInbox(own_robot_id=0, num_robots=NUM_ROBOTS)
    first, second, third, fourth = updates_from(1, 4)
    assert inbox.receive(third) and inbox.receive(first)
    assert inbox.pop_ready() == [first]  # 2 is missing: 3 waits
    assert inbox.missing() == [MissingRange(1, 2, 2)]
    assert not inbox.receive(first)  # duplicate of an applied update
    assert inbox.receive(second)
    assert not inbox.receive(second)  # duplicate of a buffered update
    assert inbox.pop_ready() == [second, third]
    assert inbox.missing() == []
    assert inbox.receive(fourth) and inbox.pop_ready() == [fourth]  # 4 is next


def test_inbox_barrier_limits_release_and_reports_known_gaps():
    inbox = TeamUpdateInbox(own_robot_id=2, num_robots=NUM_ROBOTS)
    for update in updates_from(0, 3):
        inbox.receive(update)
    assert not inbox.holds_up_to({0: 3, 1: 1})  # nothing from robot 1 yet
    assert inbox.missing(known_latest={1: 2}) == [MissingRange(1, 1, 2)]
    assert [u.sequence for u in inbox.pop_ready({0: 2, 1: 0})] == [1, 2]
    assert [u.sequence for u in inbox.pop_ready({0: 3})] == [3]


def test_inbox_rejects_own_id_and_implausible_sequence():
    inbox = TeamUpdateInbox(own_robot_id=1, num_robots=NUM_ROBOTS)
    with pytest.raises(InvalidTeamUpdate, match="this robot"):
        inbox.receive(updates_from(1, 1)[0])
    far = updates_from(0, 1)[0]
    far = type(far)(far.robot_id, 10**9, far.stamp_s, far.keyframes)
    with pytest.raises(InvalidTeamUpdate, match="implausibly far"):
        inbox.receive(far)
    assert inbox.missing() == []  # the rejected update opened no gap


@pytest.mark.parametrize("corrupt, message", [
    (lambda u: dict(robot_id=7), "not a robot of this team"),
    (lambda u: dict(sequence=0), "sequence"),
    (lambda u: dict(stamp_s=math.nan), "stamp"),
    (lambda u: dict(keyframes=(keyframe(odom=(math.nan, 0.0, 0.0)),)), "odometry"),
    (lambda u: dict(keyframes=(keyframe(robot_id=2),)), "keyframe of robot 2"),
    (lambda u: dict(keyframes=(keyframe(covariance=-np.eye(3)),)), "not a covariance"),
    (lambda u: dict(targets=(TargetRecord(1, 0, 0.0, np.array([np.inf, 0.0]),
                                          FrontierType.EXPLORATION, None, 0.0),)), "target"),
    (lambda u: dict(targets=(TargetRecord(1, 0, 0.0, np.zeros(2), FrontierType.EXPLORATION,
                                          1, 0.0),)), "EXPLORATION target with partner 1"),
    (lambda u: dict(targets=(TargetRecord(1, 0, 0.0, np.zeros(2), FrontierType.RENDEZVOUS,
                                          None, 0.0),)), "rendezvous target without"),
    (lambda u: dict(targets=(TargetRecord(1, 0, 0.0, np.zeros(2), FrontierType.RENDEZVOUS,
                                          1, 0.0),)), "robot itself as partner"),
    (lambda u: dict(targets=(TargetRecord(1, 0, 0.0, np.zeros(2), FrontierType.RENDEZVOUS,
                                          9, 0.0),)), "partner id 9 is not a robot"),
    (lambda u: dict(targets=(TargetRecord(1, 2**32 - 1, 0.0, np.zeros(2),
                                          FrontierType.EXPLORATION, None, 0.0),)),
     "decision index"),
    (lambda u: dict(keyframes=(keyframe(odom=(1e300, 0.0, 0.0)),)), "implausibly large"),
    (lambda u: dict(keyframes=(keyframe(landmark_id=2**32 - 1),)), "landmark id"),
    (lambda u: dict(targets=(TargetRecord(1, 0, 1.0, np.zeros(2), FrontierType.EXPLORATION,
                                          None, 0.0),)), "not its update's"),
    (lambda u: dict(targets=tuple(TargetRecord(1, i, 0.0, np.zeros(2), FrontierType.EXPLORATION,
                                               None, 0.0)
                                  for i in range(MAX_TARGETS_PER_UPDATE + 1))), "at most"),
])
def test_validation_rejects_malformed_updates(corrupt, message):
    good = updates_from(1, 1)[0]
    validate_team_update(good, NUM_ROBOTS)
    fields = dict(robot_id=good.robot_id, sequence=good.sequence, stamp_s=good.stamp_s,
                  keyframes=good.keyframes, targets=good.targets,
                  rendezvous=good.rendezvous)
    fields.update(corrupt(good))
    with pytest.raises(InvalidTeamUpdate, match=message):
        validate_team_update(type(good)(**fields), NUM_ROBOTS)


def test_sender_must_match_and_observers_read_every_stream():
    observer = TeamUpdateInbox(own_robot_id=None, num_robots=NUM_ROBOTS)
    update = updates_from(2, 1)[0]
    with pytest.raises(InvalidTeamUpdate, match="robot_id 2 on robot 1's topic"):
        observer.receive(update, sender=1)
    assert observer.receive(update, sender=2)
    assert observer.receive(updates_from(0, 1)[0], sender=0)
    assert [u.robot_id for u in observer.pop_ready()] == [0, 2]


def test_huge_claimed_sequence_numbers_cost_nothing_and_open_bounded_gaps():
    """A barrier or command naming sequence 2**63 (hostile or corrupt) neither loops over
    the range (issue 11: 100 % CPU forever) nor asks for more than MAX_SEQUENCE_LEAD."""
    inbox = TeamUpdateInbox(own_robot_id=0, num_robots=NUM_ROBOTS)
    first, _, third = updates_from(1, 3)
    inbox.receive(first)
    inbox.receive(third)
    assert not inbox.holds_up_to({1: 2**63, 2: 2**63})
    gaps = inbox.missing(known_latest={1: 2**63, 2: 2**64 - 1})
    assert gaps == [MissingRange(1, 2, 2), MissingRange(1, 4, 1 + MAX_SEQUENCE_LEAD),
                    MissingRange(2, 1, 1 + MAX_SEQUENCE_LEAD)]
    assert inbox.holds_up_to({1: 1, 2: 0})


def test_records_given_up_on_are_not_waited_for_again_until_they_arrive():
    """A restarted robot missed record 27 of a teammate that died right after sending it:
    after barrier_timeout_s it goes on (``waive``), and must not wait 10 s again at every
    later step for a record only the dead robot could re-send."""
    inbox = TeamUpdateInbox(0, 3)
    streams = {robot: updates_from(robot, 4) for robot in (1, 2)}
    for robot in (1, 2):
        for update in streams[robot][:2]:
            inbox.receive(update)
    inbox.pop_ready()
    assert not inbox.holds_up_to({1: 3, 2: 2})
    inbox.waive({1: 3, 2: 2})
    assert inbox.holds_up_to({1: 3, 2: 2}) and inbox.holds_up_to({1: 5, 2: 2})
    assert not inbox.holds_up_to({1: 5, 2: 3})  # robot 2 is still waited for
    # They are still asked for (a waiver that stopped the requests left a restarted robot
    # without its teammate's stream, and so without a pose, for the rest of a run).
    assert inbox.waived() == {1: 3}
    assert inbox.missing(inbox.waived()) == [MissingRange(1, 3, 3)]
    # Once record 3 arrives robot 1 is waited for again.
    inbox.receive(streams[1][2])
    inbox.pop_ready()
    assert inbox.waived() == {}
    assert not inbox.holds_up_to({1: 4, 2: 2})
    inbox.receive(streams[1][3])
    inbox.pop_ready()
    assert inbox.holds_up_to({1: 4, 2: 2})


def test_a_late_reading_must_be_of_an_earlier_keyframe():
    reading = LandmarkReading(3, 4.0, 0.1, 0.01, 0.001)
    for index in (5, 9, -1):
        keyframe = KeyframeMeasurements(1, 5, 10.0, False, 4, np.zeros(3), np.eye(3) * 1e-4,
                                        (), (), (LateReading(index, reading),))
        with pytest.raises(InvalidTeamUpdate, match="not an earlier one"):
            validate_team_update(TeamUpdate(1, 1, 10.0, (keyframe,)), 3)
    keyframe = KeyframeMeasurements(1, 5, 10.0, False, 4, np.zeros(3), np.eye(3) * 1e-4,
                                    (), (), (LateReading(4, reading),))
    validate_team_update(TeamUpdate(1, 1, 10.0, (keyframe,)), 3)
    bad = LateReading(4, LandmarkReading(3, -4.0, 0.1, 0.01, 0.001))
    with pytest.raises(InvalidTeamUpdate, match="negative range"):
        validate_team_update(TeamUpdate(1, 1, 10.0, (KeyframeMeasurements(
            1, 5, 10.0, False, 4, np.zeros(3), np.eye(3) * 1e-4, (), (), (bad,)),)), 3)
