"""The step tracer: its stage arithmetic on written traces, and a traced ROS team that
still chooses em-sim's targets while every step's stages are recorded."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from ros_process import REPO_ROOT, RUN_TEAM, finish_team_run, start_team_run

from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools.step_trace import read_traces, report, stages


def write_trace(path, events):
    path.write_text("".join(f"{int(t * 1e9)} {kind} {topic}\n" for t, kind, topic in events))


def test_stages_match_the_nth_events_of_each_process(tmp_path):
    # Two steps of a one-robot world, 100 ms apart; times in seconds.
    world, robot = [], []
    for step, start in enumerate((0.0, 0.1)):
        world += [(start, "pub", "/clock"), (start + 0.001, "pub", "/robot_0/odom"),
                  (start + 0.002, "pub", "/world/ground_truth/robot_0"),
                  (start + 0.010 + step * 0.005, "cb", "/robot_0/motion_command")]
        robot += [(start + 0.003, "cb", "/robot_0/odom"),
                  (start + 0.008, "pub", "/robot_0/motion_command")]
    write_trace(tmp_path / "world.trace", world + [(0.6, "cpu", "6.5")])
    write_trace(tmp_path / "robot_0.trace", robot + [(0.5, "cb", "/clock")])
    with open(tmp_path / "robot_0.trace", "a") as trace:
        trace.write("9" * 20 + " pub /clock\n")  # beyond the int64 nanoseconds read into
        trace.write("12345 c")  # killed while writing a line
    traces = read_traces(tmp_path, 1)
    by_name = {s.name: s.seconds for s in stages(traces, 1)}
    np.testing.assert_allclose(by_name["world publishes a step (clock to last ground truth)"],
                               [0.002, 0.002], atol=1e-9)
    np.testing.assert_allclose(by_name["robot 0: odometry published to its callback"],
                               [0.002, 0.002], atol=1e-9)
    np.testing.assert_allclose(by_name["robot 0: odometry callback to command published"],
                               [0.005, 0.005], atol=1e-9)
    np.testing.assert_allclose(by_name["robot 0: command published to the world's callback"],
                               [0.002, 0.007], atol=1e-9)
    np.testing.assert_allclose(by_name["whole step (clock to next clock)"], [0.1], atol=1e-9)
    table = report(traces, 1)
    assert "robot 0: odometry callback to command published" in table
    assert "CPU time [s]: world 6.50, robot_0 ? (no exit line)" in table
    assert "unreadable lines skipped: {'robot_0': 2}" in table


def test_report_refuses_a_directory_without_traces(tmp_path):
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.step_trace",
                             "report", str(tmp_path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and "no world.trace" in result.stderr
    write_trace(tmp_path / "world.trace", [(0.0, "pub", "/clock")])
    write_trace(tmp_path / "robot_0.trace", [])
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.step_trace",
                             "report", str(tmp_path), "--robots", "2"], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2 and "robot_1.trace: no such trace" in result.stderr


def test_report_names_a_trace_it_cannot_read(tmp_path):
    write_trace(tmp_path / "world.trace", [(0.0, "pub", "/clock")])
    (tmp_path / "robot_0.trace").mkdir()
    result = subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.step_trace",
                             "report", str(tmp_path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2, result.stderr
    assert "robot_0.trace: cannot read it (Is a directory)" in result.stderr


def test_a_traced_team_chooses_em_sims_targets_and_reports_every_step(tmp_path):
    summary_path, trace_dir = tmp_path / "run" / "summary.json", tmp_path / "trace"
    run, _ = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST", "--map-size",
                            "30", "--landmarks", "3", "--seed", "1", "--summary",
                            str(summary_path), "--trace-steps", str(trace_dir))
    assert finish_team_run(run, 120.0) == 0, run.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    reference = TeamRunner(load_params(REPO_ROOT / "config" / "exploration.yaml").replace(
        world={"num_robots": 3, "width_m": 30.0, "height_m": 30.0, "num_landmarks": 3},
        planner={"name": "NEAREST"}, run={"seed": 1})).run().to_dict()
    assert [r["targets"] for r in summary["robots"]] == [r["targets"] for r in
                                                         reference["robots"]]
    steps = round(summary["sim_time_s"] / 0.2)  # the world's steps (0.2 s each)
    traces = read_traces(trace_dir, 3)
    for stage in stages(traces, 3):
        assert len(stage.seconds) >= steps - 1, stage.name
        assert np.all(stage.seconds >= 0.0) and np.all(stage.seconds < 30.0), stage.name
    assert set(traces) == {"world", "evaluator", "robot_0", "robot_1", "robot_2"}
    for name, trace in traces.items():  # each exited normally and said what it used
        assert trace.cpu_s is not None and 0.5 < trace.cpu_s < 120.0, name
        assert trace.unreadable == 0, name
    # A second run may not mix its traces into the first one's.
    again = subprocess.run(["bash", str(RUN_TEAM), "--trace-steps", str(trace_dir),
                            "--summary", str(tmp_path / "again" / "summary.json")],
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "already holds traces" in again.stderr
