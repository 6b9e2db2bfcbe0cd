"""launch_scripts/run_team.sh: refuses bad arguments at once; runs a whole team end to end.

The end-to-end run starts the real processes (em-world, three em-robot, em-evaluator,
em-record) in this test run's ROS domain, on a small map with the cheap NEAREST planner, and
checks what the user gets: the summary JSON in em-sim's schema, the map picture, exit code 0,
no process of the run left behind, the same decisions as em-sim for the same seed, and a bag
directory that rosbags reads whole, whose /tf holds every robot's frame chain.
"""
from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from ros_process import (REPO_ROOT, RUN_PROCESS_PATTERN, RUN_TEAM, finish_team_run,
                         processes_in_domain, robot_pid, start_team_run, wait_for_liveliness)
from rosbags.rosbag2 import Reader as RosbagsReader
from small_disk import small_disk
from summary_keys import key_paths
from tf_chains import assert_frame_chains
from websockets.sync.client import connect

from em_exploration_ros.bag_format.bag_directory import read_metadata_yaml
from em_exploration_ros.bag_format.bag_reader import scan_bag
from em_exploration_ros.core.evaluation.summary import check_summary
from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.nodes.fastdds_shm import shared_memory_port_file

#: Bound of the end-to-end run (set-up check, start-up, exploration, shutdown) [s].
RUN_TIMEOUT_S = 150.0


def run_team(*args: str, timeout_s: float = 20.0) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(RUN_TEAM), *args], capture_output=True, text=True,
                          timeout=timeout_s, stdin=subprocess.DEVNULL)


@pytest.mark.parametrize("args, message", [
    (["--bogus"], "unknown argument '--bogus'"),
    (["--robots", "three"], "--robots expects a whole number"),
    (["--robots", "0"], "--robots must be in [1, 26]"),
    (["--seed", "-4"], "--seed expects a whole number, got '-4'"),
    (["--seed", "1.5"], "--seed expects a whole number"),
    (["--map-size", "5"], "--map-size must be in [10, 2000]"),
    (["--cell-size", "0"], "--cell-size must be in [0.1, 50]"),
    (["--until-explored=1.2"], "--until-explored must be in [0, 1]"),
    (["--max-sim-time", "soon"], "--max-sim-time expects a number"),
    (["--planner", "RANDOM"], "unknown planner 'RANDOM'"),
    (["--params", "/nonexistent/exploration.yaml"], "no readable file"),
    (["--realtime", "0"], "--realtime must be in [0.01, 1000]"),
    (["--domain-id", "500"], "--domain-id must be in [0, 232]"),
    (["--robots"], "--robots needs a value"),
    (["--foxglove", "70000"], "--foxglove must be in [1, 65535]"),
    (["--comm-loss", "1.5"], "--comm-loss must be in [0, 0.99]"),
    (["--comm-range", "far"], "--comm-range expects a number"),
    (["--netns", "em_absent_"], "cannot run in network namespace 'em_absent_world'"),
    (["--summary", "/tmp/em run\n/summary.json"],
     "--summary: the path must not contain control characters, got $'/tmp/em run\\n/"),
])
def test_refuses_bad_arguments(args, message):
    result = run_team(*args)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "--help" in result.stderr


def test_refuses_a_respawn_confirmation_time_that_is_not_whole_seconds(monkeypatch):
    """EM_RESPAWN_CONFIRM_S: how long a restarted robot has to show its liveliness before
    --respawn restarts it again (a process wedged in its start-up)."""
    monkeypatch.setenv("EM_RESPAWN_CONFIRM_S", "soon")
    result = run_team("--respawn")
    assert result.returncode == 2, result.stderr
    assert "EM_RESPAWN_CONFIRM_S expects a whole number of seconds, got 'soon'" in result.stderr


@pytest.mark.parametrize("text, extra, message", [
    ("/em_world:\n  ros__parameters:\n    robot_timout_s: 3.0\n", [],
     "did you mean 'robot_timeout_s'"),
    ("/em_world:\n  ros__parameters:\n    world.width_m: abc\n", [], "must be a number"),
    # the file's own section again: one of the keys twice, which YAML would keep the last of
    ("/**:\n  ros__parameters:\n    world.width_m: 50.0\n", [], "duplicate key '/**' at line"),
    # --cell-size reaches the parameters the nodes would get: checked against the world's side
    ("", ["--map-size", "40", "--cell-size", "20"],
     "MapParams.cell_size_m = 20.0 m gives fewer than 4 cells along the world's 40.0 m side"),
    ("", ["--summary", "/proc/em_run/summary.json"], "--summary: cannot create the folder"),
    ("", ["--summary", "/proc/summary.json"], "--summary /proc/summary.json: cannot write"),
    ("", ["--record", "/proc/run.mcap"], "--record /proc/run.mcap: cannot write"),
])
def test_refuses_bad_parameters_and_outputs_before_starting(tmp_path, text, extra, message):
    params = tmp_path / "params.yaml"
    params.write_text((REPO_ROOT / "config" / "exploration.yaml").read_text() + text)
    runs = REPO_ROOT / "runs"
    before = set(runs.iterdir()) if runs.is_dir() else set()
    result = run_team("--params", str(params), *extra, timeout_s=60.0)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert "logs in" not in result.stdout  # no process was started
    # A refused run leaves no folder of its own (it left runs/<stamp>/logs/ros behind).
    assert (set(runs.iterdir()) if runs.is_dir() else set()) == before


@pytest.mark.parametrize("where", ["logs", "trace"])
def test_refuses_a_recording_into_a_folder_the_run_makes_before_starting(tmp_path, where):
    """The log folder beside the summary (and the --trace-steps folder) are made before the
    outputs are checked: a recording there used to pass the check, then fail once the team
    had started."""
    run_dir = tmp_path / "run"
    result = run_team("--summary", str(run_dir / "summary.json"), "--record",
                      str(run_dir / where), "--trace-steps", str(run_dir / "trace"),
                      timeout_s=60.0)
    assert result.returncode == 2, result.stderr
    assert f"--record {run_dir / where} is a directory" in result.stderr
    assert "logs in" not in result.stdout  # no process was started
    assert not run_dir.exists()  # the folders it made for the run are gone again


def test_help_lists_the_options():
    result = run_team("--help")
    assert result.returncode == 0
    for flag in ("--robots", "--seed", "--planner", "--map-size", "--cell-size", "--landmarks",
                 "--until-explored", "--max-sim-time", "--params", "--realtime", "--summary",
                 "--domain-id", "--record", "--foxglove", "--comm-range", "--comm-loss",
                 "--comm-latency", "--comm-bandwidth"):
        assert flag in result.stdout


#: A progress window short enough that, with seed 2, a robot gives a target up (no
#: progress while it turns towards it), so the summaries' given_up lists are compared.
PROGRESS_WINDOW_S = 2.0


def _short_progress_window(tmp_path) -> str:
    """The default parameter file with ``PROGRESS_WINDOW_S``, written under ``tmp_path``."""
    default = (REPO_ROOT / "config" / "exploration.yaml").read_text()
    assert default.count("window_s: 20.0") == 1
    params = tmp_path / "params.yaml"
    params.write_text(default.replace("window_s: 20.0", f"window_s: {PROGRESS_WINDOW_S}"))
    return str(params)


def _em_sim_summary(seed: int, until: float) -> dict:
    """em-sim's summary of the three-robot NEAREST run on the 40 m map with 4 landmarks and
    ``PROGRESS_WINDOW_S`` (the end-to-end run's mission)."""
    return TeamRunner(load_params(REPO_ROOT / "config" / "exploration.yaml").replace(
        world={"num_robots": 3, "width_m": 40.0, "height_m": 40.0, "num_landmarks": 4},
        planner={"name": "NEAREST"}, run={"seed": seed, "until_explored": until},
        progress={"window_s": PROGRESS_WINDOW_S})).run().to_dict()


def test_three_robots_explore_end_to_end(tmp_path):
    summary_path = tmp_path / "run" / "summary.json"
    bag = tmp_path / "run_bag"
    until = 0.85
    params = _short_progress_window(tmp_path)
    run, domain = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST",
                            "--map-size", "40", "--landmarks", "4", "--seed", "2",
                            "--until-explored", str(until), "--max-sim-time", "600",
                            "--params", params,
                            "--summary", str(summary_path), "--record", str(bag))
    # A second mission (another seed) given the same domain id is refused at start, naming
    # the first; before, both ran and took each other's messages. The first equals em-sim's
    # run below, as alone.
    second_dir = tmp_path / "second"
    second = run_team("--seed", "5", "--domain-id", domain, "--summary",
                      str(second_dir / "summary.json"), timeout_s=60.0)
    assert second.returncode == 2, second.stdout + second.stderr
    assert (f"error: ROS_DOMAIN_ID {domain} is in use by another run of this project "
            f"(run_team.sh pid {run.pid}, seed 2, run folder {summary_path.parent})"
            in second.stderr), second.stderr
    assert not second_dir.exists()
    code = finish_team_run(run, RUN_TIMEOUT_S)
    output = run.output()
    assert code == 0, output[-3000:]
    assert f"summary: {summary_path}" in output and "explored" in output

    summary = json.loads(summary_path.read_text())
    assert check_summary(summary) == []
    assert summary["num_robots"] == 3 and summary["planner"] == "NEAREST" and summary["seed"] == 2
    assert summary["explored_ratio"] >= until, summary["stop_reason"]
    assert "explored ratio" in summary["stop_reason"] or "every robot finished" in \
        summary["stop_reason"]
    assert math.isfinite(summary["loc_rmse_m"]) and 0.0 <= summary["loc_rmse_m"] < 1.0
    assert math.isfinite(summary["landmark_rmse_m"]) and summary["landmark_rmse_m"] < 1.0
    assert summary["decisions"] >= 20 and summary["sim_time_s"] > 0.0
    assert all(robot["distance_m"] > 1.0 for robot in summary["robots"])
    assert summary["history"] and summary["history"][-1]["explored_ratio"] == \
        summary["explored_ratio"]

    # The ROS system in lockstep makes em-sim's decisions (same seed, same parameters).
    reference = _em_sim_summary(2, until)
    assert [r["targets"] for r in summary["robots"]] == [r["targets"] for r in
                                                         reference["robots"]]
    # Each robot's own progress bookkeeping reaches the evaluator through its commands.
    assert any(r["given_up"] for r in reference["robots"])
    assert [(r["given_up"], r["blocked_s"]) for r in summary["robots"]] == [
        (r["given_up"], r["blocked_s"]) for r in reference["robots"]]
    assert (summary["stop_reason"], summary["sim_time_s"]) == (reference["stop_reason"],
                                                               reference["sim_time_s"])
    assert summary["distance_m"] == pytest.approx(reference["distance_m"], abs=1e-6)
    assert_same_summary(summary, reference)
    # Each robot's position sigma at every evaluation, from the keyframe covariances it
    # published (/robot_i/estimated_pose; em-sim's observer takes the same values): em-sim's,
    # to the last digits two iSAM2 processes may differ in.
    sigmas, expected = (pose_sigmas(s) for s in (summary, reference))
    assert sigmas.shape == expected.shape and sigmas.shape[1] == 3
    assert math.isfinite(sigmas[-1].sum())
    assert sigmas.ravel().tolist() == pytest.approx(expected.ravel().tolist(), rel=1e-6,
                                                    nan_ok=True)

    for name in ("summary_map.png", "summary_timeline.png"):  # as em-sim draws beside it
        assert summary_path.with_name(name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    logs = summary_path.parent / "logs"
    assert {"world.log", "evaluator.log", "robot_0.log", "robot_1.log",
            "robot_2.log"} <= {p.name for p in logs.iterdir()}
    # Nothing of the run is left: run_team.sh stopped every process it started.
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []

    # The recording is a bag directory that rosbags reads whole.
    assert f"bag:     {bag}" in output
    assert summary["recording"] == {"path": str(bag), "complete": True, "problem": None}
    info = scan_bag(bag)
    with RosbagsReader(bag) as reader:
        assert reader.message_count == info.message_count == read_metadata_yaml(bag).message_count
    # ... from the first step: the robots answered it only once the recorder subscribed to
    # all their topics (it once missed their first 30 commands, subscribed as discovered).
    counts = info.topic_counts()
    steps = counts["/world/ground_truth/robot_0"]
    assert [counts[f"/robot_{robot}/motion_command"] for robot in range(3)] == [steps] * 3
    assert_frame_chains(bag, num_robots=3, max_error_m=2.0)


def test_a_recording_onto_a_full_disk_does_not_stop_the_mission(tmp_path):
    """The disk of the recording fills up mid-run: em-record ends the bag whole with what
    reached it and exits 3; the team goes on to its goal; run_team.sh says so, notes it in
    the summary ("recording") and exits 6. Before, the recorder's exit ended the run: every
    process stopped, exit code 1, the summary cut at 42 s of simulated time."""
    summary_path = tmp_path / "run" / "summary.json"
    with small_disk(tmp_path / "disk", 8 * 1024 + 96) as disk:  # 96 KiB beyond the reserve
        bag = disk / "bag"
        run, domain = start_team_run(tmp_path, "--planner", "NEAREST", "--map-size", "40",
                                     "--landmarks", "4", "--seed", "2", "--until-explored",
                                     "0.7", "--summary", str(summary_path), "--record", str(bag))
        code = finish_team_run(run, RUN_TIMEOUT_S)
        output = run.output()
        assert code == 6, output[-3000:]
        assert "warning: the recording stopped early; the team goes on (em-record exited " \
            "with code 3: cannot write to" in output
        summary = json.loads(summary_path.read_text())
        assert summary["explored_ratio"] >= 0.7, summary["stop_reason"]
        recording = summary["recording"]
        assert recording["path"] == str(bag) and recording["complete"] is False
        assert "No space left on device" in recording["problem"]
        assert f"recording incomplete: {recording['problem']}" in output
        info = scan_bag(bag)  # whole: summary and footer
        assert info.complete and info.message_count > 0
        with RosbagsReader(bag) as reader:
            assert reader.message_count == info.message_count
        assert read_metadata_yaml(bag).message_count == info.message_count
        assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []


#: Keys of the summary a ROS run and em-sim may differ in, and why.
SUMMARY_KEYS_APART = {
    # Wall-clock measurements of different processes.
    "wall_s", "decision_time_median_s", "decision_time_max_s",
    # The metrics from estimates: em-evaluator reads those each robot published at its
    # latest keyframe step, em-sim the agents' own at the step before the evaluation (with
    # the teammates' records applied since): the last digits may differ. The team distance
    # is compared above (to 1e-6: sums in another order).
    "explored_ratio", "loc_rmse_m", "landmark_rmse_m", "history", "distance_m",
    # Over perfect links no relay counts the ROS team's deliveries (null); em-sim's link
    # model does.
    "team_updates",
    # run_team.sh adds the recording's entry (--record) to the evaluator's summary.
    "recording",
    # Compared robot by robot (ROBOT_KEYS_APART), and meeting by meeting (MEETING_TRACES).
    "robots", "meetings",
}
#: A meeting's covariance traces come from each process's own iSAM2 solve of the same
#: graph: they agree to about 1e-8 relative, not to the bit.
MEETING_TRACES = ("trace_before_m2", "trace_after_m2")
#: Keys of each robot's entry a ROS run and em-sim may differ in, and why.
ROBOT_KEYS_APART = {
    # Wall-clock measurements.
    "decision_times_s", "downtime_wall_s",
    # The times of status changes: em-evaluator sees every command as it comes (the
    # commands after the stop step too, until the world stops), em-sim reports each robot's
    # state at the evaluation steps: a robot that finished is "finished" at a later step.
    "status", "status_changes",
    # The distance from ground truth, compared to 1e-6 (sums in another order).
    "distance_m",
}


def pose_sigmas(summary: dict) -> np.ndarray:
    """(samples, robots) array of the history's robot_pose_sigma_m, null as NaN."""
    return np.array([[math.nan if v is None else v for v in sample["robot_pose_sigma_m"]]
                     for sample in summary["history"]], dtype=float)


def assert_same_summary(summary: dict, reference: dict) -> None:
    """em-evaluator wrote em-sim's summary (both built by EvaluatorSession): the same keys
    at every level (but the run's recording), the same values but where they may differ."""
    assert reference["meetings"]  # seed 2 has meetings: their comparison is not vacuous
    assert key_paths(summary) - key_paths(reference) <= {
        ".recording", ".recording.path", ".recording.complete", ".recording.problem"}
    assert key_paths(reference) - key_paths(summary) <= {
        ".team_updates.sent", ".team_updates.on_time", ".team_updates.late",
        ".team_updates.never"}
    for key in set(reference) - SUMMARY_KEYS_APART:
        assert summary[key] == reference[key], key
    for ours, em_sim in zip(summary["meetings"], reference["meetings"], strict=True):
        assert {k: v for k, v in ours.items() if k not in MEETING_TRACES} == {
            k: v for k, v in em_sim.items() if k not in MEETING_TRACES}
        assert [ours[k] for k in MEETING_TRACES] == pytest.approx(
            [em_sim[k] for k in MEETING_TRACES], rel=1e-6)
    for ours, em_sim in zip(summary["robots"], reference["robots"], strict=True):
        for key in set(em_sim) - ROBOT_KEYS_APART:
            assert ours[key] == em_sim[key], (ours["id"], key)
        assert ours["distance_m"] == pytest.approx(em_sim["distance_m"], abs=1e-6)


def test_a_run_whose_robots_all_finish_at_an_evaluation_step_ends_there(tmp_path):
    """The evaluator evaluates every step here, so the robots' last answers (finished) come
    after the evaluation of their step: the run waited 121 s for ground truth that the
    world, which had stepped over, never sent, and ended with exit code 3."""
    params = tmp_path / "params.yaml"
    params.write_text((REPO_ROOT / "config" / "exploration.yaml").read_text()
                      + "\n/em_evaluator:\n  ros__parameters:\n    metrics_interval_s: 0.2\n")
    summary_path = tmp_path / "summary.json"
    run, _ = start_team_run(tmp_path, "--robots", "2", "--planner", "NEAREST", "--map-size",
                            "30", "--landmarks", "3", "--seed", "1", "--until-explored", "1",
                            "--max-sim-time", "600", "--params", str(params),
                            "--summary", str(summary_path))
    code = finish_team_run(run, RUN_TIMEOUT_S)
    assert code == 0, run.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    assert summary["stop_reason"] == "every robot finished"
    world = (summary_path.parent / "logs" / "world.log").read_text()
    assert f"stepping over at step {round(summary['sim_time_s'] / 0.2)} " in world
    assert summary["wall_s"] < 60.0  # not the 120 s of silence the evaluator once waited


def test_a_run_whose_robots_all_die_ends_when_the_world_steps_over(tmp_path):
    """Every robot killed (no --respawn): the world steps over ("every robot finished or
    stopped") and says so on /world/status; the evaluator, which counts no robot as
    finished, ends the run then (exit code 3) instead of after silence_timeout_s (120 s)."""
    params = tmp_path / "params.yaml"
    params.write_text((REPO_ROOT / "config" / "exploration.yaml").read_text()
                      + "\n/em_world:\n  ros__parameters:\n    robot_timeout_s: 5.0\n")
    summary_path = tmp_path / "summary.json"
    run, domain = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST",
                                 "--map-size", "100", "--landmarks", "3", "--seed", "1",
                                 "--until-explored", "0.99", "--params", str(params),
                                 "--summary", str(summary_path))
    logs = summary_path.parent / "logs"

    def kill_every_robot() -> None:
        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
        for robot in range(3):
            wait_for_liveliness(logs / "world.log", robot, RUN_TIMEOUT_S)
        for robot in range(3):
            os.kill(robot_pid(domain, robot), signal.SIGKILL)

    code = finish_team_run(run, RUN_TIMEOUT_S, meanwhile=kill_every_robot)
    assert code == 3, run.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    assert summary["stop_reason"].startswith("the world stepped over at step "), summary
    assert "(every robot finished or stopped)" in summary["stop_reason"]
    assert all(robot["status_changes"][0]["status"] == "lost" for robot in summary["robots"])
    assert summary["wall_s"] < 60.0  # not the 120 s of silence the evaluator once waited


def test_a_signal_while_the_run_stops_kills_every_process_at_once(tmp_path):
    """A supervisor's TERM soon after its INT (or a second Ctrl-C) while run_team.sh stops
    the nodes: it kills what is left and exits. It used to die in the middle of stopping
    and leave the remaining nodes running."""
    run, domain = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST",
                                 "--map-size", "100", "--until-explored", "0.95",
                                 "--summary", str(tmp_path / "summary.json"))
    with run:
        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
        run.signal_group(signal.SIGINT)
        run.wait_for_output("stopping (interrupted)", 10.0)
        run.signal_group(signal.SIGTERM)
        code = run.wait(10.0)
    assert code == 143, run.output()[-3000:]
    assert "stopped at once (a signal while stopping)" in run.output()
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_ctrl_c_stops_every_process_and_keeps_the_summary(tmp_path):
    summary_path = tmp_path / "summary.json"
    port = _free_port()
    run, domain = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST",
                            "--map-size", "100", "--until-explored", "0.95",
                            "--summary", str(summary_path), "--foxglove", str(port))
    with run:
        run.wait_for_output("t=   20.0 s", RUN_TIMEOUT_S)
        # --foxglove: the live view answers on its port (it is one of the run's processes).
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                     open_timeout=20) as viewer:
            assert json.loads(viewer.recv(timeout=20))["op"] == "serverInfo"
        run.signal_group(signal.SIGINT)  # what a terminal's Ctrl-C does
        code = run.wait(30.0)
    assert code == 130, run.output()[-3000:]
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
    summary = json.loads(summary_path.read_text())
    assert summary["stop_reason"] == "interrupted" and check_summary(summary) == []
    assert summary["sim_time_s"] >= 20.0


#: Where a run's summary goes to test that a path with YAML syntax in it reaches the
#: evaluator whole (" #" started a comment, ": " made every node fail to parse it).
YAML_LIKE_FOLDER = 'run #1: a"b\\c'


def _evaluator_pid(domain: str) -> int:
    pids = processes_in_domain(r"em_exploration_ros\.nodes\.evaluator_node", domain)
    assert len(pids) == 1, pids
    return pids[0]


def test_a_hangup_stops_every_process_and_keeps_the_summary(tmp_path):
    """A closed terminal or a lost SSH connection (SIGHUP to the foreground group): handled as
    SIGTERM, with its own exit code 129. run_team.sh used to die at once and leave every node
    (each in its own session) running for good. The summary's folder name is YAML syntax:
    it reaches the evaluator whole, quoted."""
    summary_path = tmp_path / YAML_LIKE_FOLDER / "summary.json"
    run, domain = start_team_run(tmp_path, "--planner", "NEAREST", "--map-size", "40",
                                 "--landmarks", "4", "--until-explored", "1",
                                 "--summary", str(summary_path))
    with run:
        run.wait_for_output("  explored ", RUN_TIMEOUT_S)
        run.signal_group(signal.SIGHUP)
        code = run.wait(30.0)
    assert code == 129, run.output()[-3000:]
    assert "stopping (hung up)" in run.output()
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
    summary = json.loads(summary_path.read_text())
    assert summary["stop_reason"] == "interrupted" and check_summary(summary) == []
    assert summary_path.with_name("summary_map.png").exists()
    assert not (tmp_path / "run").exists()  # where " #" cut the path short


def test_an_unexpected_end_of_the_script_stops_every_process(tmp_path):
    """Whatever ends run_team.sh other than the signals it handles (here SIGUSR1; an error of
    the script itself, such as an unbound variable, the same way) stops the nodes first. The
    nodes, each in its own session, used to run on for good."""
    run, domain = start_team_run(tmp_path, "--planner", "NEAREST", "--map-size", "40",
                                 "--landmarks", "4", "--until-explored", "1",
                                 "--summary", str(tmp_path / "summary.json"))
    with run:
        run.wait_for_output("  explored ", RUN_TIMEOUT_S)
        os.kill(run.pid, signal.SIGUSR1)
        code = run.wait(30.0)
    left_running = processes_in_domain(RUN_PROCESS_PATTERN, domain)
    for pid in left_running:  # without the guard, so that they do not outlive the test
        os.kill(pid, signal.SIGKILL)
    assert left_running == [], run.output()[-3000:]
    assert code == -signal.SIGUSR1
    assert "ended unexpectedly with nodes running; stopping them" in run.output()


def _shared_memory_ports(pid: int) -> set[str]:
    """The Fast DDS shared-memory port segments process ``pid`` has mapped (its own ports to
    listen on and its teammates' it writes to)."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    return set(re.findall(r"/dev/shm/(fastrtps_port\d+)$", maps, re.MULTILINE))


def _run_with_the_evaluator_signalled(tmp_path, signum: int, *options: str,
                                      timeout_s: float = 60.0,
                                      ports: dict[str, set[str]] | None = None,
                                      restart_port: str = "") -> tuple[int, str, str]:
    """A small NEAREST run (``options``; by default seed 0 until every robot finished) whose
    evaluator gets ``signum`` once progress shows; the exit code, output and ROS domain of
    run_team.sh. ``ports``, if given, gets the shared-memory ports the evaluator had mapped
    before the signal (``before``) and those a restarted evaluator maps once it maps
    ``restart_port``, or when the run ends first (``after``; ``_shared_memory_ports``)."""
    run, domain = start_team_run(tmp_path, "--planner", "NEAREST", "--map-size", "40",
                                 "--landmarks", "4", *(options or ("--until-explored", "1")),
                                 "--summary", str(tmp_path / "summary.json"))

    def signal_the_evaluator() -> None:
        run.wait_for_output("  explored ", RUN_TIMEOUT_S)
        evaluator = _evaluator_pid(domain)
        if ports is not None:
            ports["before"] = _shared_memory_ports(evaluator)
        os.kill(evaluator, signum)
        if ports is not None:
            ports["after"] = set()
            deadline = time.monotonic() + RUN_TIMEOUT_S
            while (restart_port not in ports["after"] and run.running()
                   and time.monotonic() < deadline):
                pids = processes_in_domain(r"em_exploration_ros\.nodes\.evaluator_node", domain)
                ports["after"] = set().union(*(_shared_memory_ports(p) for p in pids
                                               if p != evaluator))
                time.sleep(0.1)

    code = finish_team_run(run, timeout_s, meanwhile=signal_the_evaluator)
    return code, run.output(), domain


def test_a_stopped_evaluator_fails_the_run_once_the_world_has_stepped_over(tmp_path,
                                                                          monkeypatch):
    """The evaluator SIGSTOPped (or wedged): the world steps over when the robots finish, and
    nothing else ends the run; run_team.sh used to wait for the evaluator for ever. It gives
    the evaluator EM_EVALUATOR_END_GRACE_S (60 s; 3 s here) after the world stepped over."""
    monkeypatch.setenv("EM_EVALUATOR_END_GRACE_S", "3")
    code, output, domain = _run_with_the_evaluator_signalled(tmp_path, signal.SIGSTOP)
    assert code == 1, output[-3000:]
    assert ("error: the evaluator has not ended the run 3 s after the world stepped over "
            "(it is stopped (SIGSTOP or Ctrl-Z)") in output
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []


def test_a_killed_evaluator_stops_the_run_and_keeps_the_summary_so_far(tmp_path):
    """The evaluator SIGKILLed: an error line naming it and the signal, not its raw status
    137 without a word; the team is stopped and exit code 7 (issue 40, point 3: it used to
    be 1 with no summary at all). The summary so far, kept by the evaluator while the run
    went on, is left: valid, with the run up to the evaluator's last evaluations."""
    code, output, domain = _run_with_the_evaluator_signalled(tmp_path, signal.SIGKILL)
    assert code == 7, output[-3000:]
    assert ("error: the evaluator exited with code 137 (signal KILL) (see "
            in output), output[-3000:]
    assert "; the team is stopped and the summary so far kept" in output
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert check_summary(summary) == []
    assert summary["stop_reason"] == (f"evaluator lost: the run so far, to t = "
                                      f"{summary['sim_time_s']:g} s (the evaluator ended "
                                      f"before the run)")
    assert summary["sim_time_s"] > 0.0 and summary["history"]
    assert summary["history"][-1]["explored_ratio"] == summary["explored_ratio"] > 0.0
    assert f"summary: {tmp_path / 'summary.json'}" in output


def test_a_killed_evaluator_is_restarted_with_respawn_and_writes_the_clean_runs_summary(
        tmp_path):
    """The evaluator SIGKILLed with --respawn (issue 40, point 3): run_team.sh restarts it,
    and the new process reads the run back (the world's ground truth from step 0, the robots'
    estimates and answers from their transient-local writers, their streams by asking for
    them): the run ends as the clean one, exit 0, and its summary is em-sim's for the same
    mission at every level, as the end-to-end run's is (targets, decisions, the targets given
    up and the meetings the robots reported in their answers, some while no evaluator ran,
    the metrics)."""
    # The restart's own shared-memory port: Fast DDS's for participant 31 (the first id a
    # process takes instead of a dead one's, nodes/participant_id.py) in the run's domain.
    ports: dict[str, set[str]] = {}
    domain_id = int(os.environ["ROS_DOMAIN_ID"])
    own_port = shared_memory_port_file(domain_id, 31)
    code, output, domain = _run_with_the_evaluator_signalled(
        tmp_path, signal.SIGKILL, "--seed", "2", "--until-explored", "0.85",
        "--max-sim-time", "600", "--params", _short_progress_window(tmp_path), "--respawn",
        timeout_s=RUN_TIMEOUT_S, ports=ports, restart_port=own_port)
    assert domain == str(domain_id)
    assert code == 0, output[-3000:]
    assert ("warning: the evaluator exited with code 137 (signal KILL); restarting it "
            "(respawn 1)") in output
    # The restart listens on a shared-memory port of its own: on its predecessor's, the
    # others' writers could keep writing into the dead one's.
    assert re.search(r"participant id 31 instead of \d+: a process that died held id \d+ ",
                     (tmp_path / "logs" / "evaluator.log").read_text())
    assert own_port in ports["after"] and own_port not in ports["before"], ports
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert check_summary(summary) == []
    reference = _em_sim_summary(2, 0.85)
    assert summary["stop_reason"] == reference["stop_reason"]
    assert [r["targets"] for r in summary["robots"]] == [r["targets"] for r in
                                                         reference["robots"]]
    assert [(r["given_up"], r["blocked_s"]) for r in summary["robots"]] == [
        (r["given_up"], r["blocked_s"]) for r in reference["robots"]]
    assert summary["distance_m"] == pytest.approx(reference["distance_m"], abs=1e-6)
    assert len(summary["history"]) == len(reference["history"])
    assert_same_summary(summary, reference)
