"""Issue 40, point 4: the clock guard never takes up a clock that has not advanced on its
own. Measured before: a publisher sending sec = 0 at 20 Hz for 4 s while the world paused
was taken up, and every node jumped from 67.4 s back to 0."""
from em_exploration_ros.core.agent.input_checks import ClockGuard

WORLD_STEP_S = 0.2


def _world_until(guard: ClockGuard, end_s: float, wall_per_step_s: float = 0.05) -> float:
    """The world's clock, one sample per step from 0 to ``end_s``; the wall time of the
    last sample. Every sample is accepted."""
    steps = int(round(end_s / WORLD_STEP_S))
    for k in range(steps + 1):
        stamp_ns = k * int(WORLD_STEP_S * 1e9)
        assert guard.check(stamp_ns // 10**9, stamp_ns % 10**9, wall_s=k * wall_per_step_s) is None
    return steps * wall_per_step_s


def _rival(guard: ClockGuard, stamps_ns, start_wall_s: float, period_s: float = 0.05):
    """Feed ``stamps_ns`` one every ``period_s`` wall seconds from ``start_wall_s``; the
    verdicts (None: accepted) and the wall time of the last sample."""
    verdicts, wall_s = [], start_wall_s
    for k, stamp_ns in enumerate(stamps_ns):
        wall_s = start_wall_s + k * period_s
        verdicts.append(guard.check(stamp_ns // 10**9, stamp_ns % 10**9, wall_s=wall_s))
    return verdicts, wall_s


def test_repeated_identical_stamps_behind_a_paused_world_are_never_taken_up():
    guard = ClockGuard(recover_after_s=2.0)
    paused_at_wall_s = _world_until(guard, 67.4)
    assert guard.latest_ns == 67_400_000_000
    # The world pauses; a publisher sends sec = 0 at 20 Hz for 4 s (twice recover_after_s).
    verdicts, wall_s = _rival(guard, [0] * 80, paused_at_wall_s + 0.05)
    assert wall_s - paused_at_wall_s >= 4.0
    assert all(v is not None and "backwards" in v for v in verdicts), verdicts
    assert guard.latest_ns == 67_400_000_000 and guard.take_notice() is None
    # ... and for a minute more, still the same stamp: never taken up.
    verdicts, _ = _rival(guard, [0] * 1200, wall_s + 0.05)
    assert all(v is not None for v in verdicts) and guard.latest_ns == 67_400_000_000
    # The world resumes where it paused.
    assert guard.check(67, 600_000_000, wall_s=wall_s + 70.0) is None


def test_a_rival_that_creeps_less_than_a_second_is_not_taken_up():
    """Increasing stamps that add up to less than a second of its own advance (here 0.1 s
    in 4 s of wall time) do not make a clock."""
    guard = ClockGuard(recover_after_s=2.0)
    paused_at_wall_s = _world_until(guard, 67.4)
    verdicts, _ = _rival(guard, [k * 1_250_000 for k in range(80)], paused_at_wall_s + 0.05)
    assert all(v is not None for v in verdicts) and guard.take_notice() is None


def test_a_rival_of_too_few_increasing_stamps_is_not_taken_up():
    """Identical stamps with two increases of a second each: a second of advance, but not
    several increasing stamps."""
    guard = ClockGuard(recover_after_s=2.0)
    paused_at_wall_s = _world_until(guard, 67.4)
    stamps = [0] * 40 + [1_000_000_000] * 20 + [2_000_000_000] * 20
    verdicts, _ = _rival(guard, stamps, paused_at_wall_s + 0.05)
    assert all(v is not None for v in verdicts) and guard.take_notice() is None


def test_a_rival_that_advances_on_its_own_is_taken_up_after_identical_stamps():
    """A clock that went back is still taken up once it runs: after 4 s of identical sec = 0
    stamps, the timeline that then advances (0.2 s per 0.05 s wall) is taken up once it has
    advanced at least a second with several increasing stamps."""
    guard = ClockGuard(recover_after_s=2.0)
    paused_at_wall_s = _world_until(guard, 67.4)
    verdicts, wall_s = _rival(guard, [0] * 80, paused_at_wall_s + 0.05)
    assert all(v is not None for v in verdicts)
    running = [k * 200_000_000 for k in range(1, 40)]
    verdicts, _ = _rival(guard, running, wall_s + 0.05)
    taken_up = verdicts.index(None)
    assert all(v is not None for v in verdicts[:taken_up])
    assert all(v is None for v in verdicts[taken_up:])
    assert running[taken_up] >= 1_000_000_000 and taken_up + 1 >= 3
    assert running[taken_up - 1] < 1_000_000_000  # as soon as both hold
    assert guard.take_notice().startswith(
        f"clock taken up again at {running[taken_up] / 1e9:.3f} s: it went back from 67.400 s")
