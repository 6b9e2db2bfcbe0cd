"""The stream journal (core.agent.stream_journal): what a restarted robot reads back of its
own stream when no teammate holds it, and what it refuses to read."""
from __future__ import annotations

import os
import struct
from dataclasses import replace

import pytest

from em_exploration_ros.core.agent.stream_journal import (MAX_RECORD_BYTES, JournalIdentity,
                                                          StreamJournal, mission_fingerprint,
                                                          read_journal)
from em_exploration_ros.core.params import ExplorationParams

IDENTITY = JournalIdentity(1, 3, mission_fingerprint(ExplorationParams()))
RECORDS = [b"record one", b"2", bytes(range(256)) * 3]


def written(tmp_path, records=RECORDS):
    journal = StreamJournal(tmp_path / "state" / "robot_1.journal", IDENTITY)
    journal.start(records[:1])
    for record in records[1:]:
        journal.append(record)
    journal.close()
    return journal.path


def test_records_come_back_in_order_after_a_start_and_appends(tmp_path):
    contents = read_journal(written(tmp_path), IDENTITY)
    assert contents.records == RECORDS and contents.problem is None


def test_a_new_start_replaces_the_journal_whole(tmp_path):
    path = written(tmp_path)
    journal = StreamJournal(path, IDENTITY)
    journal.start([b"restored 1", b"restored 2"])
    journal.append(b"new 3")
    journal.close()
    assert read_journal(path, IDENTITY).records == [b"restored 1", b"restored 2", b"new 3"]
    assert not path.with_name(path.name + ".new").exists()


def test_a_record_torn_by_a_killed_process_ends_the_reading_after_the_whole_ones(tmp_path):
    path = written(tmp_path)
    whole = path.read_bytes()
    for cut in (1, 5, len(RECORDS[-1])):  # inside the frame header, inside the payload
        path.write_bytes(whole[:-cut])
        contents = read_journal(path, IDENTITY)
        assert contents.records == RECORDS[:-1]
        assert "record 3" in contents.problem and "cut short" in contents.problem


def test_a_flipped_byte_fails_the_checksum_and_keeps_the_records_before_it(tmp_path):
    path = written(tmp_path)
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x40
    path.write_bytes(bytes(data))
    contents = read_journal(path, IDENTITY)
    assert contents.records == RECORDS[:-1] and "fails its checksum" in contents.problem


def test_an_oversized_length_is_refused_without_reading_it(tmp_path):
    path = written(tmp_path, RECORDS[:1])
    with open(path, "ab") as file:
        file.write(struct.pack("<II", MAX_RECORD_BYTES + 1, 0))
    contents = read_journal(path, IDENTITY)
    assert contents.records == RECORDS[:1] and "more than" in contents.problem


@pytest.mark.parametrize("other", [JournalIdentity(2, 3, IDENTITY.mission),
                                   JournalIdentity(1, 4, IDENTITY.mission),
                                   JournalIdentity(1, 3, "0123456789abcdef")])
def test_the_journal_of_another_robot_team_or_mission_is_not_taken(tmp_path, other):
    contents = read_journal(written(tmp_path), other)
    assert contents.records == [] and "another robot or mission" in contents.problem


def test_missing_foreign_and_special_files_give_their_reason_and_no_records(tmp_path):
    assert "no journal at" in read_journal(tmp_path / "absent", IDENTITY).problem
    (tmp_path / "text").write_text("robot 1's notes")
    assert "not a stream journal" in read_journal(tmp_path / "text", IDENTITY).problem
    (tmp_path / "short").write_bytes(b"EMJ1" + struct.pack("<I", 4000) + b"{}")
    assert "cut short or too long" in read_journal(tmp_path / "short", IDENTITY).problem
    os.mkfifo(tmp_path / "fifo")  # opening a FIFO would wait for a writer for ever
    assert "not a regular file" in read_journal(tmp_path / "fifo", IDENTITY).problem
    descriptors = len(os.listdir("/proc/self/fd"))
    for _ in range(20):  # a folder: named as such, and no descriptor left open
        assert "not a regular file" in read_journal(tmp_path, IDENTITY).problem
    assert len(os.listdir("/proc/self/fd")) == descriptors


def test_a_zero_filled_tail_is_not_read_as_records(tmp_path):
    """After a power loss a file can end in zeros, whose CRC-32 (of no bytes) is 0."""
    path = written(tmp_path)
    with open(path, "ab") as file:
        file.write(bytes(4096))
    contents = read_journal(path, IDENTITY)
    assert contents.records == RECORDS and "is empty" in contents.problem
    with pytest.raises(ValueError):
        StreamJournal(tmp_path / "other.journal", IDENTITY).start([b""])


def test_the_fingerprint_follows_the_mission_parameters():
    params = ExplorationParams()
    assert mission_fingerprint(params) == mission_fingerprint(ExplorationParams())
    other_seed = replace(params, run=replace(params.run, seed=params.run.seed + 1))
    assert mission_fingerprint(other_seed) != mission_fingerprint(params)


def test_a_start_that_fails_leaves_no_staging_file_and_discard_removes_the_journal(tmp_path):
    path = written(tmp_path)
    journal = StreamJournal(path, IDENTITY)
    with pytest.raises(ValueError):
        journal.start([b"ok", bytes(MAX_RECORD_BYTES + 1)])
    assert not path.with_name(path.name + ".new").exists()
    assert read_journal(path, IDENTITY).records == RECORDS  # the old one is left as it was
    journal.discard()
    assert not path.exists()
    journal.discard()  # nothing there: no error


def test_a_journal_that_cannot_be_written_raises_for_the_node_to_go_on_without(tmp_path):
    blocker = tmp_path / "state"
    blocker.write_text("a file where the folder should be")
    with pytest.raises(OSError):
        StreamJournal(blocker / "robot_1.journal", IDENTITY).start()
    with pytest.raises(ValueError):
        StreamJournal(tmp_path / "robot_1.journal", IDENTITY).append(b"before start")
    # What a crash leaves between the staging file and the rename is never read as the
    # journal: the journal is the old file until the rename.
    path = written(tmp_path / "ok")
    path.with_name(path.name + ".new").write_bytes(b"half a new journal")
    assert read_journal(path, IDENTITY).records == RECORDS
