"""A running lockstep team under a fuzz attack (issue 11, point 3).

A separate process (em-fuzz, em_exploration_ros/tools/fuzz.py) reads the ROS graph for
every topic the world, the robots and the evaluator subscribe to and, for a bounded time,
publishes well-formed messages with extreme values on all of them, with the run's id that
it learned from the run's messages (another run's id is one of the extreme values) (NaN, infinities,
largest or negative ids, steps, sequence numbers and stamps, huge arrays, negative and
backwards /clock, wrong frame_ids) while a seeded lockstep team explores a small map.
Then: no process exited, the summary (targets, every metric sample, the stop step) equals
that of the same run without the attack, and no process's memory grew by more than 50 MB
over that run's (peak VmRSS).
"""
from __future__ import annotations

import json
import random
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from ros_process import (RUN_PROCESS_PATTERN, NodeProcess, ProcessSet, processes_in_domain,
                         start_team_run)

from em_exploration_ros.tools import fuzz

#: Bound of one team run [s] and of the attack [s], and its rate [messages/s].
RUN_TIMEOUT_S = 180.0
FUZZ_S = 10.0
FUZZ_RATE_HZ = 150.0
#: Memory a process may gain under the attack over the same run without it [MB].
RSS_MARGIN_MB = 50.0
TEAM = ("--robots", "3", "--map-size", "60", "--landmarks", "6", "--seed", "2",
        "--planner", "CE", "--until-explored", "0.9", "--max-sim-time", "600")
RUN_PROCESSES = {"world", "evaluator", "robot_0", "robot_1", "robot_2"}
ATTACKED_TOPICS = {"/clock", "/mission/anchor_pose", "/team/update_requests",
                   "/world/landmarks"} | {
    f"/robot_{r}/{name}" for r in range(3)
    for name in ("sonar", "odom", "motion_command", "team/updates", "estimated_path",
                 "landmarks", "estimated_pose")} | {f"/world/ground_truth/robot_{r}"
                                                    for r in range(3)}


def process_name(pid: int) -> str | None:
    """world / evaluator / robot_<i> for a run's process (None if it is gone)."""
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
    except OSError:
        return None
    module = next((w for w in words if w.startswith("em_exploration_ros.")), "")
    if module.endswith("robot_node"):
        robot = next(w for w in words if w.startswith("robot_id:="))
        return f"robot_{robot.split(':=')[1]}"
    return module.rsplit(".", 1)[-1].removesuffix("_node") or None


def rss_mb(pid: int) -> float | None:
    """VmRSS of a process [MB] (None if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class MemoryWatch:
    """Peak VmRSS of each process of a run, sampled while it runs."""

    def __init__(self, domain: str) -> None:
        self.domain = domain
        self.peak_mb: dict[str, float] = {}
        self.pids: dict[str, int] = {}

    def sample(self) -> dict[str, float]:
        """Sample every process of the run now; returns {name: RSS [MB]} of this sample."""
        now = {}
        for pid in processes_in_domain(RUN_PROCESS_PATTERN, self.domain):
            name, rss = process_name(pid), rss_mb(pid)
            if name not in RUN_PROCESSES or rss is None:
                continue  # gone, or the fuzzer
            self.pids.setdefault(name, pid)
            now[name] = rss
            self.peak_mb[name] = max(rss, self.peak_mb.get(name, 0.0))
        return now


def run(tmp_path: Path, name: str, attack: bool, beside: ProcessSet | None = None) -> dict:
    """One team run, with or without the attack (``beside`` another one: ``start_team_run``);
    what the test asserts on."""
    summary_path = tmp_path / name / "summary.json"
    team, domain = start_team_run(tmp_path / name, *TEAM, "--summary", str(summary_path),
                                  beside=beside)
    memory = MemoryWatch(domain)
    report, after_mb = None, {}
    with team:
        if attack:
            # Mid-run, so that the team runs before the attack (it may end during it). The
            # fuzzer starts with the team and reads the graph until the go file appears: a
            # fuzzer started at t = 20 s needed its own start-up and graph discovery (3-4 s),
            # and the faster team had finished by then.
            report_path, go_file = tmp_path / name / "fuzz.json", tmp_path / name / "fuzz.go"
            fuzzer = NodeProcess([sys.executable, "-m", "em_exploration_ros.tools.fuzz",
                                  "--duration", str(FUZZ_S), "--rate", str(FUZZ_RATE_HZ),
                                  "--seed", "1", "--report", str(report_path),
                                  "--start-file", str(go_file),
                                  "--start-timeout", str(RUN_TIMEOUT_S)],
                                 tmp_path / name / "fuzz.out")
            with fuzzer:
                started = time.monotonic()
                while "t=   20.0 s" not in team.output() and team.running():
                    assert time.monotonic() - started < RUN_TIMEOUT_S, team.output()[-3000:]
                    memory.sample()
                    time.sleep(0.2)
                go_file.touch()
                while fuzzer.running():
                    memory.sample()
                    time.sleep(0.2)
                assert fuzzer.wait(10.0) == 0, fuzzer.output()[-3000:]
            after_mb = memory.sample()
            report = json.loads(report_path.read_text())
        deadline = time.monotonic() + RUN_TIMEOUT_S
        while team.running() and time.monotonic() < deadline:
            memory.sample()
            time.sleep(0.2)
        code = team.wait(10.0)
    output = team.output()
    # run_team.sh reports any process that exits before the evaluator ends the run (and
    # fails unless it is a robot): a process that the attack ended shows here, even when the
    # team finished during the attack.
    assert code == 0, output[-3000:]
    assert "exited with code" not in output and "exited early" not in output, output[-3000:]
    logs = {p.stem: p.read_text() for p in (summary_path.parent / "logs").glob("*.log")}
    return dict(summary=json.loads(summary_path.read_text()), peak_mb=memory.peak_mb,
                after_mb=after_mb, report=report, logs=logs)


def test_fuzzed_team_keeps_running_its_result_and_its_memory(tmp_path):
    # The clean run goes on beside the attacked one, in a domain of its own (stopped at
    # once if the attacked one fails).
    with ThreadPoolExecutor(max_workers=1) as thread, ProcessSet() as beside:
        clean_run = thread.submit(run, tmp_path, "clean", attack=False, beside=beside)
        attacked = run(tmp_path, "attacked", attack=True)
        clean = clean_run.result()

    report = attacked["report"]
    assert ATTACKED_TOPICS <= set(report["topics"]), sorted(report["topics"])
    subscribers = set().union(*(t["subscribers"] for t in report["topics"].values()))
    assert {"/em_world", "/em_evaluator", "/robot_0/em_robot", "/robot_1/em_robot",
            "/robot_2/em_robot"} <= subscribers
    assert all(report["topics"][t]["sent"] > 0 for t in ATTACKED_TOPICS)
    # em-fuzz learned the run's id from the run's messages, so that most of its messages
    # reach the checks past the run's (another run's id is one fault among the others).
    assert report["run_id"] is not None and report["run_id_source"].startswith("/")
    for name in RUN_PROCESSES:
        assert "dropped a message on" in attacked["logs"][name], name
        assert "Traceback" not in attacked["logs"][name], name
        assert any("dropped a message on" in line and "another run" not in line
                   for line in attacked["logs"][name].splitlines()), name

    assert ([r["targets"] for r in attacked["summary"]["robots"]]
            == [r["targets"] for r in clean["summary"]["robots"]])
    # The evaluator reads each robot's estimates as of the evaluated step whatever the
    # flood does to the order in which messages reach it: every sample equals the clean one.
    for key in ("explored_ratio", "distance_m", "decisions", "loc_rmse_m", "landmark_rmse_m",
                "sim_time_s", "stop_reason", "history"):
        assert attacked["summary"][key] == clean["summary"][key], key

    assert set(attacked["peak_mb"]) == set(clean["peak_mb"]) == RUN_PROCESSES
    print(f"\nfuzz: {report['messages']} messages on {len(report['topics'])} topics in "
          f"{FUZZ_S:g} s")
    for name in sorted(clean["peak_mb"]):
        print(f"{name}: peak RSS {clean['peak_mb'][name]:.0f} MB without, "
              f"{attacked['peak_mb'][name]:.0f} MB with the attack "
              f"({attacked['after_mb'].get(name, float('nan')):.0f} MB right after it)")
    for name, peak in attacked["peak_mb"].items():
        assert peak <= clean["peak_mb"][name] + RSS_MARGIN_MB, (name, peak, clean["peak_mb"])


def test_a_start_file_that_never_appears_ends_the_fuzzer_with_code_1(tmp_path):
    fuzzer = NodeProcess([sys.executable, "-m", "em_exploration_ros.tools.fuzz",
                          "--duration", "1", "--start-file", str(tmp_path / "never"),
                          "--start-timeout", "3"], tmp_path / "fuzz.out")
    with fuzzer:
        assert fuzzer.wait(RUN_TIMEOUT_S) == 1
    assert "did not appear within 3 s; nothing sent" in fuzzer.output()


def test_sigterm_ends_the_attack_like_ctrl_c(tmp_path):
    start = tmp_path / "start"
    start.touch()  # attack at once, no settling pause
    fuzzer = NodeProcess([sys.executable, "-m", "em_exploration_ros.tools.fuzz",
                          "--duration", "60", "--nodes", "no_such_node", "--start-file",
                          str(start)], tmp_path / "fuzz.out")
    with fuzzer:
        time.sleep(1.5)  # rclpy initialized: its handler turns SIGTERM into a shutdown
        fuzzer.signal_group(signal.SIGTERM)
        assert fuzzer.wait(10.0) == 0, fuzzer.output()
    assert "Traceback" not in fuzzer.output()
    assert json.loads(fuzzer.output().strip().splitlines()[-1])["messages"] == 0


@pytest.mark.parametrize("args, phrase", [
    (["--duration", "inf"], "--duration must be a positive finite number, got inf"),
    (["--rate", "nan"], "--rate must be a positive finite number, got nan"),
    (["--start-timeout", "nan"], "--start-timeout must be a positive finite number"),
    (["--report", "/nonexistent/x.json"], "the folder /nonexistent does not exist"),
    (["--report", "."], "is a directory"),
    (["--run-id", "-1"], "--run-id must be in 0..2^64 - 1, got -1")])
def test_bad_arguments_are_refused_before_the_attack(args, phrase, capsys):
    with pytest.raises(SystemExit) as stopped:
        fuzz.main(args)
    assert stopped.value.code == 2
    assert phrase in capsys.readouterr().err


def test_messages_carry_the_runs_id_unless_it_is_their_extreme_field():
    from em_exploration_msgs.msg import SonarScan, TeamUpdate

    messages = fuzz.ExtremeMessages(random.Random(3), run_id=123456789)
    ids = [messages.make(kind).run_id for kind in (TeamUpdate, SonarScan) for _ in range(60)]
    assert set(ids) == {123456789, 2**64 - 1, 2**63}
    assert ids.count(123456789) > 0.7 * len(ids)  # most reach the checks past the run's
