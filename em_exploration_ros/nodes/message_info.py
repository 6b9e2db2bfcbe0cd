"""The metadata rclpy hands a subscription callback that takes two arguments."""
from __future__ import annotations

from typing import Any

#: A received message's metadata (``source_timestamp``, ``publication_sequence_number``, ...).
MessageInfo = dict[str, Any]


def publication_sequence(info: MessageInfo) -> int | None:
    """The writer's sequence number of a received message (how many messages that writer
    had published up to and with this one), or None where the middleware does not give it."""
    number = info.get("publication_sequence_number")
    return number if isinstance(number, int) and number > 0 else None
