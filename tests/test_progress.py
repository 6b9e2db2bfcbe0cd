"""Progress toward a target, giving targets up and the recovery turn (core.planning.progress),
and a robot agent that a world blocks."""
import numpy as np
import pytest

from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.geometry import between
from em_exploration_ros.core.params import ExplorationParams, ProgressParams
from em_exploration_ros.core.planning.frontiers import Frontier, frontier_cells
from em_exploration_ros.core.planning.progress import (GivenUpTarget, GiveUpReason, ProgressMonitor,
                                                       RecoveryTurn, TargetBlacklist)
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.records.wire_model import DeadReckoningIntegrator
from em_exploration_ros.core.world.world import step_pose

PARAMS = ProgressParams(window_s=10.0, min_progress_m=1.0, blacklist_radius_m=5.0,
                        blacklist_duration_s=100.0)
STEP_S = 0.2
STEP_M = 0.2


def run_monitor(monitor, distances, commanded, odometry):
    """Feed equal-length sequences one step at a time; (step index, verdict) of the first
    verdict, or None."""
    for k, (d, c, o) in enumerate(zip(distances, commanded, odometry)):
        verdict = monitor.update(k * STEP_S, d, c, o)
        if verdict is not None:
            return k, verdict
    return None


def test_a_robot_driving_to_its_target_makes_progress():
    steps = 400
    distances = 80.0 - STEP_M * np.arange(steps)
    assert run_monitor(ProgressMonitor(PARAMS), distances, [STEP_M] * steps,
                       [STEP_M] * steps) is None


def test_odometry_without_motion_while_driving_is_blocked_after_the_window():
    steps = 200
    verdict = run_monitor(ProgressMonitor(PARAMS), np.full(steps, 30.0), [STEP_M] * steps,
                          [0.0] * steps)
    assert verdict == (50, GiveUpReason.BLOCKED)  # 10 s after the first blocked step


def test_no_progress_while_the_odometry_shows_the_robot_blocked_is_blocked():
    steps = 200
    commanded = [0.0] * 30 + [STEP_M] * (steps - 30)  # pushing only for the last 4 s
    verdict = run_monitor(ProgressMonitor(PARAMS), np.full(steps, 30.0), commanded,
                          [0.0] * steps)
    assert verdict == (50, GiveUpReason.BLOCKED)


def test_standing_still_without_a_forward_command_is_not_blocked_but_makes_no_progress():
    steps = 200
    verdict = run_monitor(ProgressMonitor(PARAMS), np.full(steps, 30.0), [0.0] * steps,
                          [0.0] * steps)
    assert verdict == (50, GiveUpReason.NO_PROGRESS)


def test_circling_without_getting_closer_is_no_progress():
    steps = 300
    distances = 20.0 + 0.4 * np.sin(np.arange(steps) * 0.3)  # moves, never 1 m closer
    verdict = run_monitor(ProgressMonitor(PARAMS), distances, [STEP_M] * steps,
                          [STEP_M] * steps)
    assert verdict == (50, GiveUpReason.NO_PROGRESS)


def test_restart_forgets_the_approach():
    monitor = ProgressMonitor(PARAMS)
    for k in range(49):
        assert monitor.update(k * STEP_S, 30.0, STEP_M, 0.0) is None
    monitor.restart()
    for k in range(49, 99):  # 10 s after the restart at step 49
        assert monitor.update(k * STEP_S, 30.0, STEP_M, 0.0) is None
    assert monitor.update(99 * STEP_S, 30.0, STEP_M, 0.0) == GiveUpReason.BLOCKED


def test_blacklist_excludes_candidates_near_given_up_targets_until_it_expires():
    blacklist = TargetBlacklist(PARAMS)
    blacklist.add(GivenUpTarget(np.array([10.0, 10.0]), 50.0, GiveUpReason.BLOCKED))
    candidates = [Frontier(np.array(p), FrontierType.EXPLORATION)
                  for p in ([10.0, 10.0], [14.0, 10.0], [15.1, 10.0], [30.0, 30.0])]
    allowed = blacklist.allowed(candidates, 60.0)
    assert [c.position.tolist() for c in allowed] == [[15.1, 10.0], [30.0, 30.0]]
    assert blacklist.allowed(candidates, 150.0) == candidates  # expired after 100 s
    assert blacklist.allowed([], 60.0) == []


def test_blacklist_is_bounded():
    blacklist = TargetBlacklist(PARAMS, max_entries=3)
    for k in range(10):
        blacklist.add(GivenUpTarget(np.array([k * 100.0, 0.0]), 0.0, GiveUpReason.DEADLINE))
    assert len(blacklist.active(1.0)) == 3
    assert blacklist.excludes(np.array([[0.0, 0.0], [900.0, 0.0]]), 1.0).tolist() == [False, True]


@pytest.mark.parametrize("blocked_heading", [0.0, 3.0, -2.0])
def test_recovery_turn_ends_facing_away_from_the_blocked_direction(blocked_heading):
    turn = RecoveryTurn(blocked_heading)
    heading, steps = blocked_heading, 0
    while not turn.done(heading):
        heading = float(np.arctan2(np.sin(heading + np.radians(15)),
                                   np.cos(heading + np.radians(15))))
        steps += 1
    assert steps == 12  # 180 degrees at 15 degrees per step
    assert np.cos(heading - blocked_heading) < -0.99


# -- a robot agent in a world that blocks it ------------------------------------------------

#: The invisible wall: the world keeps a robot's position when it would cross x = WALL_X.
WALL_X = 30.0


def blocked_world_run(params: ExplorationParams, steps: int):
    """One robot without landmarks in a 60 m square world whose right half it cannot enter
    (an obstacle its sensors do not report); noise-free odometry. Returns the agent and, per
    step, (stamp [s], true pose (3,), whether the world blocked the step)."""
    agent = RobotAgent(0, params, np.array([8.0, 30.0, 0.0]))
    pose = np.array([8.0, 30.0, 0.0])
    odometry = DeadReckoningIntegrator()
    trace = []
    for step in range(steps):
        stamp = step * params.motion.time_step_s
        command = agent.step(StepInput(step, stamp, odometry.pose, np.eye(3) * 1e-8))
        moved = step_pose(pose, command.turn_rad, command.forward_m, params.motion)
        blocked = moved[0] > WALL_X
        if blocked:
            moved[:2] = pose[:2]
        odometry.add(between(pose, moved))
        pose = moved
        trace.append((stamp, pose.copy(), bool(blocked and command.forward_m > 0.0)))
        if command.finished:
            break
    return agent, trace


def test_a_blocked_robot_gives_its_target_up_in_the_window_and_never_returns_near_it():
    progress = {"window_s": 10.0, "min_progress_m": 1.0, "blacklist_radius_m": 8.0,
                "blacklist_duration_s": 1e9}
    params = ExplorationParams().replace(
        world={"width_m": 60.0, "height_m": 60.0, "num_robots": 1, "num_landmarks": 0},
        planner={"name": "NEAREST"}, progress=progress)
    agent, trace = blocked_world_run(params, 1500)
    blocked_given_up = [g for g in agent.given_up if g.reason == GiveUpReason.BLOCKED]
    assert blocked_given_up, "the wall never stopped the robot"
    first = blocked_given_up[0]
    first_blocked_s = next(stamp for stamp, _, blocked in trace if blocked)
    # Given up within the progress window (+ one step) of the first blocked step.
    assert first_blocked_s < first.stamp_s <= first_blocked_s + 10.0 + 0.2 + 1e-9
    for given_up in agent.given_up:
        later = [d.target.position for d in agent.decisions if d.stamp_s >= given_up.stamp_s]
        assert all(np.linalg.norm(p - given_up.position) > 8.0 for p in later), given_up
    # Before choosing again it turned on the spot to face away from the wall.
    next_decision = next(d for d in agent.decisions if d.stamp_s > first.stamp_s)
    heading = next(p[2] for stamp, p, _ in trace if stamp >= next_decision.stamp_s)
    assert np.cos(heading) < -0.9
    # No livelock against the wall: no stretch of blocked steps outlasts the window.
    stretch, longest = 0, 0
    for _, _, blocked in trace:
        stretch = stretch + 1 if blocked else 0
        longest = max(longest, stretch)
    assert 0.2 * longest <= 10.0 + 0.2 + 1e-9


def test_when_every_candidate_is_near_a_given_up_target_the_robot_falls_back_or_finishes(
        caplog):
    params = ExplorationParams().replace(
        world={"width_m": 60.0, "height_m": 60.0, "num_robots": 1, "num_landmarks": 0},
        planner={"name": "NEAREST"}, progress={"blacklist_radius_m": 0.5})
    agent = RobotAgent(0, params, np.array([8.0, 30.0, 0.0]))
    odometry = DeadReckoningIntegrator()
    pose = np.array([8.0, 30.0, 0.0])
    step = 0

    def run_step():
        nonlocal pose, step
        command = agent.step(StepInput(step, step * 0.2, odometry.pose, np.eye(3) * 1e-8))
        moved = step_pose(pose, command.turn_rad, command.forward_m, params.motion)
        odometry.add(between(pose, moved))
        pose, step = moved, step + 1
        return command

    while agent.explored_ratio <= params.frontiers.all_frontiers_below_ratio:
        run_step()  # until candidates are only the frontiers near the robot
    cells = frontier_cells(agent.grid, params.frontiers)
    for candidate in agent.last_candidates:
        agent.blacklist.add(GivenUpTarget(candidate.position, step * 0.2, GiveUpReason.BLOCKED))
    near = {tuple(c.position) for c in agent.last_candidates}
    agent.target = None  # decide at the next step
    decisions = len(agent.decisions)
    run_step()
    fallback = agent.decisions[-1].target.position
    assert len(agent.decisions) == decisions + 1 and tuple(fallback) not in near
    open_cells = [c for c in cells if tuple(c) not in near]
    nearest = min(open_cells, key=lambda c: np.linalg.norm(c - agent.current_pose()[:2]))
    assert np.linalg.norm(fallback - nearest) < 1e-9

    for cell in frontier_cells(agent.grid, params.frontiers):
        agent.blacklist.add(GivenUpTarget(cell, step * 0.2, GiveUpReason.BLOCKED))
    agent.target = None
    with caplog.at_level("INFO"):
        command = run_step()
    assert command.finished and len(agent.decisions) == decisions + 1
    assert "finished: no reachable frontier" in caplog.text
