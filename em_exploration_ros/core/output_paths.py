"""Checking, before a run starts, that the files it will write can be written, and
writing them whole or not at all.

A run that fails only at its end, after minutes of work, because its summary's folder is
missing or read-only loses everything; em-sim, run_team.sh (summary, recording) and the
evaluator node check their output paths first with ``output_path_problem`` and refuse to
start. ``write_replacing`` writes a file through a temporary one, so a write that fails
at the end (full disk) leaves no truncated file.
"""
from __future__ import annotations

import os
import secrets
import stat
import tempfile
from pathlib import Path
from typing import Callable


def output_path_problem(path: str | Path, what: str = "output file",
                        suffix: str | None = None) -> str | None:
    """Reason why ``path`` cannot be written, or None. A symbolic link is followed (a
    dangling one to where it points); the folder must exist and accept a new file (probed
    by creating and removing a temporary file, which also catches read-only file systems
    and is right for root); an existing ``path`` must be a regular file (not a folder, nor
    a device such as /dev/full); with ``suffix`` (e.g. ``.png``), the name must end in it
    (any case)."""
    target = Path(path).expanduser()
    if suffix is not None and target.suffix.lower() != suffix.lower():
        return f"{what} {target} must end in {suffix}"
    try:
        resolved = target.resolve()
    except (OSError, RuntimeError) as error:  # RuntimeError: a symbolic link loop
        return f"{what} {target}: cannot follow its symbolic links ({error})"
    shown = target if resolved == target.absolute() else f"{target} (-> {resolved})"
    folder = resolved.parent
    if resolved.is_dir():
        return f"{what} {shown} is a directory"
    if resolved.exists() and not stat.S_ISREG(resolved.stat().st_mode):
        return f"{what} {shown} is not a regular file"
    if not folder.is_dir():
        return f"{what} {shown}: the folder {folder} does not exist"
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write_probe_"):
            pass
    except OSError as error:
        return f"{what} {shown}: cannot write in {folder} ({error.strerror})"
    return None


def write_replacing(path: str | Path, write: Callable[[Path], object]) -> None:
    """Write the file ``path`` (symbolic links followed) with ``write(temporary_path)`` and
    rename the result over ``path``; if ``write`` fails (``OSError`` for a full disk),
    the temporary file is removed and ``path`` is left as it was. The temporary file is
    in the same folder and has the same suffix (which selects e.g. matplotlib's format)."""
    target = Path(path).expanduser().resolve()
    temporary = target.with_name(f".{target.stem}.{secrets.token_hex(4)}.partial{target.suffix}")
    # Created with mode 0o666 less the umask, the mode a file written in place gets.
    os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    try:
        write(temporary)
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
