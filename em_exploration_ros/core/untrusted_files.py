"""Reading a file a user or an earlier run supplies (a parameter file, a benchmark's trial
record) without waiting for ever or reading without end.

Opening a FIFO waits for a writer, and a device such as /dev/zero never ends: only regular
files of a bounded size are read.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path


class NotRegularFile(ValueError):
    """The path is a FIFO, socket, device or folder."""


class FileTooLarge(ValueError):
    """The file holds more bytes than the caller reads; ``size`` [bytes] says how many."""

    def __init__(self, size: int, max_bytes: int) -> None:
        super().__init__(f"{size} bytes, more than {max_bytes}")
        self.size = size


def read_regular_file(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes`` of them: raises
    NotRegularFile or FileTooLarge (ValueErrors), or the OSError of opening or reading it.
    Opening does not wait for a FIFO's writer (it is refused), and a file that grows while
    it is read is still refused once it passes the bound."""
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        info = os.fstat(descriptor)
        if not stat.S_ISREG(info.st_mode):  # before open(): a folder's would raise there
            raise NotRegularFile(f"{path} is not a regular file")
        if info.st_size > max_bytes:
            raise FileTooLarge(info.st_size, max_bytes)
        file = open(descriptor, "rb")  # noqa: SIM115 (owns the descriptor from here on)
    except BaseException:
        os.close(descriptor)
        raise
    with file:
        data = file.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise FileTooLarge(len(data), max_bytes)
    return data
