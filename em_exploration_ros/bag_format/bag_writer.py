"""Write a rosbag2-compatible MCAP file: chunked, compressed, crash-tolerant.

Records reach the operating system as soon as a chunk is complete (the file is unbuffered at
the Python level), so a process killed without warning leaves every finished chunk readable;
``flush()`` closes the chunk in progress early, which a recorder calls periodically to bound
what a crash can lose. Schemas and channels are written into the chunk where they are first
used, so the readable chunks of a killed recording are self-describing. ``close()`` writes
the ``rosbag2`` metadata record, the summary (schemas, channels, statistics, chunk, metadata
indexes) and the footer.

A write the operating system refuses (a full disk: ``OSError``) raises ``BagWriteError``
and ends the recording: the counts and times fall back to what reached the file (the chunks
written before), no more messages are written, and ``close()`` cuts the file back to its
last whole record and ends it there as a complete MCAP file (``cut_file.end_cut_file``).
"""
from __future__ import annotations

import io
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from mcap.well_known import MessageEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer

from em_exploration_ros.bag_format.cut_file import end_cut_file
from em_exploration_ros.bag_format.mcap_ros2_schema import MessageDefinition
from em_exploration_ros.bag_format.qos_yaml import QosProfile, qos_profiles_to_yaml
from em_exploration_ros.bag_format.rosbag2_metadata import (
    EMPTY_BAG_STARTING_TIME_NS, METADATA_RECORD_NAME, SERIALIZATION_FORMAT,
    SERIALIZED_METADATA_KEY, BagMetadata, TopicInformation, serialize_bag_metadata)

PROFILE = "ros2"
LIBRARY = f"em_exploration_ros bag_writer; {LIBRARY_IDENTIFIER}"
#: Channel metadata keys read by rosbag2's MCAP plugin.
QOS_METADATA_KEY = "offered_qos_profiles"
TYPE_HASH_METADATA_KEY = "topic_type_hash"
#: Default uncompressed chunk size [bytes].
DEFAULT_CHUNK_SIZE = 1024 * 1024
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}


class BagWriteError(Exception):
    """The operating system refused a write to the bag (e.g. a full disk); one line naming
    the file and the OS error."""


class _UnbufferedSink:
    """The file-like object the MCAP writer writes to: every write goes straight to the OS."""

    def __init__(self, raw: io.FileIO) -> None:
        self._raw = raw
        self.bytes_written = 0

    @property
    def file(self) -> io.FileIO:
        """The file itself."""
        return self._raw

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            written = self._raw.write(view)
            self.bytes_written += written
            view = view[written:]
        return len(data)

    def tell(self) -> int:
        return self._raw.tell()

    def flush(self) -> None:
        """Nothing is buffered here; the data is already in the OS page cache."""

    def close(self) -> None:
        self._raw.close()


@dataclass
class _Topic:
    name: str
    type_name: str
    offered_qos: tuple[QosProfile, ...]
    type_hash: str
    count: int = 0
    stored: int = 0  # of count, messages in chunks handed to the OS


def new_file(path: Path) -> io.FileIO:
    """``path`` created as a new unbuffered file (FileExistsError if it exists): the file a
    ``BagWriter`` writes unless it is given another maker."""
    return io.FileIO(path, "xb")


class BagWriter:
    """Writes one MCAP file that ``ros2 bag play``/``info`` and Foxglove accept.

    Times are nanoseconds of the recording clock (the ROS clock: sim time when it runs).
    Creating the writer creates ``path`` with ``create`` (a new file, unbuffered; a test
    gives a file that fails as a full disk does) and fails with ``FileExistsError`` if it
    exists.
    """

    def __init__(self, path: str | os.PathLike[str], *, compression: str = "zstd",
                 chunk_size: int = DEFAULT_CHUNK_SIZE, library: str = LIBRARY,
                 create: Callable[[Path], io.FileIO] = new_file) -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, "
                             f"got {compression!r}")
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        self.path = Path(path)
        self._sink = _UnbufferedSink(create(self.path))
        self._mcap = Writer(self._sink, chunk_size=chunk_size,
                            compression=COMPRESSIONS[compression], index_types=IndexType.ALL,
                            enable_crcs=True)
        self._mcap.start(profile=PROFILE, library=library)
        self._schema_ids: dict[str, int] = {}
        self._topics: dict[int, _Topic] = {}
        self._start_ns: int | None = None
        self._end_ns = 0
        self._stored_span: tuple[int | None, int] = (None, 0)  # start, end of stored messages
        self._whole_bytes = self._sink.bytes_written  # the file up to its last whole step
        self._failure: BagWriteError | None = None
        self._closed = False

    @property
    def closed(self) -> bool:
        """True once ``close()`` was called."""
        return self._closed

    @property
    def failure(self) -> BagWriteError | None:
        """The write the OS refused, which ended the file; None while all went well."""
        return self._failure

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return sum(topic.count for topic in self._topics.values())

    def topic_counts(self) -> dict[str, int]:
        """Messages written so far per topic name."""
        return {topic.name: topic.count for topic in self._topics.values()}

    def add_topic(self, name: str, definition: MessageDefinition,
                  offered_qos: tuple[QosProfile, ...] = (), type_hash: str = "") -> int:
        """Register a topic (one channel; its schema once per type); returns the channel id.

        ``offered_qos`` are the publishers' profiles (channel metadata offered_qos_profiles),
        ``type_hash`` the ``RIHS01_...`` type description hash (metadata topic_type_hash).
        """
        if any(topic.name == name for topic in self._topics.values()):
            raise ValueError(f"topic {name} is already registered")
        with self._writing():
            schema_id = self._schema_ids.get(definition.type_name)
            if schema_id is None:
                schema_id = self._mcap.register_schema(
                    definition.type_name, definition.encoding, definition.text.encode("utf-8"))
                self._schema_ids[definition.type_name] = schema_id
            channel_id = self._mcap.register_channel(
                name, MessageEncoding.CDR, schema_id,
                {QOS_METADATA_KEY: qos_profiles_to_yaml(offered_qos),
                 TYPE_HASH_METADATA_KEY: type_hash})
        self._topics[channel_id] = _Topic(name, definition.type_name, tuple(offered_qos),
                                          type_hash)
        return channel_id

    def write(self, channel_id: int, log_time_ns: int, data: bytes,
              publish_time_ns: int | None = None) -> None:
        """Append one CDR-serialized message, as received, to the current chunk.

        ``log_time_ns`` is the time of receipt, ``publish_time_ns`` (default: the log time)
        the time of publication; the sequence number counts messages per channel from 1.
        Raises BagWriteError if the OS refuses the chunk this message completes.
        """
        with self._writing():
            topic = self._topics[channel_id]
            topic.count += 1
            self._start_ns = (log_time_ns if self._start_ns is None
                              else min(self._start_ns, log_time_ns))
            self._end_ns = max(self._end_ns, log_time_ns)
            self._mcap.add_message(
                channel_id=channel_id, log_time=log_time_ns, data=data,
                publish_time=log_time_ns if publish_time_ns is None else publish_time_ns,
                sequence=topic.count)

    def flush(self) -> None:
        """Close the chunk in progress (if it holds messages) and hand it to the OS; raises
        BagWriteError if the OS refuses it."""
        if not self._closed:
            with self._writing():
                self._mcap.flush()

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """Run a step of the MCAP writer: once it has handed bytes to the OS, every message
        counted so far is in the file; an OSError ends the file (module docstring)."""
        if self._failure is not None:
            raise self._failure
        written = self._sink.bytes_written
        try:
            yield
        except OSError as error:
            for topic in self._topics.values():
                topic.count = topic.stored
            self._start_ns, self._end_ns = self._stored_span
            self._failure = BagWriteError(
                f"cannot write to {self.path}: {error.strerror or error}")
            raise self._failure from error
        if self._sink.bytes_written != written:
            for topic in self._topics.values():
                topic.stored = topic.count
            self._stored_span = (self._start_ns, self._end_ns)
            self._whole_bytes = self._sink.bytes_written

    def metadata(self) -> BagMetadata:
        """The rosbag2 bag metadata of what was written so far."""
        start = EMPTY_BAG_STARTING_TIME_NS if self._start_ns is None else self._start_ns
        topics = tuple(TopicInformation(
            name=t.name, type=t.type_name, message_count=t.count,
            offered_qos_profiles=t.offered_qos, type_description_hash=t.type_hash,
            serialization_format=SERIALIZATION_FORMAT) for t in self._topics.values())
        return BagMetadata(
            relative_file_path=self.path.name, starting_time_ns=start,
            duration_ns=0 if self._start_ns is None else self._end_ns - self._start_ns,
            message_count=self.message_count, topics=topics)

    def close(self) -> None:
        """Write the rosbag2 metadata record, summary and footer; close the file. Idempotent.

        After a BagWriteError (``failure``) the file is cut back to its last whole record and
        ended there (``end_cut_file``). Raises BagWriteError if the OS refuses these last
        records.
        """
        if self._closed:
            return
        self._closed = True
        self._release_reserve()
        try:
            if self._failure is None:
                with self._writing():
                    self._mcap.flush()
                with self._writing():
                    self._mcap.add_metadata(METADATA_RECORD_NAME, self._rosbag2_metadata())
                    self._mcap.finish()
            else:
                try:
                    end_cut_file(self._sink.file, self._whole_bytes, METADATA_RECORD_NAME,
                                 self._rosbag2_metadata())
                except OSError as error:
                    raise BagWriteError(f"cannot end {self.path} after the refused write: "
                                        f"{error.strerror or error}") from error
        finally:
            self._sink.close()

    def _rosbag2_metadata(self) -> dict[str, str]:
        """The content of the rosbag2 metadata record: the bag's metadata as YAML."""
        return {SERIALIZED_METADATA_KEY: serialize_bag_metadata(self.metadata())}

    def _release_reserve(self) -> None:
        """Free the space kept for the end of the file (a bag directory's reserve file);
        nothing here."""

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()
