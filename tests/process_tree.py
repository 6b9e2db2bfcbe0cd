"""Linux process-tree helpers for tests that start processes and must see them gone."""
from __future__ import annotations

import signal
from pathlib import Path


def _stat_fields(pid: int | str) -> list[str]:
    """The fields of /proc/PID/stat after the command name (state, parent pid, ...)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def children(pid: int) -> list[int]:
    """Processes whose parent is ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if int(_stat_fields(entry.name)[1]) == pid:
                found.append(int(entry.name))
        except (OSError, IndexError):
            continue  # gone meanwhile
    return found


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` in the tree, children first."""
    found, frontier = [], [pid]
    while frontier:
        below = [child for parent in frontier for child in children(parent)]
        found += below
        frontier = below
    return found


def command_line(pid: int) -> bytes:
    """The NUL-separated command line of ``pid`` (empty if it has gone meanwhile)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        return _stat_fields(pid)[0] != "Z"
    except OSError:
        return False


def interruptible() -> None:
    """In a child before it runs its command (``preexec_fn``): SIGINT and SIGHUP at their
    default action. A test suite started in the background by a non-interactive shell
    inherits SIGINT ignored (under nohup SIGHUP), a process keeps an ignored signal ignored,
    and Python then installs no KeyboardInterrupt handler: a test's Ctrl-C would not reach
    it. A terminal's Ctrl-C (or hangup) always meets the default action."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)
