"""Kill robots of a ``--respawn`` team at random moments; print how the run ended.

Runs ``./launch_scripts/run_team.sh --respawn --seed SEED --summary DIR/summary.json
--domain-id ID [run_team.sh options]`` and, from ``--first-kill`` wall seconds on, sends a
robot process SIGKILL (``--signal STOP``: SIGSTOP, a wedged process, which run_team.sh
restarts once the world reports the robot lost) ``--kills`` times, each after a pause drawn
uniformly from ``--pause`` seconds and chosen at random among the robots running then (a
``random.Random(SEED)`` draws both, so the kill times and targets repeat; what the robots
were doing at those wall times does not). Robot processes are the run's descendants
(``team_cpu.sample_descendants``). Prints the kills, run_team.sh's exit code, the summary's
stop reason, explored ratio and RMSEs, how many records each restarted robot recovered, and
how often the logs say a step waited for team data that never came ("never reached the
relay", "still missing after").

Usage: ``.venv/bin/python benchmarks/restart_chaos.py [--seed 1] [--kills 3] [--out DIR]
[-- run_team.sh options]``, e.g. ``-- --comm-range 30 --comm-loss 0.2``.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from team_cpu import sample_descendants, stop

REPO = Path(__file__).resolve().parent.parent
#: Wall seconds a run may take before it is stopped.
RUN_LIMIT_S = 600.0
POLL_S = 0.2


def robot_processes(root: int, names: dict[int, str]) -> dict[int, int]:
    """Robot id -> PID of every robot process running under ``root`` now."""
    cpu_s: dict[int, float] = {}
    sample_descendants(root, names, cpu_s)
    return {int(name.split()[1]): pid for pid, name in names.items()
            if pid in cpu_s and name.startswith("robot ") and name.split()[1].isdigit()}


def metre(value: float | None) -> str:
    """An RMSE as the summary gives it: None (nothing to compare yet) as n/a."""
    return "n/a" if value is None else f"{value:.3f} m"


def summary_line(summary: dict) -> str:
    """Explored ratio, RMSEs and simulated time of a run's summary.json data."""
    return (f"explored {summary['explored_ratio']:.3f}, loc RMSE {metre(summary['loc_rmse_m'])}, "
            f"landmark RMSE {metre(summary['landmark_rmse_m'])}, sim {summary['sim_time_s']} s")


class KillSchedule:
    """Seeded signals to the robot processes of a run: the first once ``first_kill_s`` plus
    a pause drawn from ``pause`` (wall seconds) have passed, each next one a new pause later,
    ``count`` in all, each to a robot drawn among those running then (``random.Random(seed)``
    draws pauses and robots). ``kills``: (elapsed wall s, robot) of the signals sent."""

    def __init__(self, seed: int, count: int, first_kill_s: float, pause: tuple[float, float],
                 signal_name: str) -> None:
        self._draws = random.Random(seed)
        self._count = count
        self._pause = pause
        self._signal = getattr(signal, f"SIG{signal_name}")
        self.next_kill_s = first_kill_s + self._draws.uniform(*pause)
        self.kills: list[tuple[float, int]] = []

    def poll(self, root: int, names: dict[int, str], elapsed_s: float) -> None:
        """Signal a robot under ``root`` if one is due at ``elapsed_s`` (``names`` as
        :func:`robot_processes` keeps it)."""
        if len(self.kills) >= self._count or elapsed_s < self.next_kill_s:
            return
        robots = robot_processes(root, names)
        if robots:
            robot = self._draws.choice(sorted(robots))
            os.kill(robots[robot], self._signal)
            self.kills.append((round(elapsed_s, 1), robot))
        self.next_kill_s = elapsed_s + self._draws.uniform(*self._pause)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1, help="mission seed and kill draws")
    parser.add_argument("--kills", type=int, default=3, help="robot processes to kill")
    parser.add_argument("--first-kill", type=float, default=8.0, metavar="S",
                        help="wall seconds after the start before the first pause")
    parser.add_argument("--pause", type=float, nargs=2, default=(2.0, 7.0), metavar=("MIN", "MAX"),
                        help="range of the wall seconds between two kills")
    parser.add_argument("--signal", choices=("KILL", "STOP"), default="KILL",
                        help="what each robot gets: SIGKILL (dead) or SIGSTOP (wedged)")
    parser.add_argument("--domain-id", type=int, default=70)
    parser.add_argument("--out", type=Path, default=None, help="run directory (default: new)")
    parser.add_argument("team_args", nargs="*", help="run_team.sh options (after --)")
    options = parser.parse_args()
    out = options.out or Path(tempfile.mkdtemp(prefix="restart_chaos_"))
    out.mkdir(parents=True, exist_ok=True)
    command = [str(REPO / "launch_scripts" / "run_team.sh"), "--respawn", "--seed",
               str(options.seed), "--summary", str(out / "summary.json"), "--domain-id",
               str(options.domain_id), *options.team_args]
    env = dict(os.environ, ROS_DOMAIN_ID=str(options.domain_id))
    names: dict[int, str] = {}
    schedule = KillSchedule(options.seed, options.kills, options.first_kill, options.pause,
                            options.signal)
    kills = schedule.kills
    started = time.monotonic()
    with open(out / "run_team.out", "wb") as output:
        run = subprocess.Popen(command, cwd=REPO, env=env, stdout=output,
                               stderr=subprocess.STDOUT, start_new_session=True)
        try:
            while run.poll() is None and time.monotonic() - started < RUN_LIMIT_S:
                schedule.poll(run.pid, names, time.monotonic() - started)
                time.sleep(POLL_S)
        finally:
            stop(run, list(names))
    logs = {path.name: path.read_text(errors="replace")
            for path in sorted((out / "logs").glob("*.log"))}
    recovered = [int(count) for text in logs.values()
                 for count in re.findall(r"rejoined: recovered (\d+) records", text)]
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    print(f"kills (wall s, robot): {kills}")
    print(f"run_team.sh exit code {run.returncode} after {time.monotonic() - started:.0f} s; "
          f"stop: {summary.get('stop_reason')}")
    if summary:
        print(summary_line(summary))
    print(f"records recovered by each restart: {recovered}")
    print(f"waits for team data that never came: "
          f"{sum(t.count('never reached the relay') for t in logs.values())} (world), "
          f"{sum(t.count('still missing after') for t in logs.values())} (robots); "
          f"tracebacks: {sum(t.count('Traceback') for t in logs.values())}")
    print(f"run directory: {out}")


if __name__ == "__main__":
    main()
