"""The largest valid serialized form [B] of the small fixed messages the nodes read raw.

A node drops a message longer than its topic's largest valid one before deserializing it
(``input_guard.size_limited``): a hostile writer's strings can make any message long, and
rclpy spent its time deserializing them while the middleware queued the rest of a flood.
A request and a motion command hold no unbounded field but their header's frame id: the
team's own messages name ``<robot>/base_link`` or nothing; ``FRAME_ID_ROOM`` characters are
allowed, so a frame a person or another tool sets is still read and its frame checked.
"""
from __future__ import annotations

import functools

from em_exploration_msgs.msg import GivenUpTarget, Meeting, MotionCommand, TeamUpdateRequest
from std_msgs.msg import Header

from em_exploration_ros.nodes.input_guard import serialized_size

#: Characters of a header's frame id a bounded message may carry.
FRAME_ID_ROOM = 128


@functools.lru_cache(maxsize=None)
def request_bytes() -> int:
    """Largest valid em_exploration_msgs/TeamUpdateRequest [B]."""
    return serialized_size(TeamUpdateRequest(header=Header(frame_id="x" * FRAME_ID_ROOM)))


@functools.lru_cache(maxsize=None)
def motion_command_bytes() -> int:
    """Largest valid em_exploration_msgs/MotionCommand [B]: both bounded arrays full (to
    the bounds the message definition gives them)."""
    bounds = {name: slot.maximum_size for name, slot in zip(
        MotionCommand.get_fields_and_field_types(), MotionCommand.SLOT_TYPES)
        if hasattr(slot, "maximum_size")}
    return serialized_size(MotionCommand(
        header=Header(frame_id="x" * FRAME_ID_ROOM),
        given_up=[GivenUpTarget()] * bounds["given_up"],
        meetings=[Meeting()] * bounds["meetings"]))
