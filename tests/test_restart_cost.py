"""What a restart costs (issue 40, point 5; docs/robustness.md): a robot restarted in
em-sim (``TeamRunner(restarts)``, em-sim ``--restart``) rejoins from its journals with the
uninterrupted run's estimate and target."""
import numpy as np
import pytest

from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools.sim_cli import build_parser, params_from_args

ROBOT, RESTART_STEP = 1, 125


def _state_after(restarts: list[tuple[int, int]], step: int) -> list:
    """Every robot's graph (each robot's trajectory, the landmarks) and decisions, as the
    restarted robot holds them, once ``step`` is processed (the default mission, seed 0)."""
    params = params_from_args(build_parser().parse_args(["--seed", "0"]), 0)
    runner = TeamRunner(params, restarts)
    while runner.simulation.step <= step:
        runner.step_once()
    agent = runner.agents[ROBOT]
    return ([agent.slam.trajectory(robot) for robot in range(params.world.num_robots)],
            agent.slam.landmark_estimates(),
            [(d.stamp_s, d.target.position) for d in agent.decisions], agent.target)


def test_a_restarted_robot_resumes_with_the_uninterrupted_estimate_and_target():
    clean = _state_after([], RESTART_STEP)
    restarted = _state_after([(ROBOT, RESTART_STEP)], RESTART_STEP)
    # The earlier process's updates replayed in its order and groups: the same iSAM2 steps.
    for (indices, poses), (indices_after, poses_after) in zip(clean[0], restarted[0]):
        np.testing.assert_array_equal(indices_after, indices)
        np.testing.assert_allclose(poses_after, poses, rtol=0, atol=1e-9)
    assert restarted[1].keys() == clean[1].keys()
    for landmark, position in clean[1].items():
        np.testing.assert_allclose(restarted[1][landmark], position, rtol=0, atol=1e-9)
    # It drives on to the target it had, not a new decision.
    assert len(restarted[2]) == len(clean[2]) > 0
    assert restarted[3] is not None
    np.testing.assert_allclose(restarted[3].position, clean[3].position, atol=1e-3)


def test_a_restart_of_no_robot_or_at_step_0_is_refused():
    params = params_from_args(build_parser().parse_args(["--seed", "0"]), 0)
    for restart in [(3, 10), (0, 0)]:
        with pytest.raises(ValueError):
            TeamRunner(params, [restart])
