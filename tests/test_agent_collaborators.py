"""A robot agent uses the collaborators it is given (planner, progress monitor, clock)
instead of the ones it builds from the parameters."""
import numpy as np
import pytest

from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.geometry import between
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.planner_api import (CandidateUtility, Decision,
                                                          PlanningContext)
from em_exploration_ros.core.planning.progress import GiveUpReason
from em_exploration_ros.core.records.wire_model import DeadReckoningIntegrator
from em_exploration_ros.core.world.world import step_pose

PARAMS = ExplorationParams().replace(
    world={"width_m": 60.0, "height_m": 60.0, "num_robots": 1, "num_landmarks": 0},
    planner={"name": "NEAREST"})
START = np.array([8.0, 30.0, 0.0])


class LastCandidatePlanner:
    """Chooses the last candidate (NEAREST, the parameters' planner, takes the first)."""

    name = "LAST"

    def __init__(self) -> None:
        self.chosen = []

    def choose(self, context: PlanningContext) -> Decision:
        chosen = context.candidates[-1]
        self.chosen.append(chosen)
        return Decision(chosen, [CandidateUtility(c, 0.0, 0.0, 0.0, 0.0)
                                 for c in context.candidates], 0.0)


class GiveUpOnThirdUpdate:
    """Progress monitor that calls every approach hopeless at its third step."""

    def __init__(self) -> None:
        self.updates = 0
        self.restarts = 0
        self.blocked_now = False
        self._in_approach = 0

    def restart(self) -> None:
        self.restarts += 1
        self._in_approach = 0

    def update(self, stamp_s, distance_m, commanded_forward_m, odometry_forward_m):
        self.updates += 1
        self._in_approach += 1
        return GiveUpReason.NO_PROGRESS if self._in_approach == 3 else None


class TickingClock:
    """Wall clock that advances 0.25 s each time it is read."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        self.now_s += 0.25
        return self.now_s


def drive(agent: RobotAgent, steps: int) -> None:
    """Noise-free odometry in an open world, ``steps`` steps of 0.2 s."""
    pose, odometry = START.copy(), DeadReckoningIntegrator()
    for step in range(steps):
        command = agent.step(StepInput(step, step * 0.2, odometry.pose, np.eye(3) * 1e-8))
        moved = step_pose(pose, command.turn_rad, command.forward_m, PARAMS.motion)
        odometry.add(between(pose, moved))
        pose = moved


def test_the_agent_decides_with_the_given_planner_monitor_and_clock():
    planner, monitor, clock = LastCandidatePlanner(), GiveUpOnThirdUpdate(), TickingClock()
    agent = RobotAgent(0, PARAMS, START, planner=planner, progress_monitor=monitor,
                       clock=clock)
    drive(agent, 8)  # decisions at steps 0, 3 and 6: each approach given up at its 3rd step
    assert agent.planner is planner and not agent.finished
    assert [d.stamp_s for d in agent.decisions] == pytest.approx([0.0, 0.6, 1.2])
    assert [d.target for d in agent.decisions] == planner.chosen
    assert [(g.stamp_s, g.reason) for g in agent.given_up] == [
        (d.stamp_s, GiveUpReason.NO_PROGRESS) for d in agent.decisions[1:]]
    assert monitor.updates == 7 and monitor.restarts == 3
    # The clock is read twice per decision: before the map rebuild and after the planner.
    assert all(d.planning_time_s == 0.25 for d in agent.decisions)
    assert clock.now_s == 100.0 + 0.5 * len(agent.decisions)


def test_without_collaborators_the_agent_builds_them_from_the_parameters():
    agent = RobotAgent(0, PARAMS, START)
    drive(agent, 10)
    assert agent.planner.name == "NEAREST" and agent.given_up == []
    assert agent.slam.latest_index(0) is not None
    assert 0.0 <= agent.decisions[0].planning_time_s < 60.0
