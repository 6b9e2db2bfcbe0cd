"""Bytes on the wire of the team data, computed from the core records (no rclpy).

The sizes are those of ``rclpy.serialization.serialize_message`` (XCDR1 plain CDR, little
endian): a 4-byte encapsulation header, then the fields with every primitive aligned to
its own size (counted from the end of the header), a sequence as a uint32 count and its
elements, a string as a uint32 length, its bytes and a NUL. The layouts below mirror
``msg_schemas/msg/*.msg``; ``tests/test_links.py`` checks them against rclpy, so a
message change that is not carried over here fails a test.
"""
from __future__ import annotations

from em_exploration_ros.core.agent.team_data import TeamUpdate

#: A layout: a tuple of field types. A type is a primitive size in bytes (1, 4 or 8, also
#: its alignment), ``("seq", layout)`` for a sequence, ``("array", n, size)`` for a fixed
#: array of primitives, ``"string"`` or a nested layout (a tuple).
_TIME = (4, 4)  # builtin_interfaces/Time: int32 sec, uint32 nanosec
_LANDMARK_DETECTION = (4, 8, 8, 8, 8)
_TEAMMATE_DETECTION = (4, 8, 8, 8, ("array", 9, 8))
_LANDMARK_ESTIMATE = (4, 8, 8, ("array", 4, 8))
_TARGET_RECORD = (4, 4, _TIME, 8, 8, 1, 4, 8, 8, 1)
_RENDEZVOUS = (_TIME, 4, 4, 4, 4, 1, 8, 8, 8)
#: Header of a team message: stamp and frame_id "map".
MAP_FRAME_ID = "map"
ENCAPSULATION_BYTES = 4


def _align(offset: int, size: int) -> int:
    return offset + (-offset) % size


def _primitive(offset: int, size: int, count: int = 1) -> int:
    return _align(offset, size) + size * count


def _string(offset: int, text: str) -> int:
    return _primitive(offset, 4) + len(text.encode("utf-8")) + 1


def _layout(offset: int, layout: tuple) -> int:
    """End offset of a message of fixed-size fields (no sequences or strings) at ``offset``."""
    for item in layout:
        if isinstance(item, int):
            offset = _primitive(offset, item)
        elif item[0] == "array":
            offset = _primitive(offset, item[2], item[1])
        else:
            offset = _layout(offset, item)
    return offset


def _sequence(offset: int, layout: tuple, count: int) -> int:
    offset = _primitive(offset, 4)
    for _ in range(count):
        offset = _layout(offset, layout)
    return offset


def _header(offset: int, frame_id: str) -> int:
    return _string(_layout(offset, _TIME), frame_id)


def team_update_wire_bytes(update: TeamUpdate) -> int:
    """Serialized size [bytes] of ``update`` as em_exploration_msgs/TeamUpdate (frame
    ``map``), encapsulation header included."""
    offset = _header(0, MAP_FRAME_ID)
    offset = _primitive(offset, 4)  # robot_id
    offset = _primitive(offset, 8)  # sequence
    offset = _primitive(offset, 4)  # keyframes count
    for keyframe in update.keyframes:
        offset = _layout(offset, (4, 4, _TIME, 1, 4, 8, 8, 8, ("array", 9, 8)))
        offset = _sequence(offset, _LANDMARK_DETECTION, len(keyframe.landmarks))
        offset = _sequence(offset, _TEAMMATE_DETECTION, len(keyframe.teammates))
    offset = _sequence(offset, _LANDMARK_ESTIMATE, len(update.landmarks))
    offset = _sequence(offset, _TARGET_RECORD, len(update.targets))
    offset = _sequence(offset, _RENDEZVOUS, len(update.rendezvous))
    offset = _primitive(offset, 1)  # finished
    return ENCAPSULATION_BYTES + offset


def update_request_wire_bytes() -> int:
    """Serialized size [bytes] of an em_exploration_msgs/TeamUpdateRequest with an empty
    frame_id, encapsulation header included."""
    offset = _header(0, "")
    return ENCAPSULATION_BYTES + _layout(offset, (4, 4, 8, 8))
