"""Wall time, real-time factor and CPU seconds per node process of the lockstep team.

Runs ``./launch_scripts/run_team.sh --summary DIR/summary.json [run_team.sh options]``
(default: the 3-robot lockstep mission) ``--repeat`` times, one after the other, each in its
own ROS domain (``--domain-id`` + run index) and its own kept temporary directory. While a
run goes, the CPU time (utime + stime of ``/proc/PID/stat``) of every node process is read
every 0.5 s and the last value seen per process is kept; node processes are the
descendants of that run's run_team.sh whose command line holds ``em_exploration_ros.nodes.``
(so other runs on the machine are not counted). CPU a process spends after its last reading
(at most 0.5 s of its life) is not counted. A robot restarted with ``--respawn`` counts
under its robot's name with every process it had.

Prints per run the summary's wall and simulated time, the real-time factor, the targets
chosen and the CPU seconds of the world, the evaluator, each robot and the team; then the
median and range of each over the runs, and whether every run chose the same targets.
``--repo`` times another checkout's run_team.sh (default: this script's repository).

Usage: ``.venv/bin/python benchmarks/team_cpu.py [--repeat 5] [--domain-id 60] [--repo PATH]
[-- run_team.sh options]``
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NODE_MODULES = "em_exploration_ros.nodes."
POLL_S = 0.5
CLOCK_TICKS_PER_S = os.sysconf("SC_CLK_TCK")
#: run_team.sh's options this script sets itself.
OWN_OPTIONS = ("--summary", "--domain-id")
#: Seconds run_team.sh gets to stop its nodes after SIGINT (its own grace periods are 10 + 3 s).
STOP_WAIT_S = 30.0


def read_stat(pid: str) -> tuple[int, float] | None:
    """(parent PID, CPU seconds) of a process, or None once it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            fields = stat.read().rpartition(")")[2].split()
    except OSError:
        return None
    # After the command name: state, ppid, ... utime and stime are fields 14 and 15 of stat.
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / CLOCK_TICKS_PER_S


def node_name(pid: int) -> str | None:
    """world / evaluator / robot K for a node process, None for any other process."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
            args = cmdline.read().decode(errors="replace").split("\0")
    except OSError:
        return None
    module = next((arg for arg in args if arg.startswith(NODE_MODULES)), None)
    if module is None:
        return None
    name = module[len(NODE_MODULES):].removesuffix("_node")
    if name == "robot":
        robot_id = next((arg.split(":=", 1)[1] for arg in args
                         if arg.startswith("robot_id:=")), "?")
        name = f"robot {robot_id}"
    return name


def sample_descendants(root: int, names: dict[int, str], cpu_s: dict[int, float]) -> None:
    """Record the CPU seconds of every node process under ``root`` (``names``: the node
    processes seen so far; any other process is looked at again, as it may be a node process
    between fork and exec)."""
    stats = {int(pid): stat for pid in os.listdir("/proc") if pid.isdigit()
             and (stat := read_stat(pid)) is not None}
    children: dict[int, list[int]] = {}
    for pid, (parent, _cpu) in stats.items():
        children.setdefault(parent, []).append(pid)
    pending = list(children.get(root, []))
    while pending:
        pid = pending.pop()
        pending.extend(children.get(pid, []))
        if pid not in names and (name := node_name(pid)) is not None:
            names[pid] = name
        if pid in names:
            cpu_s[pid] = stats[pid][1]


def stop(process: subprocess.Popen, node_pids: list[int]) -> None:
    """End run_team.sh as Ctrl-C does (it stops its nodes); as a last resort SIGKILL its
    process group and those of the node processes (each runs in its own session)."""
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGINT)
    try:
        process.wait(STOP_WAIT_S)
    except subprocess.TimeoutExpired:
        for group in (process.pid, *node_pids):
            try:
                os.killpg(group, signal.SIGKILL)
            except ProcessLookupError:
                pass
        process.wait()


def run_once(repo: Path, domain_id: int,
             team_args: list[str]) -> tuple[dict, dict[str, float], float, Path, int]:
    """One team run: (summary, CPU seconds by process name, command wall [s], output
    directory, run_team.sh's exit code)."""
    out_dir = Path(tempfile.mkdtemp(prefix=f"team_cpu_d{domain_id}_"))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    command = [str(repo / "launch_scripts" / "run_team.sh"), "--summary",
               str(out_dir / "summary.json"), "--domain-id", str(domain_id), *team_args]
    names: dict[int, str] = {}
    cpu_s: dict[int, float] = {}
    with open(out_dir / "run_team.out", "wb") as output:
        started = time.monotonic()
        process = subprocess.Popen(command, cwd=repo, env=env, stdout=output,
                                   stderr=subprocess.STDOUT, start_new_session=True)
        try:
            while process.poll() is None:
                sample_descendants(process.pid, names, cpu_s)
                time.sleep(POLL_S)
        finally:
            stop(process, list(names))
        wall_s = time.monotonic() - started
    by_name: dict[str, float] = {}
    for pid, seconds in cpu_s.items():
        by_name[names[pid]] = by_name.get(names[pid], 0.0) + seconds
    summary_path = out_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    return summary, by_name, wall_s, out_dir, process.returncode


def process_order(name: str) -> tuple[int, str]:
    """world, evaluator, then the robots by id."""
    rank = {"world": 0, "evaluator": 1}.get(name, 2)
    robot_id = name.removeprefix("robot ")
    return rank, f"{int(robot_id):04d}" if robot_id.isdigit() else name


def spread(values: list[float], unit: str, digits: int = 1) -> str:
    """``median (min-max)`` of ``values``."""
    return (f"{statistics.median(values):.{digits}f}{unit} "
            f"({min(values):.{digits}f}-{max(values):.{digits}f})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--domain-id", type=int, default=60,
                        help="ROS_DOMAIN_ID of the first run; run i uses this + i")
    parser.add_argument("--repo", type=Path, default=Path(__file__).resolve().parent.parent,
                        help="checkout whose launch_scripts/run_team.sh runs")
    parser.add_argument("team_args", nargs="*", metavar="-- run_team.sh options")
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    if not (0 <= args.domain_id and args.domain_id + args.repeat - 1 <= 232):
        parser.error("the runs' domain ids must lie in 0..232")
    if any(arg.split("=", 1)[0] in OWN_OPTIONS for arg in args.team_args):
        parser.error(f"{' and '.join(OWN_OPTIONS)} are set by this script")
    repo = args.repo.resolve()
    if not (repo / "launch_scripts" / "run_team.sh").is_file():
        parser.error(f"no launch_scripts/run_team.sh in {repo}")

    rows: list[tuple[float, float, float, dict[str, float]]] = []
    targets: list[list] = []
    for run in range(args.repeat):
        domain_id = args.domain_id + run
        summary, cpu_s, command_wall_s, out_dir, code = run_once(repo, domain_id, args.team_args)
        print(f"run {run + 1}/{args.repeat} (ROS_DOMAIN_ID={domain_id}): {out_dir}")
        if code != 0:
            lines = (out_dir / "run_team.out").read_text(errors="replace").splitlines()
            print(f"run_team.sh exited with code {code}; its last lines:")
            print("\n".join(f"  {line}" for line in lines[-20:]))
            return code
        if not cpu_s:
            print(f"error: no process running {NODE_MODULES}* was seen under run_team.sh")
            return 1
        wall_s, sim_s = summary["wall_s"], summary["sim_time_s"]
        chosen = [robot["targets"] for robot in summary["robots"]]
        targets.append(chosen)
        team_s = sum(cpu_s.values())
        rows.append((wall_s, sim_s / wall_s, team_s, cpu_s))
        print(f"  summary wall {wall_s:.1f} s (command {command_wall_s:.1f} s), simulated "
              f"{sim_s:.1f} s, {sim_s / wall_s:.1f}x real time, "
              f"{sum(len(t) for t in chosen)} targets")
        print("  CPU: " + ", ".join(f"{name} {cpu_s[name]:.1f} s"
                                    for name in sorted(cpu_s, key=process_order))
              + f"; team {team_s:.1f} s")

    print(f"\n{len(rows)} runs, median (range):")
    print(f"  summary wall     {spread([row[0] for row in rows], ' s')}")
    print(f"  real-time factor {spread([row[1] for row in rows], 'x')}")
    print(f"  team CPU         {spread([row[2] for row in rows], ' s')}")
    names = sorted({name for row in rows for name in row[3]}, key=process_order)
    for name in names:
        values = [row[3].get(name, 0.0) for row in rows]
        print(f"  {name + ' CPU':16s} {spread(values, ' s')}")
    same = all(chosen == targets[0] for chosen in targets)
    print(f"  same targets in every run: {'yes' if same else 'NO'} "
          f"({sum(len(t) for t in targets[0])} in the first)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
