"""Read and validate MCAP recordings with the ``mcap`` library's own reader.

``BagScanner`` walks a recording (an ``.mcap`` file or a bag directory) once with mcap's
``StreamReader``, which checks the magic bytes, decompresses every chunk and validates the
chunk and data-section CRCs. On top of it this module checks what that reader leaves to its
user: every record is read whole (the file is fed to the reader through exact reads, so a
record cut short by the end of the file is an error, not a short record), the file starts
with a Header, every message refers to a known channel and every channel to a known schema,
nothing follows the closing magic, and the Statistics record agrees with what the data
section held. Messages stream out in file order; a chunk's messages are released only after
the whole chunk was decompressed and its CRC checked.

In strict mode any problem raises ``BagError`` (one-line message). In tolerant mode the walk
stops at the first problem and ``BagInfo.problem`` says what and where: this is how the
readable part of a recording that was killed while writing is recovered.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Iterator, Mapping

import zstandard
from mcap.exceptions import InvalidMagic, McapError
from mcap.records import (Channel, Chunk, DataEnd, Footer, Header, McapRecord, Message,
                          Metadata, Schema, Statistics)
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk

from em_exploration_ros.bag_format.bag_directory import BagPathError, mcap_file
from em_exploration_ros.bag_format.qos_yaml import QosProfile, qos_profiles_from_yaml
from em_exploration_ros.bag_format.rosbag2_metadata import (
    METADATA_RECORD_NAME, SERIALIZED_METADATA_KEY, BagMetadata, parse_bag_metadata)

#: What mcap's reader raises on a malformed record (besides CRC and truncation errors).
_PARSE_ERRORS = (McapError, struct.error, ValueError, RuntimeError, zstandard.ZstdError,
                 KeyError, OverflowError, UnicodeDecodeError)


class BagError(Exception):
    """A recording cannot be read; ``str()`` is a one-line explanation for the user."""


class NotMcapError(BagError):
    """The file is not an MCAP file at all (raised even by a tolerant scan)."""


@dataclass(frozen=True)
class SchemaInfo:
    """A Schema record: ``name`` is the message type (``pkg/msg/Type``)."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelInfo:
    """A Channel record: one topic."""

    id: int
    topic: str
    message_encoding: str
    schema_id: int
    metadata: Mapping[str, str]

    @property
    def offered_qos(self) -> list[QosProfile]:
        """The publishers' QoS recorded in ``offered_qos_profiles`` (raises QosFormatError)."""
        return qos_profiles_from_yaml(self.metadata.get("offered_qos_profiles", ""))

    @property
    def type_hash(self) -> str:
        """The ``topic_type_hash`` metadata ("" if absent)."""
        return self.metadata.get("topic_type_hash", "")


@dataclass(frozen=True)
class BagMessage:
    """A Message record; times in nanoseconds of the recording clock."""

    channel_id: int
    sequence: int
    log_time_ns: int
    publish_time_ns: int
    data: bytes


@dataclass
class BagInfo:
    """What a walk over a recording found (complete once the walk is exhausted)."""

    path: Path
    file_size: int
    profile: str = ""
    library: str = ""
    schemas: dict[int, SchemaInfo] = field(default_factory=dict)
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    channel_message_counts: dict[int, int] = field(default_factory=dict)
    channel_last_log_ns: dict[int, int] = field(default_factory=dict)
    message_count: int = 0
    first_log_ns: int | None = None
    last_log_ns: int | None = None
    chunk_count: int = 0
    crc_checked_chunks: int = 0
    compressions: set[str] = field(default_factory=set)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False
    problem: str | None = None
    readable_bytes: int = 0

    def schema_of(self, channel: ChannelInfo) -> SchemaInfo:
        """The schema of a channel."""
        return self.schemas[channel.schema_id]

    def topic_counts(self) -> dict[str, int]:
        """Messages per topic."""
        return {c.topic: self.channel_message_counts.get(c.id, 0) for c in self.channels.values()}

    def rosbag2_metadata(self) -> BagMetadata | None:
        """The parsed ``rosbag2`` metadata record, if the file has one."""
        record = self.metadata.get(METADATA_RECORD_NAME)
        if record is None or SERIALIZED_METADATA_KEY not in record:
            return None
        return parse_bag_metadata(record[SERIALIZED_METADATA_KEY])


class _TruncatedError(Exception):
    """The file ended inside a record."""


class _OverlongFieldError(Exception):
    """A record declares a field longer than what is left of the record."""

    def __init__(self, declared: int, left: int) -> None:
        super().__init__(f"a field declares {declared} bytes, {left} are left in its record")


class _ExactReads:
    """The file as mcap's reader sees it: each read returns exactly the bytes asked for or
    raises _TruncatedError (a plain file returns fewer at its end, and mcap's reader would
    then parse a record from the short data). ``position`` counts the bytes read.

    A read longer than what is left of the file, or of the record being read
    (``record_end``, a position), fails before anything is read: a corrupt length field
    (a chunk's data length, a string length) must not make it allocate its declared size.
    """

    def __init__(self, stream: BinaryIO, file_size: int) -> None:
        self._stream = stream
        self._file_size = file_size
        self.position = 0
        self.record_end: int | None = None

    def read(self, size: int = -1) -> bytes:
        if self.record_end is not None and size > self.record_end - self.position:
            raise _OverlongFieldError(size, self.record_end - self.position)
        if size > self._file_size - self.position:
            raise _TruncatedError()
        data = self._stream.read(size)
        if size >= 0 and len(data) < size:
            raise _TruncatedError()
        self.position += len(data)
        return data


class _RecordBoundedReader(StreamReader):
    """mcap's StreamReader, with each top-level record's reads bounded by its declared length
    (it reads a record's fields without comparing their lengths with the record's)."""

    def __init__(self, exact: _ExactReads) -> None:
        super().__init__(exact, emit_chunks=True, validate_crcs=True)
        self._exact = exact

    def _read_record(self, opcode: int, length: int) -> McapRecord | None:
        self._exact.record_end = self._exact.position + length
        try:
            return super()._read_record(opcode, length)
        finally:
            self._exact.record_end = None


class BagScanner:
    """One validating pass over a recording; iterate ``messages()`` once, then read ``info``.

    ``path`` is an ``.mcap`` file or a bag directory (see bag_directory.mcap_file).
    """

    def __init__(self, path: str | os.PathLike[str], *, tolerant: bool = False) -> None:
        try:
            self.path = mcap_file(path)
        except BagPathError as error:
            raise BagError(str(error)) from None
        self.tolerant = tolerant
        if self.path.is_dir():
            raise BagError(f"{self.path}: is a directory, not an MCAP file")
        try:
            size = self.path.stat().st_size
        except OSError as error:
            raise BagError(f"{self.path}: cannot read: {error.strerror}") from None
        self.info = BagInfo(path=self.path, file_size=size)
        self._statistics: Statistics | None = None

    def messages(self) -> Iterator[tuple[ChannelInfo, BagMessage]]:
        """Messages in file order with their channels; validates everything on the way."""
        try:
            with self.path.open("rb") as stream:
                yield from self._walk(stream)
        except NotMcapError:
            raise
        except BagError as error:
            if not self.tolerant:
                raise
            self.info.problem = str(error)
        except OSError as error:
            raise BagError(f"{self.path}: cannot read: {error.strerror}") from None

    def _fail(self, what: str) -> BagError:
        return BagError(f"{self.path}: {what} (after byte {self.info.readable_bytes} of "
                        f"{self.info.file_size})")

    def _walk(self, stream: BinaryIO) -> Iterator[tuple[ChannelInfo, BagMessage]]:
        exact = _ExactReads(stream, self.info.file_size)
        records = _RecordBoundedReader(exact).records
        first = True
        try:
            for record in records:
                if first and not isinstance(record, Header):
                    raise NotMcapError(f"{self.path}: not an MCAP file (no Header record)")
                first = False
                released = self._record(record)
                self.info.readable_bytes = exact.position
                yield from released
        except InvalidMagic:
            if first:
                raise NotMcapError(f"{self.path}: not an MCAP file (bad magic bytes)") from None
            raise self._fail("footer is not followed by the closing magic bytes") from None
        except _TruncatedError:
            if self.info.file_size == 0:
                raise NotMcapError(f"{self.path}: an empty file") from None
            if first and exact.position == 0:
                raise NotMcapError(f"{self.path}: not an MCAP file (shorter than the magic "
                                   "bytes)") from None
            raise self._fail("file is truncated: it ends without a footer (the recording "
                             "was not closed)") from None
        except _OverlongFieldError as error:
            raise self._fail(f"truncated or corrupt record: {error}") from None
        except CRCValidationError as error:
            what = "data section" if isinstance(error.record, DataEnd) else "chunk"
            raise self._fail(f"{what} CRC mismatch") from None
        except _PARSE_ERRORS as error:
            raise self._fail(f"corrupt record: {type(error).__name__} {error}") from None
        self.info.readable_bytes = exact.position
        if stream.read(1):
            raise self._fail("data after the closing magic")
        self._check_statistics()
        self.info.complete = True

    def _record(self, record: McapRecord) -> list[tuple[ChannelInfo, BagMessage]]:
        """Take one top-level record; returns the messages it releases."""
        if isinstance(record, Header):
            self.info.profile, self.info.library = record.profile, record.library
        elif isinstance(record, Chunk):
            contents = breakup_chunk(record, validate_crc=True)
            self.info.chunk_count += 1
            self.info.crc_checked_chunks += record.uncompressed_crc != 0
            self.info.compressions.add(record.compression or "none")
            return self._apply(contents)
        elif isinstance(record, (Schema, Channel, Message)):
            return self._apply([record])
        elif isinstance(record, Metadata):
            self.info.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Statistics):
            self._statistics = record
        elif isinstance(record, Footer):
            pass
        return []

    def _apply(self, records: list[McapRecord]) -> list[tuple[ChannelInfo, BagMessage]]:
        """Validate a group of records, then register schemas/channels and count messages."""
        schemas = dict(self.info.schemas)
        channels = dict(self.info.channels)
        messages = []
        for record in records:
            if isinstance(record, Schema):
                schema = SchemaInfo(record.id, record.name, record.encoding, bytes(record.data))
                if schemas.setdefault(schema.id, schema) != schema:
                    raise self._fail(f"schema id {schema.id} is defined twice, differently")
            elif isinstance(record, Channel):
                channel = ChannelInfo(record.id, record.topic, record.message_encoding,
                                      record.schema_id, dict(record.metadata))
                if channel.schema_id != 0 and channel.schema_id not in schemas:
                    raise self._fail(f"channel {channel.topic} refers to unknown schema id "
                                     f"{channel.schema_id}")
                if channels.setdefault(channel.id, channel) != channel:
                    raise self._fail(f"channel id {channel.id} is defined twice, differently")
            elif isinstance(record, Message):
                if record.channel_id not in channels:
                    raise self._fail(f"message on unknown channel id {record.channel_id}")
                messages.append((channels[record.channel_id], BagMessage(
                    record.channel_id, record.sequence, record.log_time, record.publish_time,
                    bytes(record.data))))
        self.info.schemas, self.info.channels = schemas, channels
        counts = self.info.channel_message_counts
        for channel, message in messages:
            counts[channel.id] = counts.get(channel.id, 0) + 1
            last = self.info.channel_last_log_ns
            last[channel.id] = max(last.get(channel.id, message.log_time_ns), message.log_time_ns)
            if self.info.first_log_ns is None or message.log_time_ns < self.info.first_log_ns:
                self.info.first_log_ns = message.log_time_ns
            if self.info.last_log_ns is None or message.log_time_ns > self.info.last_log_ns:
                self.info.last_log_ns = message.log_time_ns
        self.info.message_count += len(messages)
        return messages

    def _check_statistics(self) -> None:
        """The Statistics record (if any) must describe what the data section held."""
        stats = self._statistics
        if stats is None:
            return
        info = self.info
        recorded = {k: v for k, v in stats.channel_message_counts.items() if v}
        found = {k: v for k, v in info.channel_message_counts.items() if v}
        checks = [("message count", stats.message_count, info.message_count),
                  ("chunk count", stats.chunk_count, info.chunk_count),
                  ("channel count", stats.channel_count, len(info.channels)),
                  ("schema count", stats.schema_count, len(info.schemas)),
                  ("per-channel message counts", recorded, found)]
        if info.message_count:
            checks += [("message start time", stats.message_start_time, info.first_log_ns),
                       ("message end time", stats.message_end_time, info.last_log_ns)]
        for what, stated, actual in checks:
            if stated != actual:
                raise self._fail(f"statistics {what} is {stated}, the file holds {actual}")


def scan_bag(path: str | os.PathLike[str], *, tolerant: bool = False) -> BagInfo:
    """Walk and validate a whole recording (file or bag directory); returns what it holds."""
    scanner = BagScanner(path, tolerant=tolerant)
    for _ in scanner.messages():
        pass
    return scanner.info
