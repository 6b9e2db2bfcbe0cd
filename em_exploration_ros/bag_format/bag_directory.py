"""Bag directories as ``ros2 bag record -s mcap`` writes them, and finding a bag's MCAP file.

A rosbag2 bag is a directory ``NAME/`` holding its storage files, ``NAME_0.mcap`` (then
``NAME_1.mcap`` ... when rosbag2 splits), and ``metadata.yaml``: the bag metadata under the
key ``rosbag2_bagfile_information``, written when the recording is closed. A recording that
was killed has no ``metadata.yaml``; its MCAP file alone is what is left (``em-bag repair``).

The tools accept a bag directory or a single ``.mcap`` file wherever they read a recording.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Any

import yaml

from em_exploration_ros.bag_format.bag_writer import BagWriteError, BagWriter
from em_exploration_ros.bag_format.rosbag2_metadata import (
    BagMetadata, MetadataFormatError, bag_metadata_node, parse_bag_metadata)
from em_exploration_ros.core.output_paths import write_replacing
from em_exploration_ros.core.untrusted_yaml import load_yaml, shown_value

METADATA_FILE = "metadata.yaml"
METADATA_ROOT_KEY = "rosbag2_bagfile_information"
STORAGE_SUFFIX = ".mcap"
#: Space a recording keeps free in its bag directory [bytes]: a reserve file, removed when
#: the bag is closed, so that the end of the MCAP file (summary, footer) and metadata.yaml
#: can still be written when the disk filled up. The sample 3-robot bag's are 75 kB and
#: 32 kB; its summary grows with the topics (robots) and the chunks (mission length).
RESERVE_BYTES = 8 * 1024 * 1024
RESERVE_FILE = ".space_reserve"


class BagPathError(ValueError):
    """A path is neither a readable single-file bag directory nor an MCAP file."""


def storage_file_name(directory: Path) -> str:
    """Name of a bag directory's first storage file, as rosbag2 names it (``NAME_0.mcap``)."""
    return f"{directory.name}_0{STORAGE_SUFFIX}"


def metadata_yaml(metadata: BagMetadata) -> str:
    """The text of ``metadata.yaml`` for a bag's metadata."""
    return yaml.safe_dump({METADATA_ROOT_KEY: bag_metadata_node(metadata)}, sort_keys=False)


def _metadata_document(directory: Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of a directory's metadata.yaml."""
    path = directory / METADATA_FILE
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise MetadataFormatError(f"{path}: cannot read: {error.strerror}") from None
    except UnicodeDecodeError:
        raise MetadataFormatError(f"{path}: not UTF-8 text") from None
    document = load_yaml(text, str(path), MetadataFormatError)
    node = document.get(METADATA_ROOT_KEY) if isinstance(document, dict) else None
    if not isinstance(node, dict):
        raise MetadataFormatError(f"{path}: no {METADATA_ROOT_KEY} mapping")
    return node


def read_metadata_yaml(directory: Path) -> BagMetadata:
    """The metadata of a bag directory; raises MetadataFormatError."""
    return parse_bag_metadata(yaml.safe_dump(_metadata_document(directory)))


def mcap_file(path: str | os.PathLike[str]) -> Path:
    """The MCAP file of a recording given as a ``.mcap`` file or a bag directory.

    For a directory: the file ``metadata.yaml`` names, or (no ``metadata.yaml``: a killed
    recording) its only ``.mcap`` file. Raises BagPathError for a missing path, a directory
    without exactly one storage file, a bag of another storage format, a storage file
    outside the directory, or a FIFO, socket or device.
    """
    path = Path(path)
    if not path.exists():
        raise BagPathError(f"{path}: no such file or directory")
    if not path.is_dir():
        return _not_special(path)
    if (path / METADATA_FILE).is_file():
        try:
            node = _metadata_document(path)
        except MetadataFormatError as error:
            raise BagPathError(f"unreadable bag metadata: {error}") from None
        if node.get("storage_identifier") != "mcap":
            raise BagPathError(f"{path}: storage {shown_value(node.get('storage_identifier'))}, "
                               "not mcap")
        files = node.get("relative_file_paths") or []
        if not isinstance(files, list) or not all(isinstance(name, str) for name in files):
            raise BagPathError(f"{path / METADATA_FILE}: relative_file_paths is not a list of "
                               f"file names: {shown_value(files)}")
    else:
        files = sorted(p.name for p in path.glob(f"*{STORAGE_SUFFIX}"))
    if len(files) != 1:
        raise BagPathError(f"{path}: a bag directory with {len(files)} storage files; "
                           "only single-file bags are read")
    return _storage_file(path, files[0])


def _storage_file(directory: Path, name: str) -> Path:
    """The storage file ``name`` of a bag directory; raises BagPathError unless the name is a
    relative path that stays inside the directory."""
    if (not name or "\0" in name or Path(name).is_absolute()
            or os.path.normpath(name).split(os.sep)[0] == ".."):
        raise BagPathError(f"{directory / METADATA_FILE}: storage file {shown_value(name)} is not "
                           "a file inside the bag directory")
    return _not_special(directory / name)


def _not_special(path: Path) -> Path:
    """``path``; raises BagPathError if it is a FIFO, socket or device (reading one could
    block for ever). A missing or unreadable file or a directory is left to the reader to
    report."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return path
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise BagPathError(f"{path}: not a regular file")
    return path


class BagDirectoryWriter(BagWriter):
    """A BagWriter that records into a new bag directory: ``DIR/DIR_0.mcap`` while recording,
    plus ``DIR/metadata.yaml`` when closed. Fails with FileExistsError if ``DIR`` exists, and
    with OSError (leaving no directory) if it cannot keep ``reserve_bytes`` free in it."""

    def __init__(self, directory: str | os.PathLike[str], *, reserve_bytes: int = RESERVE_BYTES,
                 **options: Any) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True)
        self._reserve = self.directory / RESERVE_FILE
        try:
            _keep_space(self._reserve, reserve_bytes)
            super().__init__(self.directory / storage_file_name(self.directory), **options)
        except BaseException:
            self._reserve.unlink(missing_ok=True)
            for leftover in self.directory.iterdir():
                leftover.unlink()
            self.directory.rmdir()
            raise

    def _release_reserve(self) -> None:
        """Give the reserve's space back for the end of the file and metadata.yaml."""
        self._reserve.unlink(missing_ok=True)

    def close(self) -> None:
        """Close the MCAP file, then write ``metadata.yaml`` (atomically), also after a
        BagWriteError (it then describes what reached the file). Idempotent. Raises
        BagWriteError if the OS refuses the last records of the MCAP file or metadata.yaml
        (then none is left)."""
        if self.closed:
            return
        try:
            super().close()
        finally:
            target = self.directory / METADATA_FILE
            text = metadata_yaml(self.metadata())
            try:
                write_replacing(target, lambda partial: partial.write_text(text, encoding="utf-8"))
            except OSError as error:
                raise BagWriteError(f"cannot write {target}: {error.strerror or error}; the bag "
                                    f"has no {METADATA_FILE}") from error


def _keep_space(path: Path, size: int) -> None:
    """Create ``path`` holding ``size`` bytes of disk space (allocated, not a sparse file)."""
    with open(path, "xb") as reserve:
        try:
            os.posix_fallocate(reserve.fileno(), 0, size)
        except OSError as error:
            if error.errno != errno.EOPNOTSUPP:
                raise
            reserve.write(bytes(size))  # a file system without fallocate
