"""Plausibility checks of received input, the re-send scheduler and the world watch."""
import math

import numpy as np
import pytest

from em_exploration_ros.core.agent.input_checks import (MAX_STEP_LEAD, ClockGuard, RejectionLog,
                                                        array_problem, barrier_problem,
                                                        command_problem, command_sequence_problem,
                                                        first_problem, frame_problem,
                                                        history_request_problem, id_problem,
                                                        landmark_reading_problem, number_problem,
                                                        reason_kind, request_problem, size_problem,
                                                        stamp_problem, stamp_step_problem,
                                                        step_problem)
from em_exploration_ros.core.agent.world_watch import WorldEvent, WorldWatch
from em_exploration_ros.core.links.resend import ResendRange, ResendScheduler

OBSERVER = 2**32 - 1


def test_clock_guard_drops_negative_malformed_backwards_and_leaping_clocks():
    guard = ClockGuard(max_rate=100.0)
    assert guard.check(5, 0, wall_s=0.0) is None
    assert "negative" in guard.check(-1, 0, wall_s=0.1)
    assert "nanosec" in guard.check(6, 2**32 - 1, wall_s=0.1)
    assert "backwards" in guard.check(4, 999_999_999, wall_s=0.1)
    assert guard.check(5, 0, wall_s=0.1) is None  # the same time again is fine
    assert guard.check(5, 200_000_000, wall_s=0.2) is None
    assert "backwards" in guard.check(5, 100_000_000, wall_s=0.3)
    assert "leapt" in guard.check(2**31 - 1, 0, wall_s=0.3)
    assert guard.check(105, 0, wall_s=1.2) is None  # 100 s in one wall second


@pytest.mark.parametrize("requester, first, last, problem", [
    (1, 1, 0, None),
    (0, 1, 0, "not a teammate"),  # this robot's own id
    (3, 1, 0, "not a teammate"),
    (-1, 1, 0, "not a teammate"),
    (1, 1, 5, "not the whole stream (1..0)"),
    (1, 0, 0, "not the whole stream (1..0)"),
])
def test_a_request_for_ones_own_stream_is_checked(requester, first, last, problem):
    """A restarted robot asks its teammates for all of its own stream (1..0); anything
    else claiming to be that request is dropped before a record is re-sent."""
    found = history_request_problem(requester, first, last, own_id=0, num_robots=3)
    assert found is None if problem is None else problem in found


def _feed(guard, samples):
    """``(sec, wall_s)`` samples; the verdict of each: 'ok' or the reason's first words."""
    verdicts = []
    for sec, wall_s in samples:
        problem = guard.check(int(sec), int(round(sec % 1 * 1e9)), wall_s=wall_s)
        verdicts.append("ok" if problem is None else " ".join(problem.split()[:3]))
    return verdicts


def test_a_forged_first_clock_is_overruled_once_the_true_one_has_run_alone():
    """One hostile /clock at 9e8 s before the world's first: every true sample is
    backwards until the true clock has advanced alone for ``recover_after_s``."""
    guard = ClockGuard(recover_after_s=2.0)
    assert guard.check(900_000_000, 0, wall_s=0.0) is None
    true = [(73.0 + 0.2 * k, 0.5 + 0.01 * k) for k in range(300)]  # 100 Hz wall, 20x
    verdicts = _feed(guard, true)
    taken_up = verdicts.index("ok")
    assert set(verdicts[:taken_up]) == {"clock went backwards"}
    assert true[taken_up][1] - 0.5 >= 2.0 > true[taken_up - 1][1] - 0.5
    assert set(verdicts[taken_up:]) == {"ok"}
    assert guard.latest_ns == int(round(true[-1][0] * 1e9))
    notice = guard.take_notice()
    assert notice.startswith(f"clock taken up again at {true[taken_up][0]:.3f} s: it went "
                             "back from 900000000.000 s")
    assert guard.take_notice() is None


def test_a_running_clock_is_never_overruled_by_an_earlier_one():
    """A replayed or hostile clock behind the accepted one is dropped as long as the
    accepted one keeps coming, and one that does not advance steadily never takes over."""
    guard = ClockGuard(recover_after_s=2.0)
    running = [(100.0 + 0.2 * k, 0.01 * k) for k in range(500)]
    behind = [(10.0 + 0.2 * k, 0.01 * k + 0.005) for k in range(500)]
    verdicts = _feed(guard, [sample for pair in zip(running, behind) for sample in pair])
    assert set(verdicts[0::2]) == {"ok"} and set(verdicts[1::2]) == {"clock went backwards"}
    guard = ClockGuard(recover_after_s=2.0)
    assert guard.check(1000, 0, wall_s=0.0) is None
    zigzag = [(50.0 + (k % 2) * 20.0 - 0.01 * k, 0.01 * k) for k in range(1, 600)]
    assert set(_feed(guard, zigzag)) == {"clock went backwards"}
    assert guard.take_notice() is None


@pytest.mark.parametrize("values, reason", [
    ((1.0, math.nan), "not finite"), ((math.inf,), "not finite"), ((-1e308,), "implausibly"),
])
def test_numbers_must_be_finite_and_plausible(values, reason):
    assert reason in number_problem(values, "x")
    assert reason in array_problem(np.array(values), "x")
    assert number_problem((0.0, -1e8, 3.5), "x") is None
    assert array_problem(np.array([0.0, -1e8, 3.5]), "x") is None
    assert array_problem(np.zeros(0), "x") is None


def test_stamps_frames_ids_and_sizes():
    assert stamp_problem(0, 0) is None and "negative" in stamp_problem(-2**31, 0)
    assert frame_problem("map", "map") is None
    assert ("'x" * 1 in frame_problem("x" * 1000, "map")
            and "..." in frame_problem("x" * 1000, "map"))
    assert id_problem(2, 3, "robot") is None and "0..2" in id_problem(3, 3, "robot")
    assert "0..2147483647" in id_problem(2**32 - 1, None, "landmark id")
    assert size_problem(5, 5, "poses") is None and "at most 5" in size_problem(6, 5, "poses")
    assert first_problem([None, "a", "b"]) == "a" and first_problem([None]) is None
    assert landmark_reading_problem(3.0, 1e-6, 1e-5, 7) is None
    assert "variance" in landmark_reading_problem(3.0, 0.0, 1e-5, 7)
    assert stamp_step_problem(600_000_000, 3, 0.2) is None
    assert "step 3" in stamp_step_problem(600_000_001, 3, 0.2)


def test_steps_are_bounded_by_the_run_and_the_receivers_progress():
    assert step_problem(0, None, 100) is None
    assert "outside the run" in step_problem(2**64 - 1, None, 100)
    assert "stale" in step_problem(4, 5, 20000)
    assert step_problem(5 + MAX_STEP_LEAD, 5, 20000) is None
    assert "ahead" in step_problem(6 + MAX_STEP_LEAD, 5, 20000)


def test_barrier_needs_one_plausible_entry_per_robot():
    expected = {1: 4, 2: 1}  # next sequence expected from robots 1 and 2
    assert barrier_problem([], 3, expected, 100) is None
    assert barrier_problem([2**63, 103, 100], 3, expected, 100) is None  # own entry unbounded
    assert "2 barrier entries" in barrier_problem([0, 1], 3, expected, 100)
    assert "robot 1" in barrier_problem([0, 104, 0], 3, expected, 100)
    assert "robot 2" in barrier_problem([0, 0, 2**63], 3, expected, 100)
    # The receiver's own entry, given the scan's step: one record per step at most (a
    # restarted robot keeps an empty record for each number below it).
    assert barrier_problem([0, 101, 100], 3, expected, 100, own=(0, 0)) is None
    assert barrier_problem([51, 101, 100], 3, expected, 100, own=(0, 50)) is None
    assert "own barrier entry" in barrier_problem([2**63, 101, 100], 3, expected, 100,
                                                  own=(0, 50))


def test_a_commands_barrier_entry_never_goes_back_nor_leaps():
    """The world and the evaluator both drop a command whose team_sequence is behind the
    robot's last one (a forged ``finished`` with sequence 0 once ended a run in the
    evaluator, which the world had rejected) or implausibly far ahead."""
    assert command_sequence_problem(13, 13, 10_000) is None
    assert command_sequence_problem(14, 13, 10_000) is None
    assert command_sequence_problem(0, 13, 10_000) == "team_sequence 0 is behind 13"
    assert "implausibly far ahead" in command_sequence_problem(10_014, 13, 10_000)


def test_motion_commands_within_the_robots_kinematics():
    limits = dict(speed_mps=1.0, max_turn_rad=math.radians(15.0), time_step_s=0.2)
    assert command_problem(1.0, math.radians(15.0) / 0.2, **limits) is None
    assert "speed" in command_problem(5.0, 0.0, **limits)
    assert "turn rate" in command_problem(0.0, 10.0, **limits)
    assert "not finite" in command_problem(math.nan, 0.0, **limits)


def test_requests_from_teammates_or_the_observer_with_a_proper_range():
    assert request_problem(1, 1, 0, 0, 3, OBSERVER) is None
    assert request_problem(OBSERVER, 3, 7, 0, 3, OBSERVER) is None
    assert "requester" in request_problem(7, 1, 0, 0, 3, OBSERVER)
    assert "requester" in request_problem(0, 1, 0, 0, 3, OBSERVER)  # itself
    assert "range" in request_problem(1, 0, 0, 0, 3, OBSERVER)
    assert "range" in request_problem(1, 5, 4, 0, 3, OBSERVER)


def test_rejection_log_throttles_per_key_and_counts_what_it_held_back():
    log = RejectionLog(period_s=5.0, max_keys=3)
    assert log.note("/a", 0.0) == 1
    assert log.note("/a", 1.0) is None and log.note("/a", 2.0) is None
    assert log.note("/b", 2.0) == 1  # another key is not held back
    assert log.note("/a", 5.5) == 3
    assert log.note("/c", 6.0) == 1
    assert log.note("/d", 6.0) == 1 and log.note("/e", 6.5) is None  # both count as "other"
    assert log.total == 8


def test_reasons_of_one_kind_share_a_key():
    assert reason_kind("frame_id 'x' is not 'map'") == reason_kind("frame_id '' is not 'map'")
    assert reason_kind("step 12 is stale (next expected 40)") == reason_kind(
        "step 7 is stale (next expected 9)")
    assert reason_kind("twist is not finite (nan)") == reason_kind("twist is not finite (-inf)")
    assert reason_kind("step 12 is stale") != reason_kind("requester id 3 is not a teammate")


def test_resends_are_coalesced_per_requester_and_rate_limited():
    scheduler = ResendScheduler(min_interval_s=1.0, max_records=4)
    scheduler.request(1, 3, 4, latest_sequence=10)
    assert scheduler.due(0.0) == [ResendRange(1, 3, 4)]
    for first, last in ((5, 5), (2, 3), (7, 0)):  # a flood within the interval
        scheduler.request(1, first, last, latest_sequence=10)
    scheduler.request(OBSERVER, 9, 20, latest_sequence=10)
    assert scheduler.pending == 2
    assert scheduler.due(0.5) == [ResendRange(OBSERVER, 9, 10)]  # requester 1 must wait
    assert scheduler.due(1.0) == [ResendRange(1, 2, 5)]  # one merged range, at most 4 records
    assert scheduler.due(1.5) == []
    assert scheduler.due(2.0) == [ResendRange(1, 6, 9)]
    assert scheduler.due(3.0) == [ResendRange(1, 10, 10)]
    assert scheduler.pending == 0
    scheduler.request(2, 11, 0, latest_sequence=10)  # nothing there yet
    assert scheduler.pending == 0


def test_world_watch_reports_loss_return_and_a_final_timeout():
    watch = WorldWatch(timeout_s=10.0)
    assert watch.update(False, 0.0) is None  # not seen yet: just waiting
    assert watch.update(True, 1.0) is None
    assert watch.update(False, 2.0) == WorldEvent.LOST
    assert watch.update(True, 3.0) == WorldEvent.BACK
    assert watch.update(False, 4.0) == WorldEvent.LOST
    assert watch.update(False, 13.0) is None
    assert watch.update(False, 14.0) == WorldEvent.GONE
    assert watch.update(False, 30.0) is None  # reported once
