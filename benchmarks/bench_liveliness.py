"""How fast a robot process that dies or wedges is noticed, and a restarted one recognized.

Starts a real em-robot process (robot 1 of 2, no world needed: it waits for the mission),
watches its liveliness as the world, the teammates and the evaluator do
(``nodes/liveliness.py``), and measures the wall time from

- SIGSTOP (a process alive but off the graph, like the Fast DDS deadlock) to "lost",
- SIGCONT to "alive" again,
- SIGKILL to "lost",
- the start of a new process with the same command line to "alive, restarted",

``--repeat`` times, and prints each figure's median and maximum.

Usage: ``.venv/bin/python benchmarks/bench_liveliness.py [--repeat 5] [--domain-id 42]``
"""
from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROBOT_MODULE = "em_exploration_ros.nodes.robot_node"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--domain-id", type=int, default=42)
    args = parser.parse_args()
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

    import rclpy  # after the domain is set
    from em_exploration_ros.nodes.liveliness import watch_liveliness

    rclpy.init()
    node = rclpy.create_node("liveliness_bench")
    events: list[tuple[float, bool, bool]] = []
    watch_liveliness(node, [1], lambda _r, alive, restarted: events.append(
        (time.monotonic(), alive, restarted)))
    command = [sys.executable, "-m", ROBOT_MODULE, "--ros-args", "-r", "__ns:=/robot_1",
               "-p", "robot_id:=1", "-p", "world.num_robots:=2"]
    log = open(Path(tempfile.mkdtemp(prefix="bench_liveliness_")) / "robot.log", "wb")

    def start() -> subprocess.Popen:
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)

    def wait_event(alive: bool, since: float, timeout_s: float = 30.0) -> tuple[float, bool]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.02)
            for stamp, state, restarted in events:
                if stamp >= since and state == alive:
                    events.clear()
                    return stamp - since, restarted
        raise TimeoutError(f"no liveliness {'gained' if alive else 'lost'} in {timeout_s} s")

    figures: dict[str, list[float]] = {"SIGSTOP -> lost": [], "SIGCONT -> alive": [],
                                       "SIGKILL -> lost": [], "restart -> alive (restarted)": []}
    process = start()
    try:
        wait_event(True, 0.0, 60.0)
        for _ in range(args.repeat):
            time.sleep(1.0)
            sent = time.monotonic()
            process.send_signal(signal.SIGSTOP)
            figures["SIGSTOP -> lost"].append(wait_event(False, sent)[0])
            sent = time.monotonic()
            process.send_signal(signal.SIGCONT)
            figures["SIGCONT -> alive"].append(wait_event(True, sent)[0])
            time.sleep(1.0)
            sent = time.monotonic()
            process.kill()
            process.wait()
            figures["SIGKILL -> lost"].append(wait_event(False, sent)[0])
            sent = time.monotonic()
            process = start()
            delay, restarted = wait_event(True, sent, 60.0)
            if not restarted:
                print("warning: a restarted process was not recognized as such")
            figures["restart -> alive (restarted)"].append(delay)
    finally:
        process.kill()
        process.wait()
        node.destroy_node()
        rclpy.try_shutdown()
    for name, values in figures.items():
        print(f"{name:30s} median {statistics.median(values):5.2f} s  max {max(values):5.2f} s  "
              f"({len(values)} times)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
