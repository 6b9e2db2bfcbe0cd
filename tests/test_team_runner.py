"""In-process team exploration (em-sim's engine) and the em-sim command."""
import json
import math
import subprocess
import sys

import pytest

from em_exploration_ros.core.agent.robot_agent import RobotAgent
from em_exploration_ros.core.evaluation.summary import check_summary
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.core.slam.team_slam import TeamSlam
from em_exploration_ros.core.world.simulation import WorldSimulation

SMALL = dict(world={"width_m": 50.0, "height_m": 50.0, "num_landmarks": 5},
             run={"seed": 3, "max_steps": 1500})


def small_params(planner: str = "NEAREST") -> ExplorationParams:
    return ExplorationParams().replace(planner={"name": planner}, **SMALL)


def test_small_nf_team_explores_to_target_ratio_with_metrics():
    summary = TeamRunner(small_params()).run()
    data = summary.to_dict()
    assert check_summary(data) == []
    assert summary.explored_ratio >= 0.85, summary.stop_reason
    assert summary.sim_time_s < 1500 * 0.2
    assert 0.0 < summary.loc_rmse_m < 1.0 and 0.0 < summary.landmark_rmse_m < 1.0
    assert summary.decisions == sum(r.decisions for r in summary.robots) > 3
    assert all(r.distance_m > 10.0 for r in summary.robots)  # every robot moved
    distances = [s.distance_m for s in summary.history]
    assert distances == sorted(distances) and len(summary.history) > 5
    json.dumps(data)  # NaN-free, serializable


def test_seeded_runs_reproduce_and_seeds_differ():
    def targets(seed: int) -> list:
        params = small_params().replace(run={"seed": seed, "max_steps": 400})
        summary = TeamRunner(params).run()
        return [(t.x, t.y, t.type) for r in summary.robots for t in r.targets]

    first = targets(5)
    assert first == targets(5)
    assert first != targets(6)


def test_agents_see_no_ground_truth():
    runner = TeamRunner(small_params())
    for agent in runner.agents:
        assert isinstance(agent, RobotAgent)
        forbidden = (runner.simulation, runner.simulation.world, runner.evaluator)
        assert not any(value is item for value in vars(agent).values() for item in forbidden)


def test_em_sim_command_writes_summary(tmp_path):
    out = tmp_path / "run.json"
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.sim_cli", "--planner", "NEAREST",
         "--map-size", "50", "--landmarks", "5", "--seed", "2", "--max-steps", "300",
         "--summary", str(out), "--quiet"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    data = json.loads(out.read_text())
    assert check_summary(data) == [] and data["planner"] == "NEAREST" and data["seed"] == 2
    assert data["num_robots"] == 3 and math.isfinite(data["explored_ratio"])


def test_em_sim_whose_reader_goes_away_still_writes_its_summary(tmp_path):
    """``em-sim ... | head -1``: the reader closes the pipe after the first progress line;
    em-sim goes on quietly, writes the summary, exits 0, prints no traceback."""
    out = tmp_path / "run.json"
    process = subprocess.Popen(
        [sys.executable, "-m", "em_exploration_ros.tools.sim_cli", "--planner", "NEAREST",
         "--map-size", "60", "--landmarks", "5", "--seed", "2", "--max-steps", "900",
         "--summary", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = process.stdout.readline()
    process.stdout.close()  # as head does after its line
    code = process.wait(timeout=120)
    stderr = process.stderr.read()
    assert first.startswith("t=") and code == 0, stderr
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr, stderr
    assert check_summary(json.loads(out.read_text())) == []


@pytest.mark.parametrize("args, message", [
    (["--robots", "0"], "num_robots"), (["--planner", "XX"], "invalid choice"),
    (["--params", "/nonexistent.yaml"], "cannot read"), (["--map-size", "-5"], "width_m"),
    (["--summary", "{absent}/s.json"], "--summary {absent}/s.json: the folder"),
    (["--map", "{absent}/map.png"], "--map {absent}/map.png: the folder")])
def test_em_sim_refuses_bad_arguments(args, message, tmp_path):
    absent = tmp_path / "absent"  # a folder that does not exist
    args = [arg.format(absent=absent) for arg in args]
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.sim_cli", *args],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and message.format(absent=absent) in result.stderr
    assert not absent.exists()


class MotorsDead(WorldSimulation):
    """A world in which no robot moves or turns, whatever it commands."""

    def apply_command(self, robot_id: int, linear_x: float, angular_z: float) -> None:
        pass


def test_stall_rule_ends_a_run_whose_robots_cannot_move():
    params = small_params().replace(run={"seed": 3, "max_steps": 1500, "stall_timeout_s": 20.0})
    summary = TeamRunner(params, simulation=MotorsDead(params)).run()
    assert summary.stop_reason.startswith("stalled: no distance and no newly explored area")
    assert summary.distance_m == 0.0
    # Metrics are evaluated every 2 s: the first at 2 s, the stall 20 s later.
    assert summary.sim_time_s == pytest.approx(22.0)
    assert all(r.blocked_s > 15.0 for r in summary.robots)  # each robot's odometry knew it


def test_em_sim_exits_with_status_4_when_the_run_stalls(tmp_path):
    from em_exploration_ros.tools import sim_cli
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    run:\n      stall_timeout_s: 10.0\n")
    out = tmp_path / "run.json"
    code = sim_cli.main(["--planner", "NEAREST", "--map-size", "50", "--landmarks", "5", "--seed",
                         "2", "--params", str(params), "--summary", str(out), "--quiet"],
                        make_runner=lambda params: TeamRunner(params,
                                                              simulation=MotorsDead(params)))
    assert code == 4
    data = json.loads(out.read_text())
    assert data["stop_reason"].startswith("stalled: ") and data["sim_time_s"] == 12.0


def test_a_failing_slam_update_mid_mission_is_resolved_and_reported(tmp_path, caplog):
    """iSAM2 raising in robot 1's 40th update (as GTSAM's IndeterminateSystemException did
    at the end of a divergence, BSP seed 44 at 200 m) costs neither the robot nor the run:
    the update is re-solved in batch, the mission ends as usual, the summary counts it and
    em-sim's log names it."""
    from em_exploration_ros.tools import sim_cli

    class FailingIsam:
        def update(self, *args: object) -> None:
            raise RuntimeError("Indeterminate linear system detected near variable 9")

    class FailingAt40th(TeamSlam):
        """A team graph whose iSAM2 raises in its 40th update."""

        updates = 0

        def update(self, *args: int) -> int:
            self.updates += 1
            if self.updates == 40:
                self._isam = FailingIsam()
            return super().update(*args)

    slams = {}

    def make_agent(robot, params, anchor):
        if robot != 1:
            return RobotAgent(robot, params, anchor)
        slams[robot] = FailingAt40th(robot, params.world.num_robots, params.slam, anchor)
        return RobotAgent(robot, params, anchor, slam=slams[robot])

    out = tmp_path / "run.json"
    code = sim_cli.main(["--planner", "NEAREST", "--map-size", "50", "--landmarks", "5", "--seed",
                         "2", "--summary", str(out), "--quiet"],
                        make_runner=lambda params: TeamRunner(params, make_agent=make_agent))
    assert code == 0 and slams[1].updates > 40
    data = json.loads(out.read_text())
    assert data["explored_ratio"] >= 0.85
    assert [robot["slam_recoveries"] for robot in data["robots"]] == [0, 1, 0]
    [warning] = [r.getMessage() for r in caplog.records if "re-solved" in r.getMessage()]
    assert warning.startswith("robot 1: iSAM2 update re-solved in batch (Indeterminate linear "
                              "system detected near variable 9)")
