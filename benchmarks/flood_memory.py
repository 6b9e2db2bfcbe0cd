"""Memory of every process of a team run under a flood of its subscribed topics.

Runs the lockstep team twice with ``./launch_scripts/run_team.sh`` (default: 3 robots, the
default world, explored to 0.95 or 600 simulated seconds, so that the flooded run goes on
after the flood), once clean and once with em-fuzz flooding ``--topics`` (default: every
topic the nodes subscribe to; or some, e.g. /team/update_requests) at ``--rate`` messages
per second for ``--flood`` wall seconds from simulated time ``--flood-at`` on. VmRSS of the
world, the evaluator and each robot (``/proc/PID/status``) is read every ``POLL_S``; printed
per process: the clean run's RSS at the flood's start, at its peak and at the run's end
(last reading before the process exits), the flooded run's, and the difference at the end;
and the simulated time of each run at the flood's start and end (wall seconds from ``go``):
how far the team stepped on under the flood (read from the evaluator's progress lines, one
every 20 simulated seconds; an evaluator that lags shows less). em-fuzz speaks with the
run's id, which it learns from the run's messages (its report's ``run_id_source``).

Usage: ``.venv/bin/python benchmarks/flood_memory.py [--topics all | TOPIC ...]
[--rate 5000] [--flood 60] [--flood-at 20] [--domain-id 71] [-- run_team.sh options]``
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from team_cpu import node_name, stop

REPO = Path(__file__).resolve().parents[1]
POLL_S = 0.5
#: The team and its mission unless run_team.sh options follow ``--``.
DEFAULT_TEAM = ("--robots", "3", "--until-explored", "0.95", "--max-sim-time", "600")
#: Wall seconds a run may last at most.
RUN_TIMEOUT_S = 900.0


def rss_mb(pid: int) -> float | None:
    """VmRSS of a process [MB] (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def run_processes(domain_id: int) -> dict[int, str]:
    """{PID: world / evaluator / robot K} of the node processes in ROS domain ``domain_id``."""
    marker = f"ROS_DOMAIN_ID={domain_id}".encode()
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        name = node_name(int(entry))
        try:
            environment = Path(f"/proc/{entry}/environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if name is not None and marker in environment:
            found[int(entry)] = name
    return found


@dataclass
class Figures:
    """One run's VmRSS per process [MB]: at the flood's start, peak from then on, last."""

    start: dict[str, float] = field(default_factory=dict)
    peak: dict[str, float] = field(default_factory=dict)
    end: dict[str, float] = field(default_factory=dict)
    #: Simulated time [s] at the flood's start and when it ended (its wall length later).
    sim_at_flood: tuple[float, float] = (0.0, 0.0)

    def sample(self, processes: dict[int, str], flooding: bool) -> None:
        """Read every process's RSS now (``flooding``: from the flood's start on)."""
        for pid, name in processes.items():
            rss = rss_mb(pid)
            if rss is None:
                continue
            self.end[name] = rss
            if flooding:
                self.start.setdefault(name, rss)
                self.peak[name] = max(rss, self.peak.get(name, 0.0))


def sim_time_s(output: str) -> float:
    """The latest simulated time run_team.sh's progress lines show [s] (0 before any)."""
    times = re.findall(r"t=\s*([0-9.]+) s", output)
    return float(times[-1]) if times else 0.0


def one_run(out: Path, options: argparse.Namespace, flood: bool) -> tuple[Figures, dict]:
    """A team run, flooded or clean; its figures and em-fuzz's report (empty when clean)."""
    out.mkdir(parents=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(options.domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    log = open(out / "run_team.out", "wb")
    team = subprocess.Popen(["bash", str(REPO / "launch_scripts" / "run_team.sh"),
                             *options.team, "--summary", str(out / "summary.json"),
                             "--domain-id", str(options.domain_id)],
                            stdout=log, stderr=subprocess.STDOUT, env=env,
                            start_new_session=True)
    go = out / "fuzz.go"
    fuzzer = subprocess.Popen(
        [sys.executable, "-m", "em_exploration_ros.tools.fuzz",
         *([] if options.topics == ["all"] else ["--topics", *options.topics]),
         "--rate", str(options.rate), "--duration", str(options.flood), "--start-file",
         str(go), "--start-timeout", str(RUN_TIMEOUT_S), "--report", str(out / "fuzz.json")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
        start_new_session=True) if flood else None
    figures, processes = Figures(), {}
    started = time.monotonic()
    flood_started = flood_start_s = None
    try:
        while team.poll() is None and time.monotonic() - started < RUN_TIMEOUT_S:
            processes.update(run_processes(options.domain_id))
            now_s = sim_time_s((out / "run_team.out").read_text(errors="replace"))
            if flood_started is None and now_s >= options.flood_at:
                flood_started, flood_start_s = time.monotonic(), now_s
                go.touch()
            elif (flood_started is not None and figures.sim_at_flood == (0.0, 0.0)
                  and time.monotonic() - flood_started >= options.flood):
                figures.sim_at_flood = (flood_start_s, now_s)
            figures.sample(processes, flood_started is not None)
            time.sleep(POLL_S)
    finally:
        stop(team, list(processes))
        if fuzzer is not None:
            stop(fuzzer, [])
        log.close()
    report = json.loads((out / "fuzz.json").read_text()) if flood else {}
    return figures, report


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--topics", nargs="+", default=["all"],
                        help="em-fuzz --topics, or all (default)")
    parser.add_argument("--rate", type=float, default=5000.0, help="em-fuzz --rate")
    parser.add_argument("--flood", type=float, default=60.0, help="wall seconds of flood")
    parser.add_argument("--flood-at", type=float, default=20.0,
                        help="simulated time the flood starts at [s]")
    parser.add_argument("--domain-id", type=int, default=71)
    parser.add_argument("--flooded-only", action="store_true", help="skip the clean run")
    parser.add_argument("team", nargs="*", help="run_team.sh options (after --)")
    options = parser.parse_args()
    options.team = options.team or list(DEFAULT_TEAM)
    runs = Path(tempfile.mkdtemp(prefix="flood_memory_"))
    print(f"run_team.sh {' '.join(options.team)}; em-fuzz --topics {' '.join(options.topics)}"
          f" --rate {options.rate:g} --duration {options.flood:g} from t = {options.flood_at:g} s; "
          f"runs in {runs}", flush=True)
    clean = (Figures() if options.flooded_only
             else one_run(runs / "clean", options, flood=False)[0])
    flooded, report = one_run(runs / "flooded", options, flood=True)
    sent = report.get("messages", 0)
    print(f"em-fuzz sent {sent} messages in {options.flood:g} s "
          f"({sent / options.flood:.0f} per second) with run_id {report.get('run_id')} "
          f"(from {report.get('run_id_source')})")
    for name, run in (("clean", clean), ("flooded", flooded)):
        print(f"{name}: simulated time t = {run.sim_at_flood[0]:.0f} s at the flood's start, "
              f"{run.sim_at_flood[1]:.0f} s {options.flood:g} wall seconds later")
    print("VmRSS [MB]     clean: start  peak   end | flooded: start  peak   end | end - clean")
    for name in sorted(flooded.end):
        print(f"{name:12s}        {clean.start.get(name, 0):6.0f} {clean.peak.get(name, 0):5.0f}"
              f" {clean.end.get(name, 0):5.0f} |          {flooded.start.get(name, 0):6.0f} "
              f"{flooded.peak.get(name, 0):5.0f} {flooded.end.get(name, 0):5.0f} | "
              f"{flooded.end[name] - clean.end.get(name, 0):+6.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
