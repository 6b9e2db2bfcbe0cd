"""A robot's own team-update stream on its own disk, for a restart that no teammate can serve.

A restarted robot process takes its earlier stream back from its teammates
(``core.agent.rejoin``). That fails when none of them holds it: the whole team was
restarted (a power cycle of every vehicle), or every teammate is out of (acoustic) range or
was restarted too. The robot then has nothing that ties it to the map and stands still. So
each robot also appends every record it makes to a journal file of its own, and a restarted
process reads its stream back from there first; its teammates' copies still fill whatever
the journal lacks.

File layout (little-endian)::

    b"EMJ1" | u32 header length | header: JSON {"robot_id", "num_robots", "mission"}
    then per record: u32 payload length | u32 CRC-32 of the payload | payload

The payload is opaque here (the robot node stores a record's serialized TeamUpdate
message, the bytes its teammates would send back). ``mission`` fingerprints the mission's
parameters, so a journal of another mission or robot is never taken. A record is written
with one ``write`` and flushed to the operating system, so a killed process loses nothing it
had journaled; a power loss can lose what the system had not yet put on the disk.

Reading trusts nothing: a missing, foreign or corrupt file, a torn last record (the
process died while writing it), a wrong checksum, an empty record (a zero-filled tail after
a power loss passes a CRC-32) or an oversized length ends the reading with the reason,
keeping the records read before it (``read_journal``). The records themselves are
checked by their reader (``core.agent.rejoin.records_beyond_the_team``: a journal that
holds more of a stream than the team does is another run's).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import struct
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from em_exploration_ros.core.untrusted_files import read_regular_file

MAGIC = b"EMJ1"
_LENGTH = struct.Struct("<I")
_FRAME = struct.Struct("<II")  # payload length, CRC-32 of the payload
#: Largest header accepted [bytes].
MAX_HEADER_BYTES = 4096
#: Largest record accepted [bytes]; a TeamUpdate of the default mission takes about 100-300.
MAX_RECORD_BYTES = 1 << 20
#: Largest journal read [bytes]; a 200 m mission's stream is about 200 kB.
MAX_JOURNAL_BYTES = 256 << 20


def mission_fingerprint(mission: object) -> str:
    """A short fingerprint of a mission's parameters (their ``repr``), the same in every
    process started with the same parameters."""
    return hashlib.sha256(repr(mission).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class JournalIdentity:
    """Whose stream a journal holds: robot ``robot_id`` of a team of ``num_robots`` on the
    mission fingerprinted ``mission`` (``mission_fingerprint``)."""

    robot_id: int
    num_robots: int
    mission: str

    def header(self) -> bytes:
        text = json.dumps({"robot_id": self.robot_id, "num_robots": self.num_robots,
                           "mission": self.mission}, sort_keys=True).encode()
        return MAGIC + _LENGTH.pack(len(text)) + text


@dataclass(frozen=True)
class JournalContents:
    """What ``read_journal`` found: the records in file order, and why the reading stopped
    before the end of the file or took nothing (None: every byte was read)."""

    records: list[bytes]
    problem: str | None


def read_journal(path: Path, identity: JournalIdentity) -> JournalContents:
    """The records of the journal at ``path`` if it is ``identity``'s (module docstring)."""
    try:
        data = read_regular_file(path, MAX_JOURNAL_BYTES)
    except FileNotFoundError:
        return JournalContents([], f"no journal at {path}")
    except (OSError, ValueError) as error:
        return JournalContents([], f"cannot read {path}: {error}")
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + _LENGTH.size:
        return JournalContents([], f"{path} is not a stream journal")
    (header_length,) = _LENGTH.unpack_from(data, len(MAGIC))
    start = len(MAGIC) + _LENGTH.size
    if header_length > MAX_HEADER_BYTES or start + header_length > len(data):
        return JournalContents([], f"{path}: its header is cut short or too long")
    if data[:start + header_length] != identity.header():
        return JournalContents([], f"{path} is the journal of another robot or mission")
    records: list[bytes] = []
    offset = start + header_length
    while offset < len(data):
        problem = _frame_problem(data, offset)
        if problem is not None:
            return JournalContents(records, f"{path}: record {len(records) + 1} (byte "
                                            f"{offset}) {problem}; read the {len(records)} "
                                            f"records before it")
        length, _ = _FRAME.unpack_from(data, offset)
        records.append(data[offset + _FRAME.size:offset + _FRAME.size + length])
        offset += _FRAME.size + length
    return JournalContents(records, None)


def _frame_problem(data: bytes, offset: int) -> str | None:
    """Why the record framed at ``offset`` cannot be taken, None if it can."""
    if offset + _FRAME.size > len(data):
        return "is cut short (torn write)"
    length, checksum = _FRAME.unpack_from(data, offset)
    if length == 0:
        return "is empty (a zero-filled tail?)"
    if length > MAX_RECORD_BYTES:
        return f"claims {length} bytes, more than {MAX_RECORD_BYTES}"
    payload = data[offset + _FRAME.size:offset + _FRAME.size + length]
    if len(payload) < length:
        return "is cut short (torn write)"
    if zlib.crc32(payload) != checksum:
        return "fails its checksum"
    return None


def _frame(payload: bytes) -> bytes:
    if not payload or len(payload) > MAX_RECORD_BYTES:
        raise ValueError(f"a record of {len(payload)} bytes (1 to {MAX_RECORD_BYTES})")
    return _FRAME.pack(len(payload), zlib.crc32(payload)) + payload


class StreamJournal:
    """Writes one robot's journal at ``path`` (module docstring). Raises the OSError of the
    file system (a full disk, a read-only folder); the caller decides to go on without."""

    def __init__(self, path: Path, identity: JournalIdentity) -> None:
        self.path = path
        self.identity = identity
        self._file = None

    def start(self, records: Iterable[bytes] = ()) -> None:
        """Begin the journal anew with ``records`` (the stream so far: none at a mission's
        start, the recovered stream after a restart). The new file replaces the old one in
        one rename, so a crash meanwhile leaves one or the other whole."""
        self.close()
        staging = self.path.with_name(self.path.name + ".new")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(staging, "wb") as file:
                file.write(self.identity.header() + b"".join(_frame(r) for r in records))
                file.flush()
                os.fsync(file.fileno())
            os.replace(staging, self.path)
        except (OSError, ValueError):
            with contextlib.suppress(OSError):
                staging.unlink()  # a half-written file would only take disk space
            raise
        self._file = open(self.path, "ab")  # noqa: SIM115 (held open for appending)

    def discard(self) -> None:
        """Remove the journal file if it can be: at a mission's start the file there is
        another run's, and one that cannot be replaced must not be read after a restart
        (a full disk left an earlier run's stream there)."""
        self.close()
        with contextlib.suppress(OSError):
            self.path.unlink()

    def append(self, payload: bytes) -> None:
        """Journal one more record (after ``start``)."""
        if self._file is None:
            raise ValueError("the journal was not started")
        self._file.write(_frame(payload))
        self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
