"""A stopped clock is said within 5 s of wall time, and the world says which robots it steps
without (issue 40, point 4): session-level, ticks with wall times, no sleeps."""
from __future__ import annotations

import dataclasses

from em_exploration_ros.core.agent.clock_watch import ClockWatch
from em_exploration_ros.core.sessions.effects import Level, LogLine
from test_evaluator_session import WORLD_NODE
from test_evaluator_session import started as evaluator_started
from test_evaluator_session import truth as evaluator_truth
from test_robot_session import SETTINGS, commands, feed, started
from test_world_session import move as world_move
from test_world_session import session as world_session
from test_world_session import started as world_started


def lines(effects: list, level: Level) -> list[str]:
    return [e.text for e in effects if isinstance(e, LogLine) and e.level == level]


def test_the_watch_reports_after_the_wait_then_throttled_then_the_move():
    watch = ClockWatch(5.0, 30.0)
    assert watch.stopped(100.0) is None                       # nothing before a first step
    assert watch.seen(3, 0.0) is None
    assert watch.stopped(4.9) is None and watch.seen(3, 4.95) is None  # the same step
    assert watch.stopped(5.0) == 5.0
    assert watch.stopped(6.0) is None and watch.stopped(34.9) is None
    assert watch.stopped(35.0) == 35.0
    assert watch.seen(2, 36.0) is None                        # older: no move
    assert watch.seen(4, 36.0) == 36.0                        # moved after 36 s
    assert watch.seen(5, 37.0) is None                        # not reported stopped since
    assert watch.stopped(41.9) is None and watch.stopped(42.0) == 5.0


def test_the_watch_started_says_no_first_step_after_its_wait_then_throttled_until_one():
    watch = ClockWatch(5.0, 30.0, started_s=100.0, first_step_after_s=10.0)
    assert watch.no_first_step(109.9) is None
    assert watch.no_first_step(110.0) == 10.0
    assert watch.no_first_step(139.9) is None and watch.no_first_step(140.0) == 40.0
    assert watch.seen(0, 141.0) is None
    assert watch.no_first_step(500.0) is None                 # a step came
    assert ClockWatch(5.0, 30.0).no_first_step(1e9) is None   # no start given


def test_a_robot_warns_when_no_step_came_for_5_s_and_says_when_they_come_again():
    session, sim = started(relay_mode=False)
    assert session.tick(100.0, 0, None) == []                 # no step yet: the world waits
    assert len(commands(feed(session, sim, 0, 100.0, barrier=(0, 0, 0)))) == 1
    assert lines(session.tick(104.9, 0, None), Level.WARN) == []
    [warning] = lines(session.tick(105.0, 0, None), Level.WARN)
    assert warning == ("no new step from the world for 5.0 s (last step 0; this robot "
                       "answered it)")
    assert lines(session.tick(110.0, 0, None), Level.WARN) == []   # throttled
    assert len(lines(session.tick(135.0, 0, None), Level.WARN)) == 1
    moved = feed(session, sim, 1, 140.0, barrier=(0, 0, 0))
    assert "the world's steps come again: step 1 after 40.0 s without a new one" in \
        lines(moved, Level.INFO)


def test_a_robot_says_when_no_scan_came_10_s_after_its_start_and_not_once_one_came():
    """A robot restarted by hand that got nothing from the world waited in silence: it now
    says so, as information (at a first start the world holds its first step while the
    team connects)."""
    session, sim = started(relay_mode=False, started_s=50.0)
    assert lines(session.tick(59.9, 0, None), Level.INFO) == []
    [line] = lines(session.tick(60.0, 0, None), Level.INFO)
    assert line == ("no scan from the world yet, 10 s after this robot started (at a run's "
                    "start the world holds its first step until the team is connected)")
    assert lines(session.tick(89.9, 0, None), Level.INFO) == []
    assert lines(session.tick(90.0, 0, None), Level.INFO) == [line.replace("10 s", "40 s")]
    feed(session, sim, 0, 91.0, barrier=(0, 0, 0))
    assert not any("no scan from the world yet" in text
                   for text in lines(session.tick(200.0, 0, None), Level.INFO))
    quiet, _ = started(relay_mode=False)  # no start time given (em-sim): no such line
    assert lines(quiet.tick(1e6, 0, None), Level.INFO) == []


def test_a_robot_waiting_for_teammates_says_so_rather_than_blaming_the_world():
    settings = dataclasses.replace(SETTINGS, barrier_timeout_s=60.0)
    session, sim = started(relay_mode=False, settings=settings)
    feed(session, sim, 0, 0.0, barrier=(0, 0, 0))
    assert commands(feed(session, sim, 1, 0.1, barrier=(0, 2, 0))) == []
    [warning] = lines(session.tick(5.1, 1, None), Level.WARN)
    assert warning == ("no new step from the world for 5.0 s (last step 1; this robot waits "
                       "for teammates' records before it answers step 1)")


def test_the_evaluator_says_when_no_first_ground_truth_came_10_s_after_its_start():
    """A restarted evaluator that got nothing from the world waited in silence until the
    silence rule ended the run: it now says so, as information (at a first start the world
    holds its first step while the team connects), and whether the world is on the graph."""
    session = evaluator_started()  # started at wall time 0
    publishers = frozenset({WORLD_NODE})
    assert lines(session.tick(9.9, True, publishers), Level.INFO) == []
    [line] = lines(session.tick(10.0, True, publishers), Level.INFO)
    assert line == ("no ground truth from the world yet, 10 s after this evaluator started "
                    "(the world is on the ROS graph; at a run's start it holds its first "
                    "step until the team is connected); the run ends by silence after 60 s "
                    "without any")
    assert lines(session.tick(39.9, False, frozenset()), Level.INFO) == []
    assert ("no ground truth from the world yet, 40 s after this evaluator started (the "
            "world is not on the ROS graph)") in lines(session.tick(40.0, False, frozenset()),
                                                       Level.INFO)[-1]
    evaluator_truth(session, 0, wall_s=41.0)
    assert [line for line in lines(session.tick(75.0, True, publishers), Level.INFO)
            if "no ground truth from the world yet" in line] == []


def test_the_evaluator_warns_when_no_ground_truth_step_came_for_5_s():
    session = evaluator_started()
    publishers = frozenset({WORLD_NODE})
    for robot in range(2):
        session.liveliness(robot, True, False, 0.0)
    assert lines(session.tick(30.0, True, publishers), Level.WARN) == []  # no step
    for step in range(3):
        evaluator_truth(session, step, wall_s=31.0)
    assert lines(session.tick(35.9, True, publishers), Level.WARN) == []
    [warning] = lines(session.tick(36.0, True, publishers), Level.WARN)
    assert warning == ("no new step from the world for 5.0 s (last ground truth of step 2); "
                       "the run ends by silence after 60 s without one")
    assert lines(session.tick(40.0, True, publishers), Level.WARN) == []
    assert len(lines(session.tick(66.0, True, publishers), Level.WARN)) == 1
    moved = evaluator_truth(session, 3, wall_s=70.0)
    assert "the world's steps come again: step 3 after 39.0 s without a new one" in \
        lines(moved, Level.INFO)
    # Once the world stepped over, its clock stands still by design.
    session.world_status(3, 3, True, "every robot finished or stopped")
    assert lines(session.tick(80.0, True, publishers), Level.WARN) == []


def test_the_world_names_the_robots_it_steps_without_then_a_line_every_5_s():
    world = world_session()
    world_started(world)
    world.on_command(0, 0, world_move(0, 0), 1.1)
    effects = world.poll(2.5)                                 # robot 1 lost: step 0 closes
    assert "step 0 taken without robots 1: not answering, their vehicles stand still" in \
        lines(effects, Level.INFO)
    for step in range(1, 5):                                  # no line within 5 s
        effects = world.on_command(0, step, world_move(0, step), 2.5 + step)
        assert not [x for x in lines(effects, Level.INFO) if "taken without" in x]
    effects = world.on_command(0, 5, world_move(0, 5), 7.5)
    assert "step 5 taken without robots 1: 6 steps without them so far" in \
        lines(effects, Level.INFO)
    # A new process of robot 1 reports its liveliness: it is named as restarting.
    world.on_liveliness(1, True, True, 7.6)
    effects = world.on_command(0, 6, world_move(0, 6), 12.6)
    assert "step 6 taken without robots 1 (restarting): 7 steps without them so far" in \
        lines(effects, Level.INFO)
    # It answers again: the step waits for it, and the world says how long it went without.
    world.on_command(1, 6, world_move(1, 6), 12.7)
    effects = world.on_command(0, 7, world_move(0, 7), 12.8)
    assert world.sim.step == 7
    effects = world.on_command(1, 7, world_move(1, 7), 12.9)
    assert "step 7: 7 steps were taken without robots 1" in lines(effects, Level.INFO)
