"""Read and validate MCAP recordings, independently of the writer.

``BagScanner`` walks a file record by record: it checks the magic at both ends, that every
record fits in the file and parses, that every chunk decompresses to its stated size and
matches its CRC, that every message refers to a known channel and every channel to a known
schema, and, at the end, the summary section against what the data section held (schemas,
channels, statistics, chunk indexes, summary CRC, data section CRC). Messages stream out in
file order. A chunk's records are released only after the whole chunk has been validated.

In strict mode any problem raises ``BagError`` (one-line message). In tolerant mode the walk
stops at the first problem and ``BagInfo.problem`` says what and where: this is how the
readable part of a recording that was killed while writing is recovered.
"""
from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import (
    Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Metadata, Schema, Statistics)

from em_exploration_ros.bag_format.qos_yaml import QosProfile, qos_profiles_from_yaml
from em_exploration_ros.bag_format.rosbag2_metadata import (
    METADATA_RECORD_NAME, SERIALIZED_METADATA_KEY, BagMetadata, parse_bag_metadata)

MAGIC = b"\x89MCAP0\r\n"
_RECORD_PREFIX = struct.Struct("<BQ")
_MESSAGE_PREFIX = struct.Struct("<HIQQ")
_FOOTER_CRC_PREFIX = struct.Struct("<BQQQ")
_PARSE_ERRORS = (McapError, struct.error, ValueError, RuntimeError, zstandard.ZstdError,
                 KeyError, OverflowError)


class BagError(Exception):
    """A recording cannot be read; ``str()`` is a one-line explanation for the user."""


class NotMcapError(BagError):
    """The file is not an MCAP file at all (raised even by a tolerant scan)."""


class _StrictStream(ReadDataStream):
    """A record field reader that fails on a short read instead of returning less."""

    def read(self, length: int) -> bytes:
        data = super().read(length)
        if len(data) != length:
            raise EndOfFile()
        return data


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


def _parse(reader: Callable[[ReadDataStream], Any], body: bytes) -> Any:
    return reader(_StrictStream(io.BytesIO(body)))


def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "zstd":
        return zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size)
    if chunk.compression == "lz4":
        return lz4.frame.decompress(chunk.data)
    if chunk.compression == "":
        return chunk.data
    raise BagError(f"unsupported chunk compression {chunk.compression!r}")


class BagScanner:
    """One validating pass over a recording; iterate ``messages()`` once, then read ``info``."""

    def __init__(self, path: str | os.PathLike[str], *, tolerant: bool = False) -> None:
        self.path = Path(path)
        self.tolerant = tolerant
        try:
            size = self.path.stat().st_size
        except FileNotFoundError:
            raise BagError(f"{self.path}: no such file") from None
        except OSError as error:
            raise BagError(f"{self.path}: cannot read: {error.strerror}") from None
        if self.path.is_dir():
            raise BagError(f"{self.path}: is a directory, not an MCAP file")
        self.info = BagInfo(path=self.path, file_size=size)
        self._chunk_offsets: set[int] = set()
        self._chunk_indexes: list[ChunkIndex] = []
        self._statistics: Statistics | None = None
        self._summary_started = False
        self._footer = Footer(summary_start=0, summary_offset_start=0, summary_crc=0)
        self._footer_offset = 0

    # ----- the walk ---------------------------------------------------------------------
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

    def _fail(self, offset: int, what: str) -> BagError:
        return BagError(f"{self.path}: {what} (at byte {offset} of {self.info.file_size})")

    def _walk(self, stream: io.BufferedReader) -> Iterator[tuple[ChannelInfo, BagMessage]]:
        magic = stream.read(len(MAGIC))
        if magic != MAGIC:
            kind = "an empty file" if not magic else "not an MCAP file (bad magic bytes)"
            raise NotMcapError(f"{self.path}: {kind}")
        data_crc = zlib.crc32(magic)
        offset = len(MAGIC)
        self.info.readable_bytes = offset
        first = True
        while True:
            prefix = stream.read(_RECORD_PREFIX.size)
            if len(prefix) < _RECORD_PREFIX.size:
                raise self._fail(offset, "file is truncated: it ends without a footer "
                                 "(the recording was not closed)")
            opcode, length = _RECORD_PREFIX.unpack(prefix)
            if offset + _RECORD_PREFIX.size + length > self.info.file_size:
                raise self._fail(offset, f"file is truncated: {self._opcode_name(opcode)} "
                                 f"record of {length} bytes extends past the end")
            body = stream.read(length)
            if first and opcode != Opcode.HEADER:
                raise NotMcapError(f"{self.path}: not an MCAP file (no Header record)")
            first = False
            try:
                released = self._record(opcode, body, offset, data_crc)
            except _PARSE_ERRORS as error:
                raise self._fail(offset, f"corrupt {self._opcode_name(opcode)} record: "
                                 f"{type(error).__name__} {error}") from None
            if opcode != Opcode.DATA_END and not self._summary_started:
                data_crc = zlib.crc32(prefix, data_crc)
                data_crc = zlib.crc32(body, data_crc)
            offset += _RECORD_PREFIX.size + length
            yield from released
            self.info.readable_bytes = offset
            if opcode == Opcode.FOOTER:
                self._finish(stream, offset)
                return

    @staticmethod
    def _opcode_name(opcode: int) -> str:
        try:
            return Opcode(opcode).name.replace("_", " ").title().replace(" ", "")
        except ValueError:
            return f"unknown (opcode {opcode:#x})"

    def _record(self, opcode: int, body: bytes, offset: int,
                data_crc: int) -> list[tuple[ChannelInfo, BagMessage]]:
        """Parse one top-level record; returns the messages it releases."""
        if opcode == Opcode.HEADER:
            header = _parse(Header.read, body)
            self.info.profile, self.info.library = header.profile, header.library
        elif opcode == Opcode.CHUNK:
            return self._chunk(_parse(Chunk.read, body), offset)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            return self._apply([(opcode, body)], offset)
        elif opcode == Opcode.METADATA:
            record = _parse(Metadata.read, body)
            self.info.metadata[record.name] = dict(record.metadata)
        elif opcode == Opcode.DATA_END:
            end = _parse(DataEnd.read, body)
            if end.data_section_crc not in (0, data_crc):
                raise self._fail(offset, "data section CRC mismatch")
            self._summary_started = True
        elif opcode == Opcode.STATISTICS:
            self._statistics = _parse(Statistics.read, body)
        elif opcode == Opcode.CHUNK_INDEX:
            self._chunk_indexes.append(_parse(ChunkIndex.read, body))
        elif opcode == Opcode.FOOTER:
            self._footer = _parse(Footer.read, body)
            self._footer_offset = offset
        return []

    def _chunk(self, chunk: Chunk, offset: int) -> list[tuple[ChannelInfo, BagMessage]]:
        data = _decompress(chunk)
        if len(data) != chunk.uncompressed_size:
            raise self._fail(offset, f"chunk decompresses to {len(data)} bytes, "
                             f"not {chunk.uncompressed_size}")
        if chunk.uncompressed_crc != 0:
            if zlib.crc32(data) != chunk.uncompressed_crc:
                raise self._fail(offset, "chunk CRC mismatch")
            self.info.crc_checked_chunks += 1
        records = []
        position = 0
        while position < len(data):
            opcode, length = _RECORD_PREFIX.unpack_from(data, position)
            start = position + _RECORD_PREFIX.size
            if start + length > len(data):
                raise self._fail(offset, "chunk holds a record that extends past its end")
            records.append((opcode, data[start:start + length]))
            position = start + length
        released = self._apply(records, offset)
        self.info.chunk_count += 1
        self.info.compressions.add(chunk.compression or "none")
        self._chunk_offsets.add(offset)
        return released

    def _apply(self, records: list[tuple[int, bytes]],
               offset: int) -> list[tuple[ChannelInfo, BagMessage]]:
        """Validate a group of records, then register schemas/channels and count messages."""
        schemas = dict(self.info.schemas)
        channels = dict(self.info.channels)
        messages = []
        for opcode, body in records:
            if opcode == Opcode.SCHEMA:
                record = _parse(Schema.read, body)
                schema = SchemaInfo(record.id, record.name, record.encoding, bytes(record.data))
                if schemas.setdefault(schema.id, schema) != schema:
                    raise self._fail(offset, f"schema id {schema.id} is defined twice, "
                                     "differently")
            elif opcode == Opcode.CHANNEL:
                record = _parse(Channel.read, body)
                channel = ChannelInfo(record.id, record.topic, record.message_encoding,
                                      record.schema_id, dict(record.metadata))
                if channel.schema_id != 0 and channel.schema_id not in schemas:
                    raise self._fail(offset, f"channel {channel.topic} refers to unknown "
                                     f"schema id {channel.schema_id}")
                if channels.setdefault(channel.id, channel) != channel:
                    raise self._fail(offset, f"channel id {channel.id} is defined twice, "
                                     "differently")
            elif opcode == Opcode.MESSAGE:
                channel_id, sequence, log_time, publish_time = _MESSAGE_PREFIX.unpack_from(body)
                if channel_id not in channels:
                    raise self._fail(offset, f"message on unknown channel id {channel_id}")
                messages.append((channels[channel_id], BagMessage(
                    channel_id, sequence, log_time, publish_time,
                    body[_MESSAGE_PREFIX.size:])))
        self.info.schemas, self.info.channels = schemas, channels
        counts = self.info.channel_message_counts
        for channel, message in messages:
            counts[channel.id] = counts.get(channel.id, 0) + 1
            if self.info.first_log_ns is None or message.log_time_ns < self.info.first_log_ns:
                self.info.first_log_ns = message.log_time_ns
            if self.info.last_log_ns is None or message.log_time_ns > self.info.last_log_ns:
                self.info.last_log_ns = message.log_time_ns
        self.info.message_count += len(messages)
        return messages

    # ----- end of file checks -------------------------------------------------------------
    def _finish(self, stream: io.BufferedReader, offset: int) -> None:
        tail = stream.read(len(MAGIC) + 1)
        if tail != MAGIC:
            raise self._fail(offset, "footer is not followed by the closing magic bytes"
                             if tail[:len(MAGIC)] != MAGIC else "data after the closing magic")
        self._check_summary_crc(stream)
        self._check_statistics()
        indexed = {index.chunk_start_offset for index in self._chunk_indexes}
        if self._chunk_indexes and indexed != self._chunk_offsets:
            raise self._fail(offset, f"chunk indexes list {len(indexed)} chunks, "
                             f"the file holds {len(self._chunk_offsets)}")
        self.info.readable_bytes = offset + len(MAGIC)
        self.info.complete = True

    def _check_summary_crc(self, stream: io.BufferedReader) -> None:
        footer = self._footer
        if footer.summary_crc == 0 or footer.summary_start == 0:
            return
        stream.seek(footer.summary_start)
        summary = stream.read(self._footer_offset - footer.summary_start)
        crc = zlib.crc32(summary)
        crc = zlib.crc32(_FOOTER_CRC_PREFIX.pack(Opcode.FOOTER, 20, footer.summary_start,
                                                 footer.summary_offset_start), crc)
        if crc != footer.summary_crc:
            raise self._fail(self._footer_offset, "summary section CRC mismatch")

    def _check_statistics(self) -> None:
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
                raise self._fail(self._footer_offset,
                                 f"statistics {what} is {stated}, the file holds {actual}")


def scan_bag(path: str | os.PathLike[str], *, tolerant: bool = False) -> BagInfo:
    """Walk and validate a whole recording; returns what it holds."""
    scanner = BagScanner(path, tolerant=tolerant)
    for _ in scanner.messages():
        pass
    return scanner.info
