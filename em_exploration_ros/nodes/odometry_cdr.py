"""nav_msgs/Odometry with fixed frames in its serialized (CDR, little endian) form, one struct.

Every step the world sends each robot its dead reckoning and the evaluator every robot's
ground truth, both as Odometry. Through rclpy's message classes one took about 25 us to
build and 10 us to convert for publishing, and 50 us to deserialize plus 12 us to check
every number on the receiving side (a Python object per header, stamp, pose, point,
quaternion, twist and vector): a fifth of the evaluator's CPU in a default lockstep run.
With the frames known in advance the whole message is one ``struct`` layout, written and
read in one call each.

Wire layout (XCDR1 as rmw_fastrtps writes it; alignment is relative to the byte after the
4-byte encapsulation header)::

    header.stamp.sec int32, header.stamp.nanosec uint32,
    header.frame_id string (uint32 length with the terminating NUL, the bytes, the NUL),
    padding to 4, child_frame_id string, padding to 8,
    pose.pose: position x y z, orientation x y z w; pose.covariance[36];
    twist.twist: linear x y z, angular x y z; twist.covariance[36]   (85 float64 in all)

``OdometryCodec.decode`` reads only messages in exactly this form with the codec's frames,
finite and plausible numbers and a valid stamp; for anything else it returns None and the
caller reads the message the ordinary way, with its checks and their reasons. Padding
bytes are not checked: rmw_fastrtps leaves them uninitialized.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from em_exploration_ros.core.agent.input_checks import array_problem, stamp_problem
from em_exploration_ros.core.records.wire_model import planar_quaternion, planar_yaw
from em_exploration_ros.nodes.path_cdr import CDR_LE_HEADER

#: float64s of the message body: pose (7), its covariance (36), twist (6), its covariance.
_FLOATS = 7 + 36 + 6 + 36
_TWIST_AT = 7 + 36
_ZERO_TWIST = (0.0,) * 6


@dataclass(frozen=True)
class PlanarOdometry:
    """An Odometry read by :meth:`OdometryCodec.decode`: ``stamp`` (sec, nanosec) as on the
    wire, ``pose`` (3,) x [m], y [m], yaw [rad] in the frame the codec was made for, and the
    6x6 pose and twist covariances."""

    stamp: tuple[int, int]
    pose: NDArray[np.float64]
    pose_covariance: NDArray[np.float64]
    twist_covariance: NDArray[np.float64]


def _string_bytes(text: str) -> bytes:
    return text.encode("utf-8") + b"\x00"


class OdometryCodec:
    """Writes and reads nav_msgs/Odometry of one ``frame_id`` / ``child_frame_id`` pair."""

    def __init__(self, frame_id: str, child_frame_id: str) -> None:
        self._frame = _string_bytes(frame_id)
        self._child = _string_bytes(child_frame_id)
        child_start = (12 + len(self._frame) + 3) // 4 * 4
        child_end = child_start + 4 + len(self._child)
        self._struct = struct.Struct(
            f"<iII{len(self._frame)}s{child_start - 12 - len(self._frame)}x"
            f"I{len(self._child)}s{(child_end + 7) // 8 * 8 - child_end}x{_FLOATS}d")
        #: Bytes of every message of this codec, encapsulation header included.
        self.size = len(CDR_LE_HEADER) + self._struct.size

    def encode(self, stamp: tuple[int, int], pose: NDArray[np.float64],
               pose_covariance: NDArray[np.float64] | None = None,
               twist_covariance: NDArray[np.float64] | None = None) -> bytes:
        """The serialized Odometry of a planar ``pose`` (x [m], y [m], theta [rad]) at
        ``stamp`` (sec, nanosec), zero twist, 6x6 covariances (zero when None): the message
        ``conversions.odometry_to_msg`` builds, as ``serialize_message`` writes it (up to
        padding)."""
        z, w = planar_quaternion(float(pose[2]))
        return CDR_LE_HEADER + self._struct.pack(
            int(stamp[0]), int(stamp[1]), len(self._frame), self._frame, len(self._child),
            self._child, float(pose[0]), float(pose[1]), 0.0, 0.0, 0.0, z, w,
            *_flat36(pose_covariance), *_ZERO_TWIST, *_flat36(twist_covariance))

    def decode(self, data: bytes) -> PlanarOdometry | None:
        """The odometry in ``data``, or None unless it is in this codec's exact form (both
        frames, little-endian CDR) with a valid stamp and only finite, plausible numbers."""
        if len(data) != self.size or data[:2] != CDR_LE_HEADER[:2]:
            return None
        sec, nanosec, frame_length, frame, child_length, child, *floats = \
            self._struct.unpack_from(data, len(CDR_LE_HEADER))
        if (frame != self._frame or child != self._child or frame_length != len(frame)
                or child_length != len(child) or stamp_problem(sec, nanosec)):
            return None
        values = np.array(floats)
        if array_problem(values, "a number"):
            return None
        x, y, _, _, _, z, w = floats[:7]
        return PlanarOdometry((sec, nanosec), np.array([x, y, planar_yaw(z, w)]),
                              values[7:_TWIST_AT].reshape(6, 6),
                              values[_TWIST_AT + 6:].reshape(6, 6))


def _flat36(matrix: NDArray[np.float64] | None) -> tuple[float, ...]:
    """The 36 entries of a 6x6 matrix, row by row (zeros for None)."""
    if matrix is None:
        return (0.0,) * 36
    return tuple(np.asarray(matrix, dtype=float).reshape(36).tolist())
