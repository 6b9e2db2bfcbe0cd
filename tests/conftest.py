"""Session-wide set-up of the tests: an isolated ROS 2 environment for every test run.

launch_scripts/run_tests.sh already exports ROS_DOMAIN_ID (a domain it holds a lock on),
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and AMENT_PREFIX_PATH. When pytest is started
directly (e.g. `.venv/bin/python -m pytest tests/...`), this module does the same before any
test runs, with the same lock scheme, so that a test run never talks to another run or to a
ROS 2 system on the network:

- ROS_DOMAIN_ID, if unset: a domain in 1..101 not held by another run on this machine (an
  exclusive flock on <tmp>/em_exploration_ros-ros-domains/<id>.lock, held by this process).
- ROS_AUTOMATIC_DISCOVERY_RANGE, if unset: LOCALHOST.
- AMENT_PREFIX_PATH: the venv prefix first, so ament_index_python finds this venv's packages.

Processes started by tests inherit os.environ and therefore the same domain.

SIGTERM (what a CI job's timeout or `kill` sends) ends the run as Ctrl-C does: pytest
stops and the tests' clean-up runs, so the processes they started are stopped too. By
default SIGTERM ended pytest at once and left every running team behind.
"""
from __future__ import annotations

import fcntl
import os
import signal
import sys
import tempfile
from pathlib import Path
from typing import IO

# Lowest and highest domain used; 0 (the ROS default) is left to other software.
_DOMAIN_MIN, _DOMAIN_MAX = 1, 101
_DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "em_exploration_ros-ros-domains"

# The lock file of the domain this process chose, kept open (and so held) for the session.
_domain_lock: IO[bytes] | None = None


def _hold_free_ros_domain() -> int:
    """Lock and return a free ROS domain id, trying ids in turn from one derived from the PID."""
    global _domain_lock
    _DOMAIN_LOCK_DIR.mkdir(parents=True, exist_ok=True)
    count = _DOMAIN_MAX - _DOMAIN_MIN + 1
    first = os.getpid() % count
    for offset in range(count):
        domain = _DOMAIN_MIN + (first + offset) % count
        lock = open(_DOMAIN_LOCK_DIR / f"{domain}.lock", "wb")  # stays open while held
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            continue
        _domain_lock = lock
        return domain
    raise RuntimeError(f"all ROS domains {_DOMAIN_MIN}..{_DOMAIN_MAX} are held by other runs "
                       f"(locks in {_DOMAIN_LOCK_DIR})")


def _isolate_ros_environment() -> None:
    """Set the ROS 2 environment variables described in the module docstring."""
    if "ROS_DOMAIN_ID" not in os.environ:
        os.environ["ROS_DOMAIN_ID"] = str(_hold_free_ros_domain())
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if not prefixes or prefixes[0] != sys.prefix:
        os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(
            [sys.prefix] + [p for p in prefixes if p != sys.prefix])


def _interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")


# At import, i.e. before any test module is collected and could initialise rclpy.
_isolate_ros_environment()
signal.signal(signal.SIGTERM, _interrupt)


def pytest_unconfigure(config: object) -> None:
    """Release the domain lock this session held (closing its file), at the very end."""
    global _domain_lock
    if _domain_lock is not None:
        _domain_lock.close()
        _domain_lock = None
