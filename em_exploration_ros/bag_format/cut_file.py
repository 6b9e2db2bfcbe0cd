"""End, in place, an MCAP file whose writing a refused write cut off (a full disk, an I/O
error, a file size limit).

``BagWriter`` hands the file to the OS in whole steps (a chunk and its message indexes, ...)
and knows the end of the last step that reached it whole. Up to there the file is a valid
MCAP data section. ``end_cut_file`` cuts the file back to that offset and appends what a
closed file has after its data: the rosbag2 metadata record, the data end, a summary rebuilt
from the records in the file (schemas, channels, statistics, chunk and metadata indexes,
summary offsets) and the footer. rosbag2, rosbags, Foxglove and ``em-bag info`` then open it
as a complete recording of what it holds. It needs a few hundred kB of free space, which the
bag directory's reserve file gives back first (``bag_directory.py``).
"""
from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, McapRecord, Message,
                          MessageIndex, Metadata, MetadataIndex, Schema, Statistics,
                          SummaryOffset)
from mcap.stream_reader import MAGIC_SIZE
from mcap.writer import MCAP0_MAGIC

#: Opcode (1 byte) and length (8 bytes) before every record's content.
_RECORD_PREFIX = struct.Struct("<BQ")
#: Records of the data section, outside chunks, that the summary lists or counts.
_TOP_LEVEL_TYPES: dict[int, type[McapRecord]] = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
                                                 Opcode.MESSAGE: Message}


@dataclass
class _DataSection:
    """What the summary of a data section lists, gathered record by record."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    metadata_indexes: list[MetadataIndex] = field(default_factory=list)
    channel_message_counts: dict[int, int] = field(default_factory=dict)
    message_start_time: int | None = None
    message_end_time: int = 0

    def take(self, record: McapRecord) -> None:
        """A schema, channel or message, at the top level or inside a chunk."""
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, Message):
            counts = self.channel_message_counts
            counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
            start = self.message_start_time
            self.message_start_time = (record.log_time if start is None
                                       else min(start, record.log_time))
            self.message_end_time = max(self.message_end_time, record.log_time)

    def statistics(self) -> Statistics:
        return Statistics(
            message_count=sum(self.channel_message_counts.values()),
            schema_count=len(self.schemas), channel_count=len(self.channels),
            attachment_count=0, metadata_count=len(self.metadata_indexes),
            chunk_count=len(self.chunk_indexes),
            message_start_time=self.message_start_time or 0,
            message_end_time=self.message_end_time,
            channel_message_counts=dict(self.channel_message_counts))


def _read_listed(opcode: int, content: bytes) -> McapRecord:
    """A schema, channel or message record from its content."""
    stream = ReadDataStream(io.BytesIO(content))
    if opcode == Opcode.MESSAGE:
        return Message.read(stream, len(content))
    return _TOP_LEVEL_TYPES[opcode].read(stream)


def _records(stream: BinaryIO, start: int, end: int) -> Iterator[tuple[int, int, bytes]]:
    """``(offset, opcode, content)`` of each record of ``stream`` from ``start`` to ``end``."""
    stream.seek(start)
    offset = start
    while offset < end:
        opcode, length = _RECORD_PREFIX.unpack(stream.read(_RECORD_PREFIX.size))
        yield offset, opcode, stream.read(length)
        offset += _RECORD_PREFIX.size + length


def _chunk_records(chunk: Chunk) -> Iterator[McapRecord]:
    """The schemas, channels and messages inside a chunk."""
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        data = lz4.frame.decompress(chunk.data)
    else:
        data = chunk.data
    for _, opcode, content in _records(io.BytesIO(data), 0, len(data)):
        if opcode in _TOP_LEVEL_TYPES:
            yield _read_listed(opcode, content)


def _read_data_section(stream: BinaryIO, end: int) -> _DataSection:
    """Gather the summary of the records between the magic bytes and ``end``."""
    section = _DataSection()
    chunk_index: ChunkIndex | None = None
    for offset, opcode, content in _records(stream, MAGIC_SIZE, end):
        record_length = _RECORD_PREFIX.size + len(content)
        reader = ReadDataStream(io.BytesIO(content))
        if opcode == Opcode.CHUNK:
            chunk = Chunk.read(reader)
            chunk_index = ChunkIndex(
                message_start_time=chunk.message_start_time,
                message_end_time=chunk.message_end_time, chunk_start_offset=offset,
                chunk_length=record_length, message_index_offsets={},
                message_index_length=0, compression=chunk.compression,
                compressed_size=len(chunk.data), uncompressed_size=chunk.uncompressed_size)
            section.chunk_indexes.append(chunk_index)
            for inner in _chunk_records(chunk):
                section.take(inner)
        elif opcode == Opcode.MESSAGE_INDEX:  # the indexes of the chunk just before
            if chunk_index is not None:
                index = MessageIndex.read(reader)
                chunk_index.message_index_offsets[index.channel_id] = offset
                chunk_index.message_index_length += record_length
        else:
            chunk_index = None
            if opcode == Opcode.METADATA:
                name = Metadata.read(reader).name
                section.metadata_indexes.append(MetadataIndex(offset, record_length, name))
            elif opcode in _TOP_LEVEL_TYPES:
                section.take(_read_listed(opcode, content))
    return section


def _encoded(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def end_cut_file(stream: io.FileIO, whole_bytes: int, metadata_name: str,
                 metadata: dict[str, str]) -> None:
    """Cut ``stream`` (the MCAP file, open for writing) back to ``whole_bytes``, the end of
    its last whole record, and close its data section there: the metadata record
    ``metadata_name`` with ``metadata``, the data end, the summary and the footer. Raises
    OSError if the OS refuses these last bytes too."""
    stream.truncate(whole_bytes)
    with open(stream.name, "rb") as reader:
        section = _read_data_section(reader, whole_bytes)
    stream.seek(whole_bytes)
    offset = whole_bytes
    tail = io.BytesIO()

    def put(record: McapRecord) -> int:
        data = _encoded(record)
        tail.write(data)
        return len(data)

    length = put(Metadata(metadata_name, metadata))
    section.metadata_indexes.append(MetadataIndex(offset, length, metadata_name))
    offset += length
    offset += put(DataEnd(data_section_crc=0))
    summary_start = offset
    groups = [(Opcode.SCHEMA, list(section.schemas.values())),
              (Opcode.CHANNEL, list(section.channels.values())),
              (Opcode.STATISTICS, [section.statistics()]),
              (Opcode.CHUNK_INDEX, section.chunk_indexes),
              (Opcode.METADATA_INDEX, section.metadata_indexes)]
    summary_offsets = []
    for opcode, records in groups:
        if not records:
            continue
        group_start = offset
        offset += sum(put(record) for record in records)
        summary_offsets.append(SummaryOffset(opcode, group_start, offset - group_start))
    summary_offset_start = offset
    for summary_offset in summary_offsets:
        offset += put(summary_offset)
    put(Footer(summary_start=summary_start, summary_offset_start=summary_offset_start,
               summary_crc=0))
    tail.write(MCAP0_MAGIC)
    stream.write(tail.getvalue())
