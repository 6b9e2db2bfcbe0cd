"""Team liveness bookkeeping: statuses, their changes and downtimes."""
from __future__ import annotations

from em_exploration_ros.core.agent.liveness import (ACTIVE, FINISHED, LOST, REJOINED,
                                                    LivelinessWriters, StatusChange,
                                                    TeamLiveness, UnseenLiveliness)


def test_a_liveliness_loss_counts_after_the_grace_and_downtime_is_summed():
    team = TeamLiveness(3, grace_s=4.0)
    assert [team.status(r) for r in range(3)] == [ACTIVE] * 3
    assert team.heard(0, 1.0, 1.0, "answers") is False        # never lost: no change
    team.liveliness_lost(0, 2.0, 2.0)                          # a lossy network ...
    team.liveliness_back(0, False, 3.0, 3.0)                   # ... and it is back
    assert team.confirm(100.0) == [] and team.status(0) == ACTIVE

    team.liveliness_lost(1, 10.0, 5.0)
    team.liveliness_lost(1, 11.0, 6.0)                         # repeated report: no news
    assert team.confirm(8.9) == [] and team.status(1) == ACTIVE
    assert team.confirm(9.0) == [1] and team.status(1) == LOST
    team.liveliness_back(1, True, 12.0, 10.0)                  # a restarted process ...
    assert team.status(1) == LOST                              # ... is lost until it answers
    assert team.heard(1, 30.0, 15.0, "answers again")
    assert team.status(1) == REJOINED
    team.liveliness_lost(1, 50.0, 20.0)
    assert team.confirm(30.0) == [1]
    assert team.downtime_s(1, until_sim_time_s=70.0, until_wall_s=40.0) == (
        (30.0 - 10.0) + (70.0 - 50.0), (15.0 - 5.0) + (40.0 - 20.0))
    assert team.changes(1) == [StatusChange(LOST, 10.0, 5.0, "liveliness lost for 4.0 s"),
                               StatusChange(REJOINED, 30.0, 15.0, "answers again"),
                               StatusChange(LOST, 50.0, 20.0, "liveliness lost for 10.0 s")]
    assert team.finished(2, 40.0, 18.0) and team.status(2) == FINISHED
    assert not team.finished(2, 41.0, 19.0)
    assert not team.finished(1, 60.0, 22.0)  # a lost robot's flag is stale news
    assert team.downtime_s(0, 70.0, 40.0) == (0.0, 0.0) and team.changes(0) == []


def test_a_restart_within_the_grace_counts_as_lost_from_the_loss():
    team = TeamLiveness(2, grace_s=4.0)
    team.liveliness_lost(1, 20.0, 8.0)
    assert not team.heard(1, 20.0, 9.0, "answers")   # the new process answered first ...
    assert team.liveliness_back(1, True, 22.0, 10.0)  # ... its liveliness came 2 s later
    assert team.status(1) == LOST
    assert team.changes(1) == [StatusChange(LOST, 20.0, 8.0, "process restarted")]
    assert team.heard(1, 26.0, 12.0, "answers again")
    assert team.downtime_s(1, 99.0, 99.0) == (6.0, 4.0)


def test_a_restart_within_the_old_process_lease_counts_as_lost_from_its_report():
    team = TeamLiveness(2, grace_s=4.0)
    # The old process died, a new one came up and was reported before the old one's
    # lease ran out, so no loss was ever reported.
    assert team.liveliness_back(1, True, 30.0, 12.0)
    assert team.status(1) == LOST
    assert team.changes(1) == [StatusChange(LOST, 30.0, 12.0,
                                            "process restarted within its liveliness lease")]
    assert not team.liveliness_back(1, False, 31.0, 12.5)  # the old lease ran out: no news
    assert team.status(1) == LOST
    assert team.heard(1, 32.0, 13.0, "answers again") and team.status(1) == REJOINED
    assert not team.liveliness_back(0, False, 30.0, 12.0) and team.status(0) == ACTIVE


def test_a_new_process_heard_before_its_liveliness_is_reported_is_not_lost_again():
    """On separate hosts (--netns) the restarted process's first answer can come a second
    before discovery reports its liveliness: that report made the rejoined robot lost again
    (a spurious lost/rejoined pair in the summary's status changes)."""
    team = TeamLiveness(2, grace_s=4.0)
    team.liveliness_lost(1, 20.0, 8.0)
    assert team.confirm(12.0) == [1]
    assert team.heard(1, 22.0, 14.0, "answers again")             # the new process ...
    assert not team.liveliness_back(1, True, 22.0, 15.0)          # ... then its liveliness
    assert team.status(1) == REJOINED
    assert [c.status for c in team.changes(1)] == [LOST, REJOINED]
    # A later restart within the lease of that process is a restart again.
    assert team.liveliness_back(1, True, 40.0, 30.0) and team.status(1) == LOST


def test_quick_restarts_each_heard_before_their_liveliness_count_as_one_loss():
    """A robot killed again and again before it answers, the last new process answering
    before its liveliness is reported: one loss and one rejoin, not a phantom restart of
    the process that had just rejoined (a chaos pass's four kills of robot 1)."""
    team = TeamLiveness(2, grace_s=4.0)
    team.liveliness_lost(1, 20.0, 8.0)
    assert team.liveliness_back(1, True, 20.0, 9.0)           # restarted within the grace
    team.liveliness_lost(1, 20.0, 12.0)                      # killed again, silent so far
    assert not team.liveliness_back(1, True, 20.0, 13.0)
    team.liveliness_lost(1, 20.0, 16.0)                      # and again
    assert team.heard(1, 21.0, 17.0, "answers again")         # the newest answers first
    assert not team.liveliness_back(1, True, 21.0, 17.5)      # then its liveliness shows
    assert [c.status for c in team.changes(1)] == [LOST, REJOINED]
    assert team.status(1) == REJOINED


def test_a_lost_process_that_comes_back_itself_leaves_the_next_restart_counted():
    team = TeamLiveness(2, grace_s=4.0)
    team.liveliness_lost(1, 20.0, 8.0)
    assert team.confirm(12.0) == [1]
    assert not team.liveliness_back(1, False, 21.0, 13.0)  # SIGCONT: the same process
    assert team.heard(1, 21.0, 13.0, "answers again")
    assert team.liveliness_back(1, True, 40.0, 30.0) and team.status(1) == LOST


def test_robots_never_seen_alive_are_due_once_a_lease_after_the_first_step():
    unseen = UnseenLiveliness(3, lease_s=3.0)
    assert unseen.due(100.0) == []                  # no first step yet
    unseen.seen(1)
    unseen.first_step(10.0)
    unseen.first_step(12.0)                          # the first one counts
    assert unseen.due(12.9) == []
    unseen.seen(0)
    assert unseen.due(13.0) == [2]
    assert unseen.due(20.0) == []                    # looked once
    assert unseen.was_seen(0) and unseen.was_seen(1) and not unseen.was_seen(2)
    unseen.seen(2)                                   # a late report still counts as seen
    assert unseen.was_seen(2)


def test_a_new_liveliness_writer_of_a_robot_seen_before_is_a_restart():
    writers = LivelinessWriters([1, 2])
    assert writers.gained(1, [b"a"]) == (False, None)          # the first process
    assert writers.gained(1, [b"a"]) == (False, None)          # its liveliness back
    assert writers.gained(2, [b"x"]) == (False, None)          # robots apart
    assert writers.gained(1, [b"b"]) == (True, None)           # a new process
    assert writers.gained(1, [b"a", b"b"]) == (False, None)    # both known


def test_a_flood_of_liveliness_identities_is_bounded_and_told_once():
    writers = LivelinessWriters([0, 1], limit=4)
    writers.gained(0, [b"robot"])
    restarted, note = writers.gained(0, [b"robot", b"f1", b"f2", b"f3"])
    assert restarted and note is None                          # at the bound
    restarted, note = writers.gained(0, [b"robot", b"f4"])
    assert restarted and "more than 4 writers seen" in note    # f1 is forgotten
    for fake in range(5, 1000):
        restarted, note = writers.gained(0, [b"robot", f"f{fake}".encode()])
        assert restarted and note is None                      # told once per robot
    assert len(writers._seen[0]) == 4
    assert writers.gained(0, [b"robot"]) == (False, None)      # present all along: kept
    assert writers.gained(0, [b"f1"])[0]                       # forgotten: a restart
    # More writers present at once than the bound: the known ones are kept.
    assert writers.gained(1, [b"robot"]) == (False, None)
    restarted, note = writers.gained(1, [b"robot"] + [b"g%d" % i for i in range(10)])
    assert restarted and "robot 1's liveliness" in note
    assert writers.gained(1, [b"robot"]) == (False, None)


def test_a_flood_of_restarts_lists_the_first_and_latest_changes_and_counts_every_downtime():
    """Each new liveliness identity is a restart: a lost and a rejoined change. The list
    keeps the first and latest half of ``max_changes``, says how many it left out, and the
    downtime still sums every lost interval."""
    team = TeamLiveness(1, grace_s=4.0, max_changes=6)
    for restart in range(10):  # lost at 10 k, rejoined at 10 k + 2 (simulated and wall)
        assert team.liveliness_back(0, True, 10.0 * restart, 10.0 * restart)
        assert team.heard(0, 10.0 * restart + 2.0, 10.0 * restart + 2.0, "answers")
    changes = team.changes(0)
    assert len(changes) == 6 and team.omitted_changes(0) == 20 - 6
    assert [c.sim_time_s for c in changes] == [0.0, 2.0, 10.0, 82.0, 90.0, 92.0]
    assert [c.status for c in changes] == [LOST, REJOINED, LOST, REJOINED, LOST, REJOINED]
    assert team.status(0) == REJOINED
    assert team.downtime_s(0, 500.0, 500.0) == (20.0, 20.0)
    team.liveliness_back(0, True, 100.0, 100.0)
    assert team.status(0) == LOST and team.omitted_changes(0) == 15
    assert team.downtime_s(0, 105.0, 103.0) == (25.0, 23.0)
