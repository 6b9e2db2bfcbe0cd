"""Memory stays bounded under a flood (issue 40, point 6).

em-fuzz floods the team updates of every robot (read by the robots and the evaluator; em-fuzz's
are up to 320 kB, with the run's id, which it learns from the run's messages) at the highest
rate it reaches, mid-run, for ``FLOOD_S`` wall seconds; the team runs on after it. From
``RUN_ON_AFTER_S`` simulated seconds after the flood to its exit, every process's VmRSS (the
median of its readings: the evaluator's end, where it draws its pictures, moved a single last
reading by up to 24 MB either way, in clean and flooded runs alike) is within
``END_MARGIN_MB`` of the same run's without the flood: every reader's and writer's queue is
bounded (nodes/qos.py), the middleware frees each sample's buffer once it is taken
(config/fastdds_profiles.xml), glibc gives the freed memory back (launch_scripts/_common.sh;
nodes/memory_return.py trims every second: every 10 s, the evaluator of a run that ended a
few seconds after the flood sometimes kept up to 40 MB it had freed), and a team update is
read only once its serialized head passed (``input_guard.screened_team_updates``: before,
the robots deserialized every flooded update, 30-180 ms for a large one, and the team stood
still under the flood). The targets may differ: a flood this fast pushes teammates' records
out of the bounded queues, and one asked for again can come after the barrier's timeout. The
flood of every other topic, for 60 s, is benchmarks/flood_memory.py's (docs/robustness.md,
"Memory and stepping under a flood").
"""
from __future__ import annotations

import json
import re
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ros_process import NodeProcess, ProcessSet, start_team_run
from test_fuzz import RUN_PROCESSES, MemoryWatch

#: Bound of one team run [s]; the flood's length [s] and rate [messages/s] (more than em-fuzz
#: reaches on this machine: it sends as fast as it can).
RUN_TIMEOUT_S = 240.0
FLOOD_S = 6.0
FLOOD_RATE_HZ = 5000.0
FLOODED_TOPICS = [f"/robot_{r}/team/updates" for r in range(3)]
#: Memory a process may hold after the flood over the same run without the flood [MB].
END_MARGIN_MB = 30.0
#: Simulated seconds the flooded team must run on after the flood, for the memory to come back;
#: each process's memory is compared from then on.
RUN_ON_AFTER_S = 20.0
TEAM = ("--robots", "3", "--map-size", "60", "--landmarks", "6", "--seed", "2",
        "--planner", "CE", "--until-explored", "0.9", "--max-sim-time", "600")


def sim_time_s(output: str) -> float:
    """The latest simulated time of the run's progress lines [s] (0 before any)."""
    times = re.findall(r"t=\s*([0-9.]+) s", output)
    return float(times[-1]) if times else 0.0


def run(tmp_path: Path, name: str, flood: bool, beside: ProcessSet | None = None) -> dict:
    """One team run, flooded or not (``beside`` another one: ``start_team_run``): every
    reading of the processes' VmRSS [MB] with the simulated time of the run then [s], each
    process's last one before it exited, the fuzzer's report and the simulated times the
    flood ended and the run ended at."""
    summary_path = tmp_path / name / "summary.json"
    team, domain = start_team_run(tmp_path / name, *TEAM, "--summary", str(summary_path),
                                  beside=beside)
    memory, last_mb, readings = MemoryWatch(domain), {}, []
    report, flood_end_s = None, 0.0

    def sample() -> None:
        now = memory.sample()
        readings.append((sim_time_s(team.output()), now))
        last_mb.update(now)
        time.sleep(0.2)

    with team:
        if flood:
            report_path, go_file = tmp_path / name / "fuzz.json", tmp_path / name / "fuzz.go"
            fuzzer = NodeProcess([sys.executable, "-m", "em_exploration_ros.tools.fuzz",
                                  "--topics", *FLOODED_TOPICS, "--duration", str(FLOOD_S),
                                  "--rate", str(FLOOD_RATE_HZ), "--seed", "1",
                                  "--report", str(report_path), "--start-file", str(go_file),
                                  "--start-timeout", str(RUN_TIMEOUT_S)],
                                 tmp_path / name / "fuzz.out")
            with fuzzer:
                started = time.monotonic()
                while sim_time_s(team.output()) < 20.0 and team.running():
                    assert time.monotonic() - started < RUN_TIMEOUT_S, team.output()[-3000:]
                    sample()
                go_file.touch()
                while fuzzer.running():
                    sample()
                assert fuzzer.wait(10.0) == 0, fuzzer.output()[-3000:]
            flood_end_s = sim_time_s(team.output())
            report = json.loads(report_path.read_text())
        deadline = time.monotonic() + RUN_TIMEOUT_S
        while team.running() and time.monotonic() < deadline:
            sample()
        code = team.wait(10.0)
    output = team.output()
    assert code == 0, output[-3000:]
    summary = json.loads(summary_path.read_text())
    return dict(last_mb=last_mb, readings=readings, report=report, flood_end_s=flood_end_s,
                end_s=summary["sim_time_s"])


def median_mb_from(result: dict, sim_time_s: float) -> dict[str, float]:
    """Each process's median VmRSS [MB] over the readings of a run from simulated time
    ``sim_time_s`` [s] on (none: the process is left out)."""
    series: dict[str, list[float]] = {}
    for reading_s, now in result["readings"]:
        if reading_s >= sim_time_s:
            for name, mb in now.items():
                series.setdefault(name, []).append(mb)
    return {name: statistics.median(values) for name, values in series.items()}


def test_memory_comes_back_after_a_flood_of_team_updates(tmp_path):
    # The clean run goes on beside the flooded one, in a domain of its own.
    with ThreadPoolExecutor(max_workers=1) as thread, ProcessSet() as beside:
        clean_run = thread.submit(run, tmp_path, "clean", flood=False, beside=beside)
        flooded = run(tmp_path, "flooded", flood=True)
        clean = clean_run.result()

    sent = flooded["report"]["messages"]
    assert set(flooded["report"]["topics"]) == set(FLOODED_TOPICS)
    assert flooded["report"]["run_id_source"].startswith("/")  # the run's id, learned
    assert flooded["end_s"] >= flooded["flood_end_s"] + RUN_ON_AFTER_S, (
        "the team ended too soon after the flood", flooded["flood_end_s"], flooded["end_s"])
    assert set(flooded["last_mb"]) == set(clean["last_mb"]) == RUN_PROCESSES
    after_s = flooded["flood_end_s"] + RUN_ON_AFTER_S
    clean_mb, flooded_mb = median_mb_from(clean, after_s), median_mb_from(flooded, after_s)
    assert set(flooded_mb) == set(clean_mb) == RUN_PROCESSES, (clean_mb, flooded_mb)
    print(f"\nflood: {sent} messages in {FLOOD_S:g} s on {', '.join(FLOODED_TOPICS)}, "
          f"ended at t = {flooded['flood_end_s']:.0f} s of {flooded['end_s']:.0f} s")
    for name in sorted(clean_mb):
        print(f"{name}: VmRSS from t = {after_s:.0f} s to the end (median) {clean_mb[name]:.0f} "
              f"MB clean, {flooded_mb[name]:.0f} MB flooded; the last reading "
              f"{clean['last_mb'][name]:.0f} and {flooded['last_mb'][name]:.0f} MB")
    for name, mb in flooded_mb.items():
        assert mb <= clean_mb[name] + END_MARGIN_MB, (name, mb, clean_mb)
