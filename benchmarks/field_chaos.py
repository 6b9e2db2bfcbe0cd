"""Field chaos: robots on separate hosts, lossy links, and robot processes killed mid-mission.

Composes two existing tools into the scenario of a deployed team:

- ``separate_hosts.HostNetwork`` puts the world/evaluator and every robot in a network
  namespace of its own, joined by veths to a bridge; ``run_team.sh --netns`` then runs DDS
  over UDPv4 only, with multicast discovery on that subnet;
- ``--loss N`` drops about 1 packet in N at both ends of every robot's veth
  (``HostNetwork``'s random-loss qdisc; world <-> robot packets cross one lossy hop,
  robot <-> robot packets two);
- as in ``restart_chaos.py`` (same seeded draws of times and robots), from ``--first-kill``
  wall seconds on (after the start, or with ``--after-first-step`` after the world's first
  step) a robot process gets SIGKILL (``--signal STOP``: SIGSTOP, a wedged
  process) ``--kills`` times, and ``run_team.sh --respawn`` must restart it and the robot
  must rejoin.

Prints the kills, run_team.sh's exit code, the summary's stop reason, explored ratio,
localization and landmark RMSE, every robot's final status, the measured drop ratio, then
the log lines that show trouble (tracebacks, errors, waits for data that never came, robots
lost, targets given up, processes gone from the graph), as ``file:line: text``.
Namespaces and processes are removed on every exit path (end, error, Ctrl-C, SIGTERM).

Needs root. Usage (one run per call)::

    sudo .venv/bin/python benchmarks/field_chaos.py [--seed 1] [--kills 3] [--signal KILL]
        [--loss 10] [--domain-id 90] [--out DIR] [-- run_team.sh options]

e.g. ``-- --map-size 60 --landmarks 6``. Exit code: run_team.sh's (2: cannot run here).
"""
from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from restart_chaos import POLL_S, RUN_LIMIT_S, KillSchedule, summary_line
from team_cpu import stop

from em_exploration_ros.tools.separate_hosts import RUN_TEAM, HostNetwork, cannot_run_reason

#: Log lines that show trouble (case-sensitive; "lost" as a word, not "lost_count").
TROUBLE = re.compile(r"Traceback|\bERROR\b|\berror\b|never reached|still missing|\blost\b|"
                     r"gave up|gone|not connected|wedged|deadlock|Segmentation|Abort|"
                     r"core dumped|exited with code|has not ended|stall")
#: The world's log line when it starts stepping (world_node._try_start).
FIRST_STEP = "all set after"
#: Trouble every kill brings, and lossy links too (counted, not printed): a liveliness lease
#: runs out, a restarted process is noticed.
EXPECTED = re.compile(r"liveliness lost \(process dead|lost: its process was restarted")
#: run_team.sh options this script sets itself.
OWN_OPTIONS = ("--respawn", "--netns", "--summary", "--domain-id", "--seed")


def run_with_kills(command: list[str], out: Path, options: argparse.Namespace
                   ) -> tuple[int, list[tuple[float, int]], float]:
    """run_team.sh with robots killed as restart_chaos.py does: (exit code, kills, wall s).
    Ctrl-C or SIGTERM stops the run early (as does ``--limit``); it is reported all the same."""
    names: dict[int, str] = {}
    schedule = KillSchedule(options.seed, options.kills, options.first_kill, options.pause,
                            options.signal)
    started = time.monotonic()
    world_log = out / "logs" / "world.log"
    with open(out / "run_team.out", "wb") as output:
        run = subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            clock_from = None if options.after_first_step else started
            while run.poll() is None and time.monotonic() - started < options.limit:
                elapsed = time.monotonic() - started
                if clock_from is None:  # the kill clock starts with the world's first step
                    if world_log.exists() and FIRST_STEP in world_log.read_text(errors="replace"):
                        clock_from = time.monotonic()
                        schedule.next_kill_s += clock_from - started
                else:
                    schedule.poll(run.pid, names, elapsed)
                time.sleep(POLL_S)
        except (KeyboardInterrupt, SystemExit):  # SystemExit: SIGTERM (main)
            print("field_chaos: interrupted; stopping the run", file=sys.stderr)
        finally:
            stop(run, list(names))
    return run.returncode, schedule.kills, time.monotonic() - started


def outcome(out: Path, max_lines: int) -> list[str]:
    """The summary's stop reason, explored ratio, RMSEs and robots, then the trouble lines."""
    path = out / "summary.json"
    summary = json.loads(path.read_text()) if path.exists() else {}
    lines = [f"stop: {summary.get('stop_reason')}"]
    if summary:
        lines += [summary_line(summary),
                  "robots at the end: " + ", ".join(
                      f"{r['id']} {r.get('status')} ({r['decisions']} decisions, "
                      f"{r['distance_m']:.0f} m)" for r in summary["robots"])]
    return lines + [f"  {line}" for line in trouble_lines(out, max_lines)]


def trouble_lines(out: Path, limit: int) -> list[str]:
    """``file:line: text`` of the lines of run_team.out (its own, not the evaluator's log it
    echoes) and logs/*.log that match TROUBLE but not EXPECTED, at most ``limit`` per file;
    then how many EXPECTED lines there were."""
    found, expected = [], 0
    for path in [out / "run_team.out", *sorted((out / "logs").glob("*.log"))]:
        if not path.exists():
            continue
        hits = []
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if path.suffix == ".out" and line.startswith("["):
                continue
            if EXPECTED.search(line):
                expected += 1
            elif TROUBLE.search(line):
                hits.append(f"{path.relative_to(out)}:{number}: {line.strip()}")
        found += hits[:limit] + ([f"{path.relative_to(out)}: ... {len(hits) - limit} more"]
                                 if len(hits) > limit else [])
    return found + [f"({expected} lines of liveliness lost or of a restarted process not "
                    f"shown)"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1, help="mission seed and kill draws")
    parser.add_argument("--kills", type=int, default=3, help="robot processes to kill")
    parser.add_argument("--signal", choices=("KILL", "STOP"), default="KILL",
                        help="what each robot gets: SIGKILL (dead) or SIGSTOP (wedged)")
    parser.add_argument("--loss", type=int, default=0, metavar="N",
                        help="drop 1 packet in N on every robot's veth (0: no loss)")
    parser.add_argument("--first-kill", type=float, default=8.0, metavar="S",
                        help="wall seconds after the start before the first pause")
    parser.add_argument("--after-first-step", action="store_true",
                        help="count --first-kill from the world's first step, not from the "
                             "start (start-up takes long on a loaded machine)")
    parser.add_argument("--pause", type=float, nargs=2, default=(2.0, 7.0),
                        metavar=("MIN", "MAX"), help="range of wall seconds between two kills")
    parser.add_argument("--domain-id", type=int, default=90, help="ROS_DOMAIN_ID of the run")
    parser.add_argument("--limit", type=float, default=RUN_LIMIT_S,
                        help=f"wall seconds before the run is stopped (default {RUN_LIMIT_S:g})")
    parser.add_argument("--max-lines", type=int, default=12,
                        help="trouble lines printed per log file")
    parser.add_argument("--out", type=Path, help="run directory (default: a new temp one)")
    parser.add_argument("team_args", nargs="*", metavar="-- run_team.sh options")
    options = parser.parse_args()
    if any(arg.split("=", 1)[0] in OWN_OPTIONS for arg in options.team_args):
        parser.error(f"{', '.join(OWN_OPTIONS)} are set by this script")
    robots = argparse.ArgumentParser(add_help=False)
    robots.add_argument("--robots", type=int, default=3)  # run_team.sh's default
    num_robots = robots.parse_known_args(options.team_args)[0].robots
    reason = cannot_run_reason()
    if reason:
        print(f"field_chaos: cannot run: {reason}", file=sys.stderr)
        return 2
    out = options.out or Path(tempfile.mkdtemp(prefix="field_chaos_"))
    out.mkdir(parents=True, exist_ok=True)
    # SIGTERM unwinds like Ctrl-C: the run is stopped and the namespaces are removed.
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))
    try:
        network = HostNetwork(num_robots, loss_one_in=options.loss)
    except ValueError as error:
        parser.error(str(error))
    with network:
        command = ["bash", str(RUN_TEAM), "--respawn", "--netns", network.prefix, "--seed",
                   str(options.seed), "--summary", str(out / "summary.json"), "--domain-id",
                   str(options.domain_id), *options.team_args]
        code, kills, wall_s = run_with_kills(command, out, options)
        dropped = network.drop_ratio()
    print(f"{num_robots} robots on separate hosts, loss 1/{options.loss or 'inf'} per robot "
          f"veth end (measured {100 * dropped:.1f} %), SIG{options.signal}, seed {options.seed}")
    print(f"kills (wall s since the start, robot): {kills}")
    print(f"run_team.sh exit code {code} after {wall_s:.0f} s"
          f"{' (stopped: --limit reached)' if wall_s >= options.limit else ''}")
    print("\n".join(outcome(out, options.max_lines)))
    print(f"run directory: {out}")
    return code


if __name__ == "__main__":
    sys.exit(main())
