"""Screening a serialized team update by its head, before anything reads the rest.

A team update (em_exploration_msgs/TeamUpdate) opens with fixed fields: its run, its step
and sequence number, its sender and how many keyframes follow. Deserializing a whole
record with thousands of nested messages took rclpy 30-180 ms; under a flood of them every
robot fell tens of seconds behind the lockstep barrier. ``screen_team_update`` reads only
the head (plain CDR at fixed offsets, a few microseconds) and says whether the receiver
should read the record, ignore it without a word, or drop it for a reason it logs. The
rules are the receiver's own checks, applied early: of this run, a record of a robot the
topic may carry, at most ``MAX_KEYFRAMES_PER_UPDATE`` keyframes, not implausibly far ahead
of the next sequence number expected, and not a long copy of a record already held.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable

from em_exploration_ros.core.records.limits import MAX_HELD_RECORD_READ_BYTES
from em_exploration_ros.core.records.team_data import (MAX_SEQUENCE_LEAD, InvalidTeamUpdate,
                                                       check_record_sizes)

#: CDR offsets [B] after the 4-byte encapsulation header: run_id (uint64) at 4, step and
#: sequence (uint32) at 12 and 16, robot_id (uint8) at 20, finished at 21, the keyframes'
#: count (uint32, aligned) at 24.
_HEAD_FORMAT = "Q4xIB3xI"
_HEAD_SIZE = 4 + struct.calcsize("<" + _HEAD_FORMAT)


@dataclass(frozen=True)
class TeamUpdateHead:
    """The fixed fields that open a serialized em_exploration_msgs/TeamUpdate: its run, its
    sequence number, its sender (the robot whose stream the record is of) and how many
    keyframes follow."""

    run_id: int
    sequence: int
    robot_id: int
    keyframes: int


@dataclass(frozen=True)
class Screening:
    """What a receiver does with a serialized team update: ``read`` it (deserialize and
    check the whole record), or not; when not, ``problem`` is the reason to log (None: the
    record is ignored without a line, as the receiver ignores one it already holds)."""

    read: bool
    problem: str | None = None


READ = Screening(True)
IGNORE = Screening(False)


def team_update_head(data: bytes) -> TeamUpdateHead | None:
    """The head of a serialized TeamUpdate (little- or big-endian CDR), read without
    deserializing the rest; None if the bytes are too short or not plain CDR."""
    if len(data) < _HEAD_SIZE or data[0] != 0 or data[1] > 1:
        return None
    run_id, sequence, robot_id, keyframes = struct.unpack_from(
        ("<" if data[1] else ">") + _HEAD_FORMAT, data, 4)
    return TeamUpdateHead(run_id, sequence, robot_id, keyframes)


def only_sender(sender: int) -> Callable[[int], str | None]:
    """The owner check of robot ``sender``'s own topic: it carries only ``sender``'s records."""
    def owner_problem(owner: int) -> str | None:
        if owner != sender:
            return f"rejected a team update: robot_id {owner} on robot {sender}'s topic"
        return None
    return owner_problem


def team_member(num_robots: int) -> Callable[[int], str | None]:
    """The owner check of a topic that carries records of any robot of a team of
    ``num_robots`` (the links' deliveries to a robot)."""
    def owner_problem(owner: int) -> str | None:
        if not 0 <= owner < num_robots:
            return f"rejected a team update: robot_id {owner} is not in the team of {num_robots}"
        return None
    return owner_problem


def screen_team_update(data: bytes, run_problem: Callable[[int], str | None],
                       owner_problem: Callable[[int], str | None],
                       next_expected: Callable[[int], int] | None = None) -> Screening:
    """Whether to read a serialized team update, from its head alone.

    ``run_problem(run_id)`` is the receiver's run check; ``owner_problem(robot_id)`` says
    why the topic may not carry a record of that robot's stream (``only_sender`` for a
    robot's own topic); ``next_expected(robot_id)``, when the receiver keeps that robot's
    stream, is the next sequence number it expects (called only for an owner that passed).
    A record already held (below that number) and longer than
    ``MAX_HELD_RECORD_READ_BYTES`` is ignored unread (a shorter one is still read, so that
    its faults are named); one more than ``MAX_SEQUENCE_LEAD`` ahead is dropped.
    """
    head = team_update_head(data)
    if head is None:
        return Screening(False, f"malformed TeamUpdate: {len(data)} bytes")
    problem = run_problem(head.run_id) or owner_problem(head.robot_id)
    if problem is None:
        try:
            check_record_sizes(head.keyframes, 0, 0)
        except InvalidTeamUpdate as error:
            problem = f"rejected a team update: {error}"
    if problem is not None:
        return Screening(False, problem)
    if next_expected is None:
        return READ
    expected = next_expected(head.robot_id)
    if head.sequence < expected and len(data) > MAX_HELD_RECORD_READ_BYTES:
        return IGNORE
    if head.sequence > expected + MAX_SEQUENCE_LEAD:
        return Screening(False, f"rejected a team update: sequence {head.sequence} of robot "
                                f"{head.robot_id} is implausibly far ahead of the expected "
                                f"{expected}")
    return READ
