"""Where a flooded node's memory goes: a listener with the evaluator's subscriptions under em-fuzz.

Starts a process named ``em_evaluator`` that only subscribes to the evaluator's topics with
the evaluator's QoS (nothing publishes them but the fuzzer), then ``em-fuzz --nodes
em_evaluator`` against it, and prints the listener's VmRSS before, at its peak and at the
end, how many messages it took, the Python heap's peak (tracemalloc) and VmRSS after
glibc's ``malloc_trim(0)``, for each way of taking the messages:

- ``raw``: the serialized bytes only (no deserialization),
- ``deserialize``: rclpy's message objects, dropped at once,
- ``check``: message objects checked as every node checks them (``content_problem``),
- ``check-traced``: the same with tracemalloc on, for the Python heap's peak (tracemalloc
  slows the allocation of Python objects, so fewer messages are taken).

Messages the listener has not taken yet wait in the middleware's reader queues; the
difference between the modes shows what deserializing thousands of nested messages costs.

Usage: ``.venv/bin/python benchmarks/bench_fuzz_memory.py [--rate 150] [--duration 10]
[--domain-id 43]``
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

#: Wall seconds the listener runs beyond the attack, and is given to start before it.
LISTEN_EXTRA_S = 12.0
LISTENER_START_S = 3.0
MODES = ("raw", "deserialize", "check", "check-traced")


def listen(mode: str, duration_s: float) -> None:
    """The listener process: subscribe, take messages for ``duration_s``, print a JSON line."""
    import ctypes
    import tracemalloc

    import rclpy
    from em_exploration_msgs.msg import LandmarkArray, MotionCommand, TeamUpdate
    from nav_msgs.msg import Odometry, Path
    from rclpy.node import Node

    from em_exploration_ros.nodes.input_guard import content_problem
    from em_exploration_ros.nodes.qos import (ESTIMATE_READER_QOS, GROUND_TRUTH_QOS,
                                              LATCHED_QOS, SENSOR_QOS, TEAM_QOS)

    if mode == "check-traced":
        tracemalloc.start()
    rclpy.init()
    node = Node("em_evaluator")
    taken = [0]

    def on_message(message) -> None:
        taken[0] += 1
        if mode.startswith("check"):
            content_problem(message)

    raw = mode == "raw"
    topics = [(LandmarkArray, "/world/landmarks", LATCHED_QOS)]
    for robot in range(3):
        topics += [(Odometry, f"/world/ground_truth/robot_{robot}", GROUND_TRUTH_QOS),
                   (Path, f"/robot_{robot}/estimated_path", ESTIMATE_READER_QOS),
                   (LandmarkArray, f"/robot_{robot}/landmarks", ESTIMATE_READER_QOS),
                   (TeamUpdate, f"/robot_{robot}/team/updates", TEAM_QOS),
                   (MotionCommand, f"/robot_{robot}/motion_command", SENSOR_QOS)]
    for message_class, topic, qos in topics:
        node.create_subscription(message_class, topic, on_message, qos, raw=raw)
    start = time.monotonic()
    before = peak = rss_mb()
    while time.monotonic() - start < duration_s:
        rclpy.spin_once(node, timeout_sec=0.05)
        peak = max(peak, rss_mb())
    end = rss_mb()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    print(json.dumps({"mode": mode, "taken": taken[0], "rss_before_mb": before,
                      "rss_peak_mb": peak, "rss_end_mb": end, "rss_trimmed_mb": rss_mb(),
                      "python_heap_peak_mb": (tracemalloc.get_traced_memory()[1] / 2**20
                                              if tracemalloc.is_tracing() else None)}),
          flush=True)


def rss_mb() -> float:
    """This process's VmRSS [MB]."""
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=150.0, help="messages per second")
    parser.add_argument("--duration", type=float, default=10.0, help="attack [s]")
    parser.add_argument("--domain-id", type=int, default=43)
    parser.add_argument("--listen", choices=MODES, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.listen:
        listen(args.listen, args.duration + LISTEN_EXTRA_S)
        return 0
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    print(f"em-fuzz at {args.rate:g} messages/s for {args.duration:g} s on the evaluator's "
          f"topics; listener runs {args.duration + LISTEN_EXTRA_S:g} s")
    for mode in MODES:
        listener = subprocess.Popen(
            [sys.executable, __file__, "--listen", mode, "--duration", str(args.duration)],
            env=env, stdout=subprocess.PIPE, text=True)
        time.sleep(LISTENER_START_S)
        fuzz = subprocess.run(
            [sys.executable, "-m", "em_exploration_ros.tools.fuzz", "--duration",
             str(args.duration), "--rate", str(args.rate), "--nodes", "em_evaluator"],
            env=env, capture_output=True, text=True, timeout=args.duration + 60.0)
        sent = json.loads(fuzz.stdout.strip().splitlines()[-1])["messages"]
        out, _ = listener.communicate(timeout=args.duration + LISTEN_EXTRA_S + 30.0)
        result = json.loads(out.strip().splitlines()[-1])
        heap = result["python_heap_peak_mb"]
        print(f"{mode:12s} sent {sent:5d} taken {result['taken']:5d}  VmRSS "
              f"{result['rss_before_mb']:.0f} -> peak {result['rss_peak_mb']:.0f} -> end "
              f"{result['rss_end_mb']:.0f} MB, after malloc_trim {result['rss_trimmed_mb']:.0f}"
              " MB" + (f"; Python heap peak {heap:.1f} MB" if heap is not None else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
