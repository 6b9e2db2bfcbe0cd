"""A node process's Fast DDS participant id, kept off a dead process's shared-memory port.

Fast DDS gives a participant the first id (0, 1, ...) whose ports are free on this host, so
a process restarted after its predecessor was killed takes the predecessor's id, and with
it the name of its shared-memory port. The other processes' writers keep the dead port's
segment mapped and go on writing into it, and the restart gets none of their data (seen
with an evaluator restarted in CI: no ground truth for 60 s; docs/robustness.md "A restart
on its predecessor's shared-memory port"). A killed process leaves that port's file in
/dev/shm with no live listener (``fastdds_shm.dead_port_files``), while its UDP discovery
port is free again: that is how a dead process's id is told from a free one.

:func:`participant_to_avoid` judges this from the host's UDP socket tables and /dev/shm;
:func:`profile_with_participant_id` makes the Fast DDS profile that gives the process an id
of its own instead, the first from ``HIGHEST_ANNOUNCED_ID`` down whose ports are clean;
:func:`own_participant_id` puts that profile in place while the process makes its
participant (``node_main.first_node``: every node process, restarted by run_team.sh
``--respawn`` or by hand with ``ros2 run``, and em-record and em-replay).

A dead process's port file is evidence only while it is there: run_team.sh and run_tests.sh
remove dead ports of their own domain alone before they start (``tools/shm_leftovers.py``).
"""
from __future__ import annotations

import fcntl
import os
import re
import tempfile
import time
from collections.abc import Iterable, Iterator, MutableMapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from em_exploration_ros.nodes.fastdds_shm import (dead_port_files, discovery_port,
                                                  shared_memory_port_file)

#: Participants on one host announce themselves to ids 0..31 (rmw_fastrtps, localhost
#: discovery): a participant with a higher id is found by no one that starts after it.
HIGHEST_ANNOUNCED_ID = 31
#: Linux's tables of bound UDP sockets (``udp6`` is absent on a host without IPv6).
UDP_SOCKET_TABLES = (Path("/proc/net/udp"), Path("/proc/net/udp6"))
#: A profile that only sets the id (when the process has no profile file of its own).
BARE_PROFILE = ('<?xml version="1.0" encoding="UTF-8" ?>\n'
                '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'
                '  <participant profile_name="participant_id" is_default_profile="true">\n'
                '    <rtps>\n    </rtps>\n  </participant>\n</profiles>\n')


@dataclass(frozen=True)
class ParticipantChoice:
    """The id Fast DDS would give (``dead``: a dead process's) and the one to take instead
    (None when every id up to ``HIGHEST_ANNOUNCED_ID`` is held or dead)."""

    dead: int
    instead: int | None


def bound_udp_ports(tables: Iterable[str]) -> set[int]:
    """Local ports of the sockets in ``/proc/net/udp``-format ``tables`` (their text)."""
    ports = set()
    for text in tables:
        for line in text.splitlines()[1:]:
            match = re.match(r"\s*\d+:\s+[0-9A-Fa-f]+:([0-9A-Fa-f]{4})\s", line)
            if match:
                ports.add(int(match[1], 16))
    return ports


def participant_to_avoid(domain: int, bound_ports: set[int], dead_port_names: set[str]
                         ) -> ParticipantChoice | None:
    """The choice to make when the id Fast DDS would give (the first whose discovery port
    is not in ``bound_ports``) has its shared-memory port file in ``dead_port_names`` (port
    files no live process owns: a dead process's); None when it has not, or every id is
    held (Fast DDS chooses)."""
    def held(participant: int) -> bool:
        return discovery_port(domain, participant) in bound_ports

    def dead(participant: int) -> bool:
        return (not held(participant)
                and shared_memory_port_file(domain, participant) in dead_port_names)

    free = [p for p in range(HIGHEST_ANNOUNCED_ID + 1) if not held(p)]
    if not free or not dead(free[0]):
        return None
    clean = [p for p in reversed(free) if not dead(p)]
    return ParticipantChoice(free[0], clean[0] if clean else None)


def host_choice(domain: int) -> ParticipantChoice | None:
    """:func:`participant_to_avoid` from this host's UDP socket tables and /dev/shm; None
    (Fast DDS chooses) when they cannot be read: a node's start does not hang on them."""
    try:
        tables = [path.read_text() for path in UDP_SOCKET_TABLES if path.is_file()]
        return participant_to_avoid(domain, bound_udp_ports(tables),
                                    dead_port_files(domain=domain))
    except OSError:
        return None


#: Looks at the host, and the pause [s] between them, before a process takes Fast DDS's
#: choice: a writer that finds a dead port resets it (removes its file, then makes it anew,
#: ``SharedMemGlobal``'s "Port Zombie. Reset the port"), and a look between the two saw no
#: dead port (a restarted evaluator took its predecessor's id in 3 of 8 runs of its test).
CHOICE_LOOKS = 5
CHOICE_LOOK_PAUSE_S = 0.02


def looked_choice(domain: int) -> ParticipantChoice | None:
    """:func:`host_choice` at the first of ``CHOICE_LOOKS`` looks that finds one, None when
    none does."""
    for look in range(CHOICE_LOOKS):
        choice = host_choice(domain)
        if choice is not None or look + 1 == CHOICE_LOOKS:
            return choice
        time.sleep(CHOICE_LOOK_PAUSE_S)
    return None


def profile_with_participant_id(profile: str | None, participant: int) -> str | None:
    """The Fast DDS profile ``profile`` (XML text; None: none, ``BARE_PROFILE``) with
    ``<participantID>`` set in its first ``<rtps>`` element; None when it sets one already
    or has no ``<rtps>`` element (the caller's choice stands)."""
    text = BARE_PROFILE if profile is None else profile
    if "<participantID>" in text or "<rtps>" not in text:
        return None
    return text.replace("<rtps>", f"<rtps>\n      <participantID>{participant}</participantID>",
                        1)


PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"
#: Processes that take an id of their own choose, and make their participant, one at a
#: time per domain, under an flock on this file (``{domain}``): two restarted at once saw
#: the same free id, which only one of them can have.
CHOICE_LOCK = "em_exploration_participant_choice_{domain}.lock"
#: The folder, beside that lock file, of the profiles' copies (one per process id).
PROFILE_COPIES = "em_exploration_participant_profiles"
#: How long [s] a process waits for that lock before it chooses without it (a process
#: stopped while holding it must not stop the others' starts).
CHOICE_LOCK_WAIT_S = 10.0


class ParticipantProfile:
    """What :func:`own_participant_id` did: ``line`` to log (None when nothing was
    changed), and :meth:`release`, to call once the process's first node exists (rmw_fastrtps
    makes the participant, binding its ports, and Fast DDS reads the profile, with the
    first node, not at ``rclpy.init``)."""

    def __init__(self, line: str | None = None,
                 environ: MutableMapping[str, str] | None = None,
                 previous: str | None = None, copy: str | None = None,
                 lock: IO[bytes] | None = None) -> None:
        self.line = line
        self._environ = environ
        self._previous = previous
        self._copy = copy
        self._lock = lock

    def release(self) -> None:
        """The profile variable as before, the copy removed, the choice's lock let go (once;
        later calls do nothing)."""
        if self._environ is not None and self._copy is not None:
            if self._previous is None:
                self._environ.pop(PROFILE_VARIABLE, None)
            else:
                self._environ[PROFILE_VARIABLE] = self._previous
            Path(self._copy).unlink(missing_ok=True)  # a temporary-folder cleaner's already
            self._copy = None
        if self._lock is not None:
            self._lock.close()
            self._lock = None


@contextmanager
def own_participant_id(environ: MutableMapping[str, str] = os.environ,
                       lock_dir: Path | None = None) -> Iterator[ParticipantProfile]:
    """For the block (``rclpy.init`` and the first node): when Fast DDS would give this
    process a dead process's id (:func:`looked_choice`), ``environ[PROFILE_VARIABLE]`` names a
    copy of the process's profile with an id of its own, until
    :meth:`ParticipantProfile.release` or the block's end; the choice is made under the
    domain's ``CHOICE_LOCK`` in ``lock_dir`` (the temporary folder), held until then, and
    the copy is written in its ``PROFILE_COPIES`` folder. Only for rmw_fastrtps_cpp, and
    never over a profile that sets its own id."""
    profile = _own_participant_profile(environ, lock_dir or Path(tempfile.gettempdir()))
    try:
        yield profile
    finally:
        profile.release()


def _choice_lock(path: Path) -> tuple[IO[bytes] | None, str]:
    """``path`` open with an exclusive flock on it, or None and why not: it cannot be
    opened, or had within ``CHOICE_LOCK_WAIT_S``."""
    try:
        handle = os.fdopen(os.open(path, os.O_RDWR | os.O_CREAT, 0o666), "r+b")
    except OSError as error:
        return None, f"it cannot be opened: {error.strerror}"
    deadline = time.monotonic() + CHOICE_LOCK_WAIT_S
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return handle, ""
        except OSError:
            if time.monotonic() >= deadline:
                handle.close()
                return None, (f"another process held it for over {CHOICE_LOCK_WAIT_S:g} s")
            time.sleep(0.02)


def _profile_copy(lock_dir: Path) -> Path:
    """Where this process writes its profile's copy: ``PROFILE_COPIES/<pid>.xml`` in
    ``lock_dir``, the copies of processes that are gone removed first (a process killed
    while it made its participant leaves its copy; the next one that chooses removes it)."""
    folder = lock_dir / PROFILE_COPIES
    folder.mkdir(mode=0o777, exist_ok=True)
    for left in folder.glob("*.xml"):
        if left.stem.isdigit() and not _alive(int(left.stem)):
            try:
                left.unlink(missing_ok=True)
            except OSError:
                pass  # another user's: theirs to remove
    return folder / f"{os.getpid()}.xml"


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def _own_participant_profile(environ: MutableMapping[str, str], lock_dir: Path
                             ) -> ParticipantProfile:
    """:func:`own_participant_id`'s profile, in place."""
    if environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return ParticipantProfile()
    try:
        domain = int(environ.get("ROS_DOMAIN_ID") or 0)
    except ValueError:
        return ParticipantProfile()  # rclpy refuses it itself
    if looked_choice(domain) is None:
        return ParticipantProfile()
    lock, no_lock = _choice_lock(lock_dir / CHOICE_LOCK.format(domain=domain))
    choice = looked_choice(domain)  # again, with the ids the others took meanwhile
    if choice is None:
        return ParticipantProfile(lock=lock)
    dead_port = shared_memory_port_file(domain, choice.dead)
    if choice.instead is None:
        return ParticipantProfile(
            f"Fast DDS gives this process participant id {choice.dead}, whose shared-memory "
            f"port a dead process left (/dev/shm/{dead_port}); every other id up to "
            f"{HIGHEST_ANNOUNCED_ID} is held or dead too", lock=lock)
    previous = environ.get(PROFILE_VARIABLE)
    try:
        text = profile_with_participant_id(Path(previous).read_text() if previous else None,
                                           choice.instead)
    except OSError:
        text = None  # rmw_fastrtps reports an unreadable profile itself
    if text is None:
        return ParticipantProfile(lock=lock)
    try:
        copy = str(_profile_copy(lock_dir))
        with open(copy, "w") as file:
            file.write(text)
    except OSError as error:
        return ParticipantProfile(
            f"Fast DDS gives this process participant id {choice.dead}, whose shared-memory "
            f"port a dead process left (/dev/shm/{dead_port}): a profile with id "
            f"{choice.instead} could not be written ({error})", lock=lock)
    environ[PROFILE_VARIABLE] = copy
    return ParticipantProfile(
        f"participant id {choice.instead} instead of {choice.dead}: a process that died held "
        f"id {choice.dead} and left its shared-memory port (/dev/shm/{dead_port}), into "
        f"which the others may still write"
        + ("" if lock else f" (chosen without {CHOICE_LOCK.format(domain=domain)}: "
                           f"{no_lock})"),
        environ, previous, copy, lock)
