"""Fast DDS's files and ports on one host: the RTPS port mapping, the names of the
shared-memory files in /dev/shm, and whether a file's owner is alive.

Ports (the RTPS specification's default mapping, Fast DDS's too): participant ``id`` of ROS
domain ``domain`` has the UDP discovery port ``7400 + 250 domain + 10 + 2 id`` and the user
data port ``... + 11 + 2 id``; its shared-memory port is the file ``fastrtps_port<user data
port>`` (with ``..._el`` and ``sem.fastrtps_port<port>_mutex``). A process's segment is
``fastrtps_<16 characters>`` (with ``..._el``). A live process holds an exclusive ``flock``
on each ``_el`` file it made; one that can be locked is a dead process's. Fast DDS tells a
dead port the same way: a process writing to a port takes its lock for a moment to see
whether the port's owner is alive (``SharedMemGlobal::Port::is_zombie``), so a lock found
held once may be such a look, not an owner.
"""
from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

PORT_BASE = 7400
DOMAIN_GAIN = 250
PARTICIPANT_GAIN = 2
DISCOVERY_OFFSET = 10
USER_DATA_OFFSET = 11
SHARED_MEMORY_DIR = Path("/dev/shm")
LOCK_SUFFIX = "_el"
PORT_PREFIX = "fastrtps_port"
#: Tries, and the pause [s] between them, before a port's lock counts as an owner's: another
#: process's look at it (module docstring) lasts microseconds, an owner's hold its life.
PORT_LOCK_TRIES = 3
PORT_LOCK_PAUSE_S = 0.002


def _port(domain: int, participant: int, offset: int) -> int:
    """``participant``'s port in ``domain`` at ``offset`` of the mapping (module docstring)."""
    return PORT_BASE + DOMAIN_GAIN * domain + offset + PARTICIPANT_GAIN * participant


def discovery_port(domain: int, participant: int) -> int:
    """The UDP discovery (metatraffic unicast) port of ``participant`` in ``domain``."""
    return _port(domain, participant, DISCOVERY_OFFSET)


def shared_memory_port_file(domain: int, participant: int) -> str:
    """The /dev/shm file name of ``participant``'s shared-memory port in ``domain``."""
    return f"{PORT_PREFIX}{_port(domain, participant, USER_DATA_OFFSET)}"


def in_domain(port: int, domain: int) -> bool:
    """Whether ``port`` is one of ``domain``'s (the mapping gives each domain 250)."""
    return PORT_BASE + DOMAIN_GAIN * domain <= port < PORT_BASE + DOMAIN_GAIN * (domain + 1)


def lock_is_free(lock_file: Path, tries: int = 1) -> bool:
    """Whether no live process holds ``lock_file``'s flock: free at one of ``tries`` tries,
    ``PORT_LOCK_PAUSE_S`` apart (False if it cannot be opened; opened to read only, so that
    one removed meanwhile is not made anew)."""
    try:
        descriptor = os.open(lock_file, os.O_RDONLY)
    except OSError:
        return False
    try:
        for attempt in range(tries):
            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except OSError:
                if attempt + 1 < tries:
                    time.sleep(PORT_LOCK_PAUSE_S)
        return False
    finally:
        os.close(descriptor)


def dead_port_files(directory: Path = SHARED_MEMORY_DIR, domain: int | None = None
                    ) -> set[str]:
    """Names of the shared-memory port files in ``directory`` (of ``domain``'s ports, if
    given) that no live process listens on: their lock is free (within
    ``PORT_LOCK_TRIES``), or they have none. A writer that found a port's listener dead
    makes the port anew without a lock file; so does, for a moment, a process opening its
    own port (which then counts as dead: a process starting beside it may take another
    id)."""
    if not directory.is_dir():
        return set()
    names = {path.name for path in directory.iterdir()}
    ports = {name for name in names
             if name.startswith(PORT_PREFIX) and name[len(PORT_PREFIX):].isdigit()
             and (domain is None or in_domain(int(name[len(PORT_PREFIX):]), domain))}
    return {name for name in ports
            if name + LOCK_SUFFIX not in names
            or lock_is_free(directory / (name + LOCK_SUFFIX), PORT_LOCK_TRIES)}
