"""Remove the Fast DDS shared-memory files that dead processes left in /dev/shm, of one ROS
domain's ports only: ``python -m em_exploration_ros.tools.shm_leftovers --domain D``.

A Fast DDS process killed by SIGKILL (or crashed) leaves its files, a segment and its ports
(``nodes/fastdds_shm.py``), whose locks no live process holds any more. On a lab machine
such files pile up, and with about 950 of them a run's processes missed some of each other's
data (docs/results.md "Set-up and tests"). run_team.sh and run_tests.sh run this before
their processes start (``em_clean_shared_memory`` in launch_scripts/_common.sh).

Fast DDS's own ``fastdds shm clean`` removes every dead port of the host. That is not safe
beside another run: a dead port's file is what tells that run's restarted process not to
take the dead one's participant id (``nodes/participant_id.py``), while the others' writers
may still write into the dead port. So ports are removed only in the domain given (whose
run lock the caller holds: no live process maps them), with the port files that have no
lock file (made anew by a writer that found the port's listener dead); segments, named once
at random and never taken again, wherever they are dead. Files of other users, which cannot
be removed, stay. Prints one line of what it removed (nothing when nothing was); exit code
0, or 2 for a wrong argument.
"""
from __future__ import annotations

import re
import sys
from collections.abc import Sequence
from pathlib import Path

from em_exploration_ros.nodes.fastdds_shm import (LOCK_SUFFIX, SHARED_MEMORY_DIR,
                                                  dead_port_files, lock_is_free)
from em_exploration_ros.tools.cli_parser import CliParser

SEGMENT = re.compile(r"^fastrtps_[0-9a-z]{16}$")
#: ROS 2's highest domain id (with the default port mapping).
MAX_DOMAIN = 232


def _remove(paths: Sequence[Path]) -> bool:
    """Remove ``paths`` (those that exist); False if one could not be removed."""
    removed = True
    for path in paths:
        try:
            path.unlink(missing_ok=True)
        except OSError:
            removed = False
    return removed


def remove_leftovers(domain: int, directory: Path = SHARED_MEMORY_DIR) -> tuple[int, int]:
    """Remove the dead ports of ``domain`` (``fastdds_shm.dead_port_files``: those without a
    lock file too) and every dead segment in ``directory``; returns (ports, segments)
    removed."""
    ports = sum(_remove([directory / name, directory / (name + LOCK_SUFFIX),
                         directory / f"sem.{name}_mutex"])
                for name in sorted(dead_port_files(directory, domain)))
    names = {path.name for path in directory.iterdir()} if directory.is_dir() else set()
    segments = sum(_remove([directory / name, directory / (name + LOCK_SUFFIX)])
                   for name in sorted(names)
                   if SEGMENT.match(name) and name + LOCK_SUFFIX in names
                   and lock_is_free(directory / (name + LOCK_SUFFIX)))
    return ports, segments


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    parser = CliParser(prog="shm_leftovers", description=__doc__.split("\n\n")[0])
    parser.add_argument("--domain", type=int, required=True,
                        help=f"the ROS domain whose dead ports go (0-{MAX_DOMAIN})")
    parser.add_argument("--prog", default="shm_leftovers",
                        help="the name the printed line begins with (the caller's)")
    args = parser.parse_args(argv)
    if not 0 <= args.domain <= MAX_DOMAIN:
        parser.error(f"argument --domain: must be in [0, {MAX_DOMAIN}], got {args.domain}")
    ports, segments = remove_leftovers(args.domain)
    if ports or segments:
        print(f"{args.prog}: removed the shared-memory files of {ports} port(s) of ROS domain "
              f"{args.domain} and {segments} segment(s) that dead Fast DDS processes left in "
              f"{SHARED_MEMORY_DIR}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
