"""Checking, before a run starts, that the files it will write can be written.

A run that fails only at its end, after minutes of work, because its summary's folder is
missing or read-only loses everything; em-sim, run_team.sh (summary, recording) and the
evaluator node check their output paths first with ``output_path_problem`` and refuse to
start.
"""
from __future__ import annotations

import tempfile
from pathlib import Path


def output_path_problem(path: str | Path, what: str = "output file") -> str | None:
    """Reason why ``path`` cannot be written, or None: its folder must exist and accept a
    new file (probed by creating and removing a temporary file, which also catches
    read-only file systems and is right for root), and ``path`` must not be a folder."""
    target = Path(path).expanduser()
    folder = target.parent
    if target.is_dir():
        return f"{what} {target} is a directory"
    if not folder.is_dir():
        return f"{what} {target}: the folder {folder} does not exist"
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write_probe_"):
            pass
    except OSError as error:
        return f"{what} {target}: cannot write in {folder} ({error.strerror})"
    return None
