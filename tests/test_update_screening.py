"""Screening a serialized team update by its head (core/records/update_screening.py): what
a receiver reads, ignores or drops before it deserializes anything."""
from __future__ import annotations

from em_exploration_msgs.msg import Keyframe, TeamUpdate
from rclpy.serialization import serialize_message

from em_exploration_ros.core.records.update_screening import (IGNORE, READ, Screening,
                                                              TeamUpdateHead, only_sender,
                                                              screen_team_update, team_member,
                                                              team_update_head)

RUN = 7


def of_run(run_id: int) -> str | None:
    return None if run_id == RUN else f"of run {run_id}"


def record(**fields) -> bytes:
    return serialize_message(TeamUpdate(**{"run_id": RUN, "robot_id": 1, **fields}))


def test_team_update_head_is_read_from_the_bytes_in_either_byte_order():
    message = TeamUpdate(run_id=2**64 - 2, step=7, sequence=2**32 - 1, robot_id=2,
                         keyframes=[Keyframe()] * 3)
    data = serialize_message(message)
    assert team_update_head(data) == TeamUpdateHead(2**64 - 2, 2**32 - 1, 2, 3)
    big_endian = (b"\x00\x00\x00\x00" + (2**64 - 2).to_bytes(8, "big") + (7).to_bytes(4, "big")
                  + (2**32 - 1).to_bytes(4, "big") + b"\x02\x00\x00\x00" + (3).to_bytes(4, "big"))
    assert team_update_head(big_endian) == TeamUpdateHead(2**64 - 2, 2**32 - 1, 2, 3)
    assert team_update_head(data[:27]) is None
    assert team_update_head(b"\x00\x02" + data[2:]) is None  # not plain CDR


def test_a_robot_topic_reads_its_own_records_of_this_run_within_bounds():
    expected = {1: 5}

    def screen(data: bytes) -> Screening:
        return screen_team_update(data, of_run, only_sender(1), expected.__getitem__)

    assert screen(record(run_id=8, sequence=5)) == Screening(False, "of run 8")
    assert "robot_id 2 on robot 1's topic" in screen(record(robot_id=2, sequence=5)).problem
    assert "keyframes" in screen(record(sequence=5, keyframes=[Keyframe()] * 1001)).problem
    assert "implausibly far ahead of the expected 5" in screen(record(sequence=10_006)).problem
    assert screen(record(sequence=10_005)) == READ
    assert screen(record(sequence=4, keyframes=[Keyframe()] * 400)) == IGNORE  # held, 20 kB
    assert screen(record(sequence=4, keyframes=[Keyframe()] * 300)) == READ  # held, 15 kB
    assert screen(b"\x00\x01\x00") == Screening(False, "malformed TeamUpdate: 3 bytes")


def test_a_topic_of_the_whole_team_reads_any_member_and_asks_no_sequence():
    """The links' deliveries carry any robot's records (this robot's own copies too); the
    sequence is not asked for a robot whose stream the receiver does not keep."""
    def screen(data: bytes) -> Screening:
        return screen_team_update(data, of_run, team_member(3))

    assert screen(record(robot_id=0, sequence=50_000)) == READ
    assert screen(record(robot_id=2, keyframes=[Keyframe()] * 400)) == READ
    assert "robot_id 3 is not in the team of 3" in screen(record(robot_id=3)).problem


def test_the_owner_is_checked_before_the_sequence_is_looked_up():
    """A hostile robot id never reaches ``next_expected`` (a receiver's stream table)."""
    asked: list[int] = []

    def next_expected(robot_id: int) -> int:
        asked.append(robot_id)
        return 1

    screen_team_update(record(robot_id=200), of_run, team_member(3), next_expected)
    screen_team_update(record(robot_id=2), of_run, team_member(3), next_expected)
    assert asked == [2]
