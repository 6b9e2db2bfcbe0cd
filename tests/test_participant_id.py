"""A node process's participant id kept off a dead process's shared-memory port
(``nodes/participant_id.py``): the choice from socket tables and /dev/shm files, the profile
copy in place while the participant is made, and a real restart after a SIGKILL."""
from __future__ import annotations

import fcntl
import os
import re
import signal
import sys
import tempfile
from pathlib import Path

import pytest
from ros_process import NodeProcess, wait_until

from em_exploration_ros.nodes import participant_id
from em_exploration_ros.nodes.fastdds_shm import discovery_port, shared_memory_port_file
from em_exploration_ros.nodes.participant_id import (BARE_PROFILE, PROFILE_VARIABLE,
                                                     ParticipantChoice, bound_udp_ports,
                                                     own_participant_id,
                                                     participant_to_avoid,
                                                     profile_with_participant_id)

UDP4 = ("  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid\n"
        "  12: 00000000:6824 00000000:0000 07 00000000:00000000 00:00000000 00000000     0\n"
        "  40: 0100007F:1B58 00000000:0000 07 00000000:00000000 00:00000000 00000000     0\n")
UDP6 = ("  sl  local_address                         remote_address                        st\n"
        "   7: 00000000000000000000000000000000:7662 00000000000000000000000000000000:0000 07\n")
DOMAIN = 77


def test_the_bound_ports_are_read_from_both_socket_tables():
    assert bound_udp_ports([UDP4, UDP6]) == {0x6824, 0x1B58, 0x7662}
    assert bound_udp_ports([]) == set()


def _held(*participants: int) -> set[int]:
    return {discovery_port(DOMAIN, p) for p in participants}


def _left(*participants: int) -> set[str]:
    return {shared_memory_port_file(DOMAIN, p) for p in participants} | {"fastrtps_port7000"}


def test_a_dead_process_s_id_is_avoided_for_the_highest_clean_one():
    # Nothing left behind, or only by ids Fast DDS would not give: its choice stands.
    assert participant_to_avoid(DOMAIN, set(), set()) is None
    assert participant_to_avoid(DOMAIN, _held(0, 1), _left(0, 1, 5)) is None
    # Ids 0 and 1 live, 2 dead (its UDP port free, its shared-memory port file left, no
    # live process owning it).
    assert participant_to_avoid(DOMAIN, _held(0, 1), _left(0, 1, 2)) == ParticipantChoice(2, 31)
    # 31 held, 30 dead too: the next clean one down.
    assert participant_to_avoid(DOMAIN, _held(0, 1, 31), _left(0, 1, 2, 30, 31)) == \
        ParticipantChoice(2, 29)
    every = set(range(participant_id.HIGHEST_ANNOUNCED_ID + 1))
    assert participant_to_avoid(DOMAIN, _held(*every - {4}), _left(*every)) == \
        ParticipantChoice(4, None)
    assert participant_to_avoid(DOMAIN, _held(*every), _left(*every)) is None


def test_the_profile_gets_the_id_in_its_first_rtps_element_unless_it_has_one():
    team = (Path(__file__).resolve().parents[1] / "config" / "fastdds_profiles.xml").read_text()
    changed = profile_with_participant_id(team, 31)
    assert changed.count("<participantID>31</participantID>") == 1
    assert changed.replace("\n      <participantID>31</participantID>", "") == team
    assert profile_with_participant_id(changed, 30) is None  # the caller's own id stands
    assert profile_with_participant_id("<profiles/>", 30) is None
    bare = profile_with_participant_id(None, 29)
    assert "<participantID>29</participantID>" in bare and bare.startswith(BARE_PROFILE[:20])


def test_a_host_whose_tables_cannot_be_read_leaves_the_choice_to_fast_dds(monkeypatch):
    def unreadable(*_args, **_kwargs):
        raise PermissionError(13, "Permission denied", "/dev/shm")

    monkeypatch.setattr(participant_id, "dead_port_files", unreadable)
    assert participant_id.host_choice(DOMAIN) is None


@pytest.fixture()
def dead_id_2(monkeypatch):
    """This host as if id 2 were a dead process's (and 31 free)."""
    monkeypatch.setattr(participant_id, "host_choice",
                        lambda domain: ParticipantChoice(2, 31) if domain == DOMAIN else None)


def test_the_copy_is_in_place_until_released_then_the_variable_is_as_before(tmp_path,
                                                                            dead_id_2):
    profile = tmp_path / "team.xml"
    profile.write_text("<profiles><participant><rtps><name>x</name></rtps></participant>"
                       "</profiles>")
    environ = {"ROS_DOMAIN_ID": str(DOMAIN), PROFILE_VARIABLE: str(profile)}
    with own_participant_id(environ, tmp_path) as chosen:
        copy = Path(environ[PROFILE_VARIABLE])
        assert copy != profile
        assert "<participantID>31</participantID>" in copy.read_text()
        assert "<name>x</name>" in copy.read_text()
        assert chosen.line == (
            f"participant id 31 instead of 2: a process that died held id 2 and left its "
            f"shared-memory port (/dev/shm/{shared_memory_port_file(DOMAIN, 2)}), into which "
            f"the others may still write")
        chosen.release()
        assert environ[PROFILE_VARIABLE] == str(profile) and not copy.exists()
        chosen.release()  # once only
    assert environ == {"ROS_DOMAIN_ID": str(DOMAIN), PROFILE_VARIABLE: str(profile)}

    # A copy left by a process killed while it made its participant goes with the next.
    gone = tmp_path / participant_id.PROFILE_COPIES / "999999999.xml"
    gone.write_text("<profiles/>")
    bare: dict[str, str] = {"ROS_DOMAIN_ID": str(DOMAIN)}
    # No profile: one that sets the id alone.
    with own_participant_id(bare, tmp_path) as chosen:
        copy = Path(bare[PROFILE_VARIABLE])
        assert "<participantID>31</participantID>" in copy.read_text()
        assert copy == tmp_path / participant_id.PROFILE_COPIES / f"{os.getpid()}.xml"
        assert not gone.exists()
        copy.unlink()  # as a temporary-folder cleaner may: the release still ends the choice
    assert bare == {"ROS_DOMAIN_ID": str(DOMAIN)} and not copy.exists()


@pytest.mark.parametrize("environ", [
    {"ROS_DOMAIN_ID": "5"},  # no dead id there
    {"ROS_DOMAIN_ID": str(DOMAIN), "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
    {"ROS_DOMAIN_ID": "seven"},  # rclpy refuses it itself
    {"ROS_DOMAIN_ID": str(DOMAIN), PROFILE_VARIABLE: "/nonexistent/profile.xml"},
])
def test_nothing_changes_where_there_is_nothing_to_avoid_or_no_profile_to_change(environ,
                                                                                dead_id_2,
                                                                                tmp_path):
    before = dict(environ)
    with own_participant_id(environ, tmp_path) as chosen:
        assert environ == before and chosen.line is None
    assert environ == before


def test_a_copy_that_cannot_be_written_leaves_fast_dds_s_choice_and_says_so(tmp_path,
                                                                             dead_id_2):
    (tmp_path / participant_id.PROFILE_COPIES).write_text("a file where the folder goes")
    environ = {"ROS_DOMAIN_ID": str(DOMAIN)}
    with own_participant_id(environ, tmp_path) as chosen:
        assert environ == {"ROS_DOMAIN_ID": str(DOMAIN)}
        assert chosen.line.startswith(
            "Fast DDS gives this process participant id 2, whose shared-memory port a dead "
            "process left"), chosen.line
        assert "a profile with id 31 could not be written (" in chosen.line


def test_a_dead_port_seen_at_a_later_look_is_avoided_too(tmp_path, monkeypatch):
    """A writer resetting a dead port removes its file for a moment: the first looks may
    find no dead port, a later one does, and the process takes an id of its own."""
    looks = iter([None, None, ParticipantChoice(2, 31), None, ParticipantChoice(2, 31)])
    monkeypatch.setattr(participant_id, "host_choice", lambda domain: next(looks))
    monkeypatch.setattr(participant_id, "CHOICE_LOOK_PAUSE_S", 0.0)
    environ = {"ROS_DOMAIN_ID": str(DOMAIN)}
    with own_participant_id(environ, tmp_path) as chosen:
        assert chosen.line.startswith("participant id 31 instead of 2: ")
        assert "<participantID>31</participantID>" in Path(environ[PROFILE_VARIABLE]).read_text()
    assert next(looks, "all looked") == "all looked"
    monkeypatch.setattr(participant_id, "host_choice", lambda domain: None)
    with own_participant_id(environ, tmp_path) as chosen:  # every look finds nothing
        assert chosen.line is None and PROFILE_VARIABLE not in environ


def test_a_profile_with_its_own_id_is_left_as_it_is(tmp_path, dead_id_2):
    profile = tmp_path / "own.xml"
    profile.write_text("<profiles><participant><rtps><participantID>7</participantID></rtps>"
                       "</participant></profiles>")
    environ = {"ROS_DOMAIN_ID": str(DOMAIN), PROFILE_VARIABLE: str(profile)}
    with own_participant_id(environ, tmp_path) as chosen:
        assert environ[PROFILE_VARIABLE] == str(profile) and chosen.line is None


def test_the_choice_is_made_under_the_domain_s_lock_or_says_it_was_not(tmp_path, dead_id_2,
                                                                      monkeypatch):
    lock_path = tmp_path / participant_id.CHOICE_LOCK.format(domain=DOMAIN)
    environ = {"ROS_DOMAIN_ID": str(DOMAIN)}
    with own_participant_id(environ, tmp_path) as chosen:
        with open(lock_path, "ab") as other, pytest.raises(BlockingIOError):
            fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held until the release
        chosen.release()
        with open(lock_path, "ab") as other:
            fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
    monkeypatch.setattr(participant_id, "CHOICE_LOCK_WAIT_S", 0.2)
    with open(lock_path, "ab") as other:
        fcntl.flock(other, fcntl.LOCK_EX)  # a process stopped while holding it
        with own_participant_id(environ, tmp_path) as chosen:
            assert chosen.line.endswith(
                f"(chosen without {lock_path.name}: another process held it for over 0.2 s)")
            assert "<participantID>31</participantID>" in Path(
                environ[PROFILE_VARIABLE]).read_text()


#: A node process as every node of the package runs (``run_node``), with a publisher.
NODE = """
import sys, rclpy.node
from std_msgs.msg import String
from em_exploration_ros.nodes.node_main import run_node
def make():
    node = rclpy.node.Node("participant_probe")
    node.create_publisher(String, "participant_probe", 10)
    node.get_logger().info("node made")
    return node
sys.exit(run_node(make, "participant_probe"))
"""
LINE = re.compile(r"participant id (\d+) instead of (\d+): a process that died held id \2 ")


def _shared_memory_ports() -> set[str]:
    return {path.name for path in Path("/dev/shm").glob("fastrtps_port*")
            if not path.name.endswith(("_el", "_sl"))}


def test_nodes_restarted_after_a_kill_take_ids_of_their_own_two_at_once(tmp_path):
    """As robots restarted by hand with ``ros2 run`` after their processes were killed:
    Fast DDS would give them a dead one's id and shared-memory port. Two restarted at once
    take two ids (without the choice's lock both chose 31 in a run of three)."""
    domain = int(os.environ.get("ROS_DOMAIN_ID") or 0)
    before = _shared_memory_ports()
    first = NodeProcess([sys.executable, "-c", NODE], tmp_path / "first.log")
    with first:
        first.wait_for_output("node made", 60)
        wait_until(lambda: _shared_memory_ports() - before, 30, "the first node's port file")
        ports = _shared_memory_ports() - before
        ids = {k for k in range(participant_id.HIGHEST_ANNOUNCED_ID + 1)
               if shared_memory_port_file(domain, k) in ports}
        assert len(ids) == 1, ports
        first.signal_group(signal.SIGKILL)
        first.wait(30)
    assert ports <= _shared_memory_ports()  # the killed process left its port
    restarts = [NodeProcess([sys.executable, "-c", NODE], tmp_path / f"restart_{k}.log")
                for k in range(2)]
    try:
        chosen = []
        for restart in restarts:
            restart.wait_for_output("node made", 60)
            found = LINE.search(restart.output())
            assert found, restart.output()
            chosen.append(int(found[1]))
        assert len(set(chosen)) == 2 and not set(chosen) & ids
        assert max(chosen) <= participant_id.HIGHEST_ANNOUNCED_ID
        for restart, number in zip(restarts, chosen):
            bound = bound_udp_ports([Path(f"/proc/{restart.pid}/net/udp").read_text()])
            assert discovery_port(domain, number) in bound
    finally:
        for restart in restarts:
            restart.stop()
    copies = Path(tempfile.gettempdir()) / participant_id.PROFILE_COPIES
    assert not [restart.pid for restart in restarts if (copies / f"{restart.pid}.xml").exists()]


def test_em_record_restarted_after_a_kill_takes_an_id_of_its_own(tmp_path):
    """em-record makes its participant as the nodes do: a recorder started again by hand
    after its process was killed does not take the dead one's id, whose port the others may
    still write into (its recording would miss what they write)."""
    def recorder(name: str) -> NodeProcess:
        return NodeProcess([sys.executable, "-m", "em_exploration_ros.tools.record",
                            "-o", str(tmp_path / name), "--topics", "/em_test/nothing"],
                           tmp_path / f"{name}.log")

    before = _shared_memory_ports()
    with recorder("killed") as killed:
        wait_until(lambda: _shared_memory_ports() - before, 60, "the recorder's port file")
        killed.signal_group(signal.SIGKILL)
        killed.wait(30)
    with recorder("again") as again:
        again.wait_for_output("participant id ", 60)
        assert LINE.search(again.output()), again.output()
        again.signal_group(signal.SIGINT)
        assert again.wait(30) == 0, again.output()
