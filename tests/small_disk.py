"""A small disk for tests of what a full disk does: a tmpfs of a given size, mounted in the
test's temporary folder and unmounted afterwards. Mounting needs root: without it the test
is skipped, saying so."""
from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest


@contextmanager
def small_disk(where: Path, size_kib: int) -> Iterator[Path]:
    """A tmpfs of ``size_kib`` KiB mounted at ``where`` (made here), unmounted at the end."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs (a small disk that fills up) needs root")
    where.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(where)],
                   check=True)
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)
