"""Lockstep under packet loss: does a lossy network change the team's decisions?

Runs ``launch_scripts/run_team.sh`` (lockstep) inside a network namespace created for the
purpose, with ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` so every DDS packet, discovery included,
crosses the namespace's loopback interface. First one run without loss, then ``--runs``
runs with about ``--loss`` of all packets dropped at random: this kernel has no netem, so
the loopback gets an ``htb`` root qdisc, a classic-BPF ``tc`` filter that loads the
kernel's random number (SKF_AD_OFF + SKF_AD_RANDOM), takes it modulo N = round(1 / loss)
and sends the packets where it is 0 to a class whose ``pfifo limit 0`` drops them. Each
lossy run's targets (every robot's, in order) are compared with the lossless run's, and
the script prints per run: exit code, identical targets or not, wall time, how many steps
the world re-sent and how many re-send requests the robots answered, plus the measured
drop ratio from the qdisc's counters.

Needs root (``ip netns``, ``tc``); the host's own interfaces are never touched and the
namespace is deleted at the end, whatever happens.

Usage: ``sudo .venv/bin/python benchmarks/bench_loss.py [--runs 5] [--loss 0.2]
[-- run_team.sh arguments]`` (default team: 3 robots, EM_3, 60 m map, 6 landmarks, seed 2).
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
import uuid
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
RUN_TEAM = REPO_ROOT / "launch_scripts" / "run_team.sh"
DEFAULT_TEAM = ["--robots", "3", "--planner", "EM_3", "--map-size", "60", "--landmarks", "6",
                "--seed", "2", "--max-sim-time", "900"]
#: Classic BPF, tc's "count,code jt jf k,..." form: A = random; A %= N; A == 0 ? match : no.
#: 32 = LD|W|ABS (k = SKF_AD_OFF + SKF_AD_RANDOM = -4096 + 56), 148 = ALU|MOD|K,
#: 21 = JMP|JEQ|K, 6 = RET|K (-1: the filter's class, 0: no match).
RANDOM_MATCH_BPF = "5,32 0 0 4294963256,148 0 0 {n},21 0 1 0,6 0 0 4294967295,6 0 0 0"
RUN_TIMEOUT_S = 900


def sh(*args: str, namespace: str | None = None, check: bool = True) -> str:
    command = (["ip", "netns", "exec", namespace] if namespace else []) + list(args)
    result = subprocess.run(command, capture_output=True, text=True)
    if check and result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)}: {result.stderr.strip()}")
    return result.stdout


def add_random_loss(namespace: str, device: str, n: int) -> None:
    """Drop about 1 in ``n`` packets leaving ``device`` of ``namespace`` (module docstring)."""
    def tc(*args: str) -> None:
        sh("tc", *args, namespace=namespace)
    tc("qdisc", "add", "dev", device, "root", "handle", "1:", "htb", "default", "1")
    for minor in ("1", "2"):
        tc("class", "add", "dev", device, "parent", "1:", "classid", f"1:{minor}", "htb", "rate",
           "10gbit")
    tc("qdisc", "add", "dev", device, "parent", "1:2", "handle", "20:", "pfifo", "limit", "0")
    tc("filter", "add", "dev", device, "parent", "1:", "protocol", "all", "prio", "1", "bpf",
       "bytecode", RANDOM_MATCH_BPF.format(n=n), "classid", "1:2")


class LossyNamespace:
    """A network namespace whose loopback drops about one packet in ``n`` (``n`` = 0: none)."""

    def __init__(self, n: int) -> None:
        self.name = f"em_loss_{uuid.uuid4().hex[:8]}"
        self.n = n

    def __enter__(self) -> "LossyNamespace":
        sh("ip", "netns", "add", self.name)
        try:
            sh("ip", "link", "set", "lo", "up", namespace=self.name)
            if self.n > 0:
                add_random_loss(self.name, "lo", self.n)
        except Exception:
            self.__exit__()
            raise
        return self

    def drop_ratio(self) -> float:
        """Packets dropped / packets sent on the namespace's loopback so far."""
        stats = sh("tc", "-s", "qdisc", "show", "dev", "lo", namespace=self.name)
        root = re.search(r"qdisc htb 1: root.*?Sent \d+ bytes (\d+) pkt \(dropped (\d+)", stats,
                         re.S)
        if root is None:
            return 0.0
        sent, dropped = int(root.group(1)), int(root.group(2))
        return dropped / max(sent + dropped, 1)

    def __exit__(self, *exc: object) -> None:
        sh("ip", "netns", "del", self.name, check=False)


def run_team(namespace: LossyNamespace, out_dir: Path, team_args: list[str]) -> dict:
    """One run_team.sh inside the namespace; its summary and a few counters."""
    summary = out_dir / "summary.json"
    env = dict(os.environ, FASTDDS_BUILTIN_TRANSPORTS="UDPv4")
    started = time.monotonic()
    with open(out_dir / "run_team.out", "wb") as log:
        code = subprocess.run(["ip", "netns", "exec", namespace.name, "bash", str(RUN_TEAM),
                               *team_args, "--domain-id", "7", "--summary", str(summary)],
                              stdout=log, stderr=subprocess.STDOUT, env=env,
                              timeout=RUN_TIMEOUT_S).returncode
    wall = time.monotonic() - started
    logs = out_dir / "logs"
    world = (logs / "world.log").read_text(errors="replace") if logs.exists() else ""
    robots = "".join(p.read_text(errors="replace") for p in logs.glob("robot_*.log"))
    data = json.loads(summary.read_text()) if summary.exists() else {}
    return {"code": code, "wall_s": wall, "summary": data, "drop_ratio": namespace.drop_ratio(),
            "lost_lines": world.count(" lost:"), "resent": robots.count("re-sent updates"),
            "targets": [r["targets"] for r in data.get("robots", [])]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--loss", type=float, default=0.2, help="fraction of packets dropped")
    parser.add_argument("--out", type=Path, default=None, help="folder for runs (default: tmp)")
    parser.add_argument("team", nargs="*", help="run_team.sh arguments (after --)")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_loss: needs root (ip netns, tc)", file=sys.stderr)
        return 2
    team_args = args.team or DEFAULT_TEAM
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_loss_"))
    n = max(2, round(1.0 / args.loss))
    print(f"team: {' '.join(team_args)}; loss 1/{n}; runs in {out}")
    with LossyNamespace(0) as clean:
        (out / "lossless").mkdir(parents=True, exist_ok=True)
        reference = run_team(clean, out / "lossless", team_args)
    print(f"lossless: exit {reference['code']}, wall {reference['wall_s']:.0f} s, "
          f"{sum(map(len, reference['targets']))} targets, stop: "
          f"{reference['summary'].get('stop_reason')}")
    identical = 0
    for index in range(args.runs):
        run_dir = out / f"loss_{index}"
        run_dir.mkdir(parents=True, exist_ok=True)
        with LossyNamespace(n) as lossy:
            result = run_team(lossy, run_dir, team_args)
        same = result["code"] == 0 and result["targets"] == reference["targets"]
        same_history = (result["summary"].get("history") == reference["summary"].get("history"))
        identical += same
        print(f"run {index}: exit {result['code']}, targets identical: {same}, metrics history "
              f"identical: {same_history}, wall {result['wall_s']:.0f} s, dropped "
              f"{100 * result['drop_ratio']:.1f} % of packets, 'lost' lines {result['lost_lines']},"
              f" update re-sends {result['resent']}, explored "
              f"{result['summary'].get('explored_ratio')}")
    print(f"identical targets: {identical} of {args.runs} lossy runs")
    return 0 if identical == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
