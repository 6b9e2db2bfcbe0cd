"""The world's lockstep barrier: answers, re-sends, timeouts, liveliness stops, rejoins."""
from __future__ import annotations

from em_exploration_ros.core.sessions.lockstep import STAND_STILL, LockstepBarrier, StepAnswer

GO = StepAnswer(1.0, 0.1, 4, False)


def test_answers_timeouts_and_close():
    barrier = LockstepBarrier(3, robot_timeout_s=2.0)
    barrier.open(0, now_s=100.0)
    assert barrier.answer(0, 0, GO, 100.1) == LockstepBarrier.ACCEPTED
    assert barrier.answer(0, 0, GO, 100.2) == LockstepBarrier.DUPLICATE
    forged = StepAnswer(0.0, 0.0, 4, True)  # another publisher on robot 0's topic
    assert barrier.answer(0, 0, forged, 100.2) == LockstepBarrier.CONFLICT
    assert barrier.answer(1, 1, GO, 100.2) == LockstepBarrier.FUTURE
    assert not barrier.complete and barrier.waiting_for() == [1, 2]
    assert barrier.expire(101.9) == []
    assert barrier.answer(1, 0, StepAnswer(0.5, 0.0, 3, True), 101.9) == LockstepBarrier.ACCEPTED
    assert barrier.expire(102.0) == [2]
    assert barrier.complete
    assert barrier.close() == [GO, StepAnswer(0.5, 0.0, 3, True), STAND_STILL]
    assert barrier.team_sequences == [4, 3, 0] and barrier.finished == [False, True, False]
    assert not barrier.all_done
    barrier.open(1, now_s=200.0)
    assert barrier.answer(0, 0, GO, 200.0) == LockstepBarrier.STALE
    assert barrier.answer(0, 1, StepAnswer(0.0, 0.0, 6, True), 200.0) == LockstepBarrier.ACCEPTED
    assert not barrier.complete  # a finished robot still answers every step
    assert barrier.answer(1, 1, StepAnswer(0.0, 0.0, 3, True), 200.0) == LockstepBarrier.ACCEPTED
    assert barrier.complete  # robot 2 is stopped: not waited for
    barrier.close()
    assert barrier.team_sequences == [6, 3, 0] and barrier.all_done


def test_missing_answers_are_due_a_resend_before_the_timeout():
    barrier = LockstepBarrier(2, robot_timeout_s=10.0, resend_period_s=1.0)
    barrier.open(0, now_s=0.0)
    assert barrier.due_for_resend(0.5) == []
    barrier.answer(0, 0, GO, 0.6)
    assert barrier.due_for_resend(1.0) == [1]  # robot 1 missed the start
    assert barrier.due_for_resend(1.5) == []   # not again before one more period
    assert barrier.due_for_resend(2.0) == [1]
    assert barrier.expire(9.9) == []
    assert barrier.answer(1, 0, GO, 9.9) == LockstepBarrier.ACCEPTED
    assert barrier.due_for_resend(20.0) == [] and barrier.complete
    barrier.close()
    barrier.open(1, now_s=30.0)  # a new step re-arms every robot's re-send and deadline
    assert barrier.due_for_resend(30.5) == [] and barrier.due_for_resend(31.0) == [0, 1]
    assert barrier.expire(39.9) == [] and barrier.expire(40.0) == [0, 1]


def test_stopped_robot_rejoins_when_it_answers_again():
    barrier = LockstepBarrier(2, robot_timeout_s=5.0, resend_period_s=1.0)
    barrier.open(3, now_s=0.0)
    assert barrier.stop([1]) == [1] and barrier.stop([1]) == []   # liveliness lost
    barrier.answer(0, 3, GO, 0.1)
    assert barrier.complete
    assert barrier.close()[1] == STAND_STILL
    barrier.open(4, now_s=1.0)
    barrier.answer(0, 4, GO, 1.5)
    assert barrier.due_for_resend(2.0) == [1]      # a stopped robot is still sent its steps
    assert barrier.complete                          # ... but not waited for
    # It answers an earlier step (a restarted process catching up): waited for from now on,
    # with a fresh deadline.
    assert barrier.answer(1, 2, GO, 4.0) == LockstepBarrier.REJOINED
    assert barrier.waiting_for() == [1]
    assert barrier.expire(8.9) == []
    assert barrier.answer(1, 4, StepAnswer(0.2, 0.0, 9, False), 5.0) == LockstepBarrier.ACCEPTED
    assert barrier.close()[1] == StepAnswer(0.2, 0.0, 9, False)
    assert barrier.team_sequences[1] == 9
    # A stopped robot answering the open step is used at once.
    barrier.open(5, now_s=10.0)
    barrier.stop([0])
    assert barrier.answer(0, 5, GO, 10.5) == LockstepBarrier.REJOINED
    assert barrier.answer(1, 5, GO, 10.5) == LockstepBarrier.ACCEPTED
    assert barrier.complete and barrier.close() == [GO, GO]


def test_suspect_robot_gets_the_short_timeout_until_trusted():
    barrier = LockstepBarrier(2, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(0, now_s=0.0)
    barrier.suspect(1, now_s=2.0)              # liveliness lost while the world waits
    barrier.answer(0, 0, GO, 2.5)
    assert barrier.expire(5.9) == []
    assert barrier.answer(1, 0, GO, 5.9) == LockstepBarrier.ACCEPTED  # it was alive: no harm
    barrier.close()
    barrier.open(1, now_s=10.0)                # still suspect: 4 s again
    assert barrier.expire(13.9) == [] and barrier.expire(14.0) == [1]
    barrier.trust(1, now_s=14.5)
    barrier.answer(1, 1, GO, 15.0)             # rejoins
    barrier.answer(0, 1, GO, 15.0)
    barrier.close()
    barrier.open(2, now_s=20.0)                # trusted again: the long timeout
    assert barrier.expire(49.9) == [] and barrier.expire(50.0) == [0, 1]


def test_a_suspect_silent_since_its_loss_report_gets_no_new_short_timeout_at_the_next_step():
    """Two robots wedged at once, robot 1 just after answering the open step: the step waits
    for robot 2 until 4 s after its loss report, and the next step gave robot 1 another 4 s
    from its opening, so the team stood still 8 s instead of 4."""
    barrier = LockstepBarrier(3, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(0, now_s=0.0)
    barrier.answer(0, 0, GO, 0.1)
    barrier.answer(1, 0, GO, 0.1)              # then robots 1 and 2 wedge
    barrier.suspect(2, now_s=2.0)
    barrier.suspect(1, now_s=2.1)
    assert barrier.expire(5.9) == [] and barrier.expire(6.0) == [2]
    barrier.close()
    barrier.open(1, now_s=6.0)
    barrier.answer(0, 1, GO, 6.05)
    assert barrier.expire(6.09) == [] and barrier.expire(6.1) == [1]


def test_a_team_lost_at_once_is_told_from_a_team_that_finished():
    """The world waits for a team whose every unfinished robot is lost (run_team.sh
    --respawn restarts them) instead of ending the mission; a finished team ends it."""
    barrier = LockstepBarrier(2, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    done = StepAnswer(0.0, 0.0, 4, True)
    barrier.open(0, now_s=0.0)
    barrier.answer(0, 0, done, 0.1)                            # robot 0 finished
    barrier.answer(1, 0, GO, 0.1)
    barrier.close()
    barrier.open(1, now_s=1.0)
    barrier.answer(0, 1, done, 1.1)
    assert not barrier.team_lost and not barrier.all_done
    assert barrier.expire(31.0) == [1]                         # robot 1 wedged: lost
    assert barrier.all_done and barrier.team_lost
    barrier.restarted(1, now_s=32.0)                           # its new process is up
    assert not barrier.all_done and not barrier.team_lost
    finished = LockstepBarrier(1, robot_timeout_s=30.0)
    finished.open(0, now_s=0.0)
    finished.answer(0, 0, StepAnswer(0.0, 0.0, 4, True), 0.1)
    finished.close()
    assert finished.all_done and not finished.team_lost


def test_a_robot_whose_liveliness_comes_back_gets_the_long_timeout_on_the_open_step_too():
    """Under packet loss a live robot's liveliness assertions get lost and come back: it
    kept the 4 s of the loss report on the open step, was stopped when that step took
    longer, and run_team.sh --respawn killed a healthy process."""
    barrier = LockstepBarrier(2, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(0, now_s=0.0)
    barrier.answer(0, 0, GO, 0.5)
    barrier.suspect(1, now_s=2.0)
    barrier.trust(1, now_s=2.5)
    assert barrier.expire(6.0) == [] and barrier.expire(32.4) == []
    assert barrier.expire(32.5) == [1]


def test_a_restarted_robot_gets_the_short_timeout_on_the_open_step_only():
    """A new process that reports its liveliness before the old one's loss was reported
    (a restart within the lease) must not make the world wait ``robot_timeout_s`` for the
    open step while the new process recovers (a test run's world waited 30 s and never
    went on without the restarted robot)."""
    barrier = LockstepBarrier(2, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(0, now_s=0.0)
    barrier.answer(0, 0, GO, 0.5)
    barrier.restarted(1, now_s=2.0)
    assert barrier.expire(5.9) == [] and barrier.expire(6.0) == [1]
    barrier.close()
    barrier.open(1, now_s=10.0)
    assert barrier.answer(1, 1, GO, 10.5) == LockstepBarrier.REJOINED
    barrier.answer(0, 1, GO, 10.5)
    barrier.close()
    barrier.open(2, now_s=20.0)                # the steps after: the long timeout
    assert barrier.expire(49.9) == [] and barrier.expire(50.0) == [0, 1]


def test_a_team_whose_every_robot_is_restarting_waits_for_them_instead_of_ending():
    """--respawn, every robot killed within seconds: each new process recovers while the
    others are stopped. The world stepped over at once ("every robot finished or
    stopped", exit 3 at explored 0.61); it must wait for a rejoining robot, for at most
    ``robot_timeout_s``, and only then end the run."""
    barrier = LockstepBarrier(2, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(0, now_s=0.0)
    barrier.restarted(0, now_s=1.0)
    barrier.restarted(1, now_s=2.0)
    assert barrier.expire(6.0) == [0, 1]
    assert not barrier.complete and not barrier.all_done  # waiting for the rejoiners
    # Robot 1 comes back and answers the open step.
    assert barrier.answer(1, 0, GO, 9.0) == LockstepBarrier.REJOINED
    assert barrier.complete and not barrier.all_done
    barrier.close()
    barrier.open(1, now_s=9.5)
    barrier.expire(31.5)                      # robot 0's rejoin deadline (1 + 30) passed
    assert barrier.rejoining == {}
    assert not barrier.complete               # robot 1 is live and has not answered
    assert barrier.answer(1, 1, GO, 31.6) == LockstepBarrier.ACCEPTED
    assert barrier.complete and not barrier.all_done
    barrier.close()
    barrier.open(2, now_s=32.0)
    assert barrier.expire(62.0) == [1]         # robot 1 silent again, nobody rejoining
    assert barrier.complete and barrier.all_done


def test_a_rejoining_robot_that_never_answers_is_given_up_after_the_robot_timeout():
    barrier = LockstepBarrier(1, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(0, now_s=0.0)
    barrier.restarted(0, now_s=1.0)
    assert barrier.expire(5.0) == [0]
    assert not barrier.complete and not barrier.all_done
    barrier.expire(30.9)
    assert not barrier.complete
    barrier.expire(31.0)
    assert barrier.complete and barrier.all_done


def test_a_robot_that_rejoins_from_an_old_step_has_the_long_timeout_to_catch_up():
    """A wedged robot's liveliness was lost (suspect), its restarted process answered an old
    step: with the suspect's 4 s to reach the open step it was stopped again while it caught
    up, the world ran on more than 1000 steps ahead, and the robot never rejoined (a CI
    run of the respawn system test)."""
    barrier = LockstepBarrier(2, robot_timeout_s=30.0, suspect_timeout_s=4.0)
    barrier.open(100, now_s=0.0)
    barrier.suspect(1, now_s=0.5)
    barrier.answer(0, 100, GO, 1.0)
    assert barrier.expire(4.5) == [1]
    barrier.close()
    barrier.open(101, now_s=5.0)
    barrier.answer(0, 101, GO, 5.5)
    assert barrier.answer(1, 90, GO, 6.0) == LockstepBarrier.REJOINED
    assert barrier.expire(10.0) == [] and barrier.expire(35.9) == []
    assert barrier.expire(36.0) == [1]
    # A loss reported after it rejoined shortens the wait again.
    barrier.close()
    barrier.open(102, now_s=37.0)
    barrier.answer(0, 102, GO, 37.2)
    assert barrier.answer(1, 101, GO, 37.5) == LockstepBarrier.REJOINED
    barrier.suspect(1, now_s=38.0)
    assert barrier.expire(41.9) == [] and barrier.expire(42.0) == [1]
