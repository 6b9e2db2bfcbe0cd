"""Fast DDS's shared-memory files: which are a dead process's (``nodes/fastdds_shm.py``) and
their removal in one domain (``tools/shm_leftovers.py``), on a folder of files made here with
their locks held or not."""
from __future__ import annotations

import fcntl
import os
import subprocess
import sys

import pytest

from em_exploration_ros.nodes import fastdds_shm
from em_exploration_ros.nodes.fastdds_shm import (dead_port_files, discovery_port, in_domain,
                                                  shared_memory_port_file)
from em_exploration_ros.tools.shm_leftovers import remove_leftovers

SEGMENT_LIVE, SEGMENT_DEAD, SEGMENT_NO_LOCK = ("fastrtps_0123456789abcdef",
                                               "fastrtps_fedcba9876543210",
                                               "fastrtps_aaaaaaaaaaaaaaaa")


def test_the_port_mapping_is_rtps_s():
    # Domain 77, participant 0: 26660 = 0x6824, seen bound by an rclpy node.
    assert discovery_port(77, 0) == 0x6824 and discovery_port(77, 3) == 26666
    assert shared_memory_port_file(77, 3) == "fastrtps_port26667"
    assert in_domain(26667, 77) and in_domain(7400 + 250 * 77, 77)
    assert not in_domain(7400 + 250 * 78, 77) and not in_domain(7000, 0)


@pytest.fixture()
def shm(tmp_path):
    """A folder as /dev/shm with: in domain 5, a live port (participant 0, its lock held
    here), a dead one (1), one without a lock file (2); a dead port of domain 6;
    a live, a dead and a lockless segment; a port outside every domain's range, dead; other
    files."""
    held = []

    def shared_file(name, lock="dead"):
        """``name`` with its lock file (held here when "live"), or without one ("none")."""
        (tmp_path / name).write_bytes(b"x")
        if lock != "none":
            (tmp_path / f"{name}_el").write_bytes(b"")
        if lock == "live":
            handle = open(tmp_path / f"{name}_el", "ab")
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held.append(handle)

    for name, lock in ((shared_memory_port_file(5, 0), "live"),
                       (shared_memory_port_file(5, 1), "dead"),
                       (shared_memory_port_file(5, 2), "none"),
                       (shared_memory_port_file(6, 0), "dead"), ("fastrtps_port7000", "dead")):
        shared_file(name, lock)
        (tmp_path / f"sem.{name}_mutex").write_bytes(b"x")
    for name, lock in ((SEGMENT_LIVE, "live"), (SEGMENT_DEAD, "dead"),
                       (SEGMENT_NO_LOCK, "none")):
        shared_file(name, lock)
    (tmp_path / "lttng-ust-wait-6").write_bytes(b"x")
    yield tmp_path
    for handle in held:
        handle.close()


def test_a_port_file_is_dead_when_no_live_process_holds_its_lock_or_it_has_none(shm):
    assert dead_port_files(shm) == {shared_memory_port_file(5, 1),
                                    shared_memory_port_file(5, 2),
                                    shared_memory_port_file(6, 0), "fastrtps_port7000"}
    assert dead_port_files(shm / "missing") == set()
    assert dead_port_files(shm, domain=5) == {shared_memory_port_file(5, 1),
                                              shared_memory_port_file(5, 2)}


def test_a_lock_taken_for_a_moment_by_another_process_s_look_is_not_an_owner(shm,
                                                                          monkeypatch):
    """Fast DDS's writers take a port's lock for a moment to see whether its owner lives;
    a port found locked at the first try, then free, is still a dead one's. The live one
    stays live."""
    real_flock, looked = fcntl.flock, set()

    def flock_after_a_look(descriptor, operation):
        inode = os.fstat(descriptor).st_ino
        if inode not in looked:  # every lock file's first try: another process looks
            looked.add(inode)
            raise BlockingIOError(11, "Resource temporarily unavailable")
        return real_flock(descriptor, operation)

    monkeypatch.setattr(fastdds_shm.fcntl, "flock", flock_after_a_look)
    assert dead_port_files(shm, domain=5) == {shared_memory_port_file(5, 1),
                                              shared_memory_port_file(5, 2)}
    assert (shm / f"{shared_memory_port_file(5, 1)}_el").stat().st_ino in looked


def test_dead_ports_of_the_domain_and_dead_segments_are_removed_the_rest_stays(shm):
    before = {path.name for path in shm.iterdir()}
    assert remove_leftovers(5, shm) == (2, 1)
    gone = before - {path.name for path in shm.iterdir()}
    dead_1, lockless_2 = shared_memory_port_file(5, 1), shared_memory_port_file(5, 2)
    assert gone == {dead_1, f"{dead_1}_el", f"sem.{dead_1}_mutex",
                    lockless_2, f"sem.{lockless_2}_mutex",
                    SEGMENT_DEAD, f"{SEGMENT_DEAD}_el"}
    assert remove_leftovers(5, shm) == (0, 0)
    assert remove_leftovers(6, shm) == (1, 0)  # another run's, when that run cleans


def test_shm_leftovers_refuses_a_domain_outside_ros_s_range():
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.shm_leftovers",
                             "--domain", "300"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.splitlines() == [
        "shm_leftovers: error: argument --domain: must be in [0, 232], got 300",
        "Try 'shm_leftovers --help'."]
