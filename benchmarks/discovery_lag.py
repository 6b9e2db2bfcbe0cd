"""How long ROS processes that start at different times take to find each other.

A trial starts ``--participants`` processes (each one rclpy context, so one Fast DDS
participant, with a node that publishes and subscribes to one reliable topic) at seeded
random delays in [0, ``--spread``] s, beside ``--busy`` busy loops (the load of a team
that is already running). Each process waits until its own writer and reader have matched
every participant's (its own included) and reports when. A trial's lag is the time from
the last process being up (its node created) to the last match, i.e. what discovery adds
once everybody runs. Printed per Fast DDS profile: the team's (config/fastdds_profiles.xml)
and Fast DDS's default (no profile file), each over ``--trials`` trials with the same
delays, as the median and the maximum lag [s].

Usage: ``.venv/bin/python benchmarks/discovery_lag.py [--trials 10] [--participants 6]
[--spread 6] [--busy 2] [--seed 0] [--domain-id 62]``
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

TEAM_PROFILE = Path(__file__).resolve().parents[1] / "config" / "fastdds_profiles.xml"
#: Bound of one participant's wait for its matches [s].
MATCH_TIMEOUT_S = 30.0


def participant(count: int, delay_s: float) -> None:
    """Child: after ``delay_s``, one participant; prints "<up> <matched>" (time.time() [s])
    once its writer and reader each matched ``count`` endpoints, then stays until the parent
    stops it."""
    time.sleep(delay_s)
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Empty

    rclpy.init()
    node = rclpy.create_node(f"discovery_lag_{os.getpid()}")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    writer = node.create_publisher(Empty, "/discovery_lag", qos)
    reader = node.create_subscription(Empty, "/discovery_lag", lambda _msg: None, qos)
    up = time.time()
    while (writer.get_subscription_count() < count or reader.get_publisher_count() < count) \
            and time.time() - up < MATCH_TIMEOUT_S:
        rclpy.spin_once(node, timeout_sec=0.02)
    print(f"{up} {time.time()}", flush=True)
    time.sleep(MATCH_TIMEOUT_S)


def trial(delays: list[float], env: dict[str, str]) -> float:
    """One trial's lag [s]: the last match after the last participant was up."""
    children = []
    for delay in delays:
        children.append(subprocess.Popen(
            [sys.executable, __file__, "--child", str(len(delays)), repr(delay)], env=env,
            stdout=subprocess.PIPE, text=True, start_new_session=True))
    try:
        times = [[float(value) for value in child.stdout.readline().split()]
                 for child in children]
    finally:
        for child in children:
            child.kill()
            child.wait()
    if any(len(pair) != 2 for pair in times):
        raise RuntimeError("a participant ended without reporting its matches")
    return max(matched for _, matched in times) - max(up for up, _ in times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--participants", type=int, default=6)
    parser.add_argument("--spread", type=float, default=6.0, help="start delays [s]")
    parser.add_argument("--busy", type=int, default=2, help="busy loops beside them")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--domain-id", type=int, default=62)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    delays = [[rng.uniform(0.0, args.spread) for _ in range(args.participants)]
              for _ in range(args.trials)]
    base = {key: value for key, value in os.environ.items()
            if key not in ("FASTRTPS_DEFAULT_PROFILES_FILE", "RMW_FASTRTPS_USE_QOS_FROM_XML")}
    base.update(ROS_DOMAIN_ID=str(args.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    profiles = {"config/fastdds_profiles.xml": dict(
        base, FASTRTPS_DEFAULT_PROFILES_FILE=str(TEAM_PROFILE),
        RMW_FASTRTPS_USE_QOS_FROM_XML="1"), "Fast DDS default": base}
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(args.busy)]
    try:
        print(f"{args.participants} participants started 0-{args.spread:g} s apart beside "
              f"{args.busy} busy loops, {args.trials} trials: lag after the last one is up [s]")
        for name, env in profiles.items():
            lags = [trial(trial_delays, env) for trial_delays in delays]
            print(f"{name:28s} median {statistics.median(lags):5.2f}  max {max(lags):5.2f}  "
                  f"({' '.join(f'{lag:.2f}' for lag in lags)})", flush=True)
    finally:
        for process in busy:
            process.kill()
            process.wait()
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        participant(int(sys.argv[2]), float(sys.argv[3]))
    else:
        sys.exit(main())
