"""Publisher-side CPU of one DDS publish of the team's messages, and of an idle executor wake-up.

For each count K of ``--subscribers``, K subscriber processes (this script in its hidden
``--subscriber`` mode: a ``LeanNode`` spun on ``LeanExecutor``, as the team's nodes are) each
subscribe to one topic per message type, with the QoS the team uses:

- rosgraph_msgs/Clock with ``CLOCK_QOS`` (the world's /clock),
- nav_msgs/Odometry with ``SENSOR_QOS`` (a robot's dead reckoning, covariances filled),
- em_exploration_msgs/SonarScan with ``SENSOR_QOS`` (robot 0's scan at the first step of
  the default mission, built as em-world builds it),
- em_exploration_msgs/TeamUpdate with ``TEAM_QOS`` (two keyframes with landmark and
  teammate readings, one target).

Once the publisher's ``get_subscription_count()`` shows all K readers of every topic, it
publishes ``--messages`` messages of each type, 1 ms apart so that the readers keep up (after
100 unmeasured ones), and measures the publishing thread's CPU time
(``time.thread_time_ns``) around each ``publish`` call: median and 90th percentile.

Then, with the last subscriber processes still running, the CPU time of one
``executor.spin_once(timeout_sec=0)`` with nothing ready, on a ``LeanNode`` with 10
subscriptions, 10 publishers, 5 timers (1 h period) and its parameter services, for rclpy's
``SingleThreadedExecutor`` and for ``LeanExecutor`` (``nodes/lean_executor.py``).

Usage: ``.venv/bin/python benchmarks/dds_publish_cost.py [--subscribers 0 1 2 3 4]
[--messages 2000] [--spins 5000] [--domain-id 61]``
"""
from __future__ import annotations

import argparse
import functools
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

WARMUP_MESSAGES = 100
WARMUP_SPINS = 100
PUBLISH_PERIOD_S = 0.001
MATCH_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 5.0
PARAMS_FILE = Path(__file__).resolve().parent.parent / "config" / "exploration.yaml"


def topics() -> list[tuple[str, str, type, Any]]:
    """(label, topic, message class, QoS) of each measured message type."""
    from em_exploration_msgs.msg import SonarScan, TeamUpdate
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock

    from em_exploration_ros.nodes.qos import CLOCK_QOS, SENSOR_QOS, TEAM_QOS
    return [("rosgraph_msgs/Clock", "/dds_cost/clock", Clock, CLOCK_QOS),
            ("nav_msgs/Odometry (serialized)", "/dds_cost/odom", Odometry, SENSOR_QOS),
            ("em_exploration_msgs/SonarScan", "/dds_cost/sonar", SonarScan, SENSOR_QOS),
            ("em_exploration_msgs/TeamUpdate", "/dds_cost/team_updates", TeamUpdate, TEAM_QOS)]


def sample_messages() -> list[Any]:
    """One message of each type of ``topics()``, in that order, filled as the team fills
    them."""
    from em_exploration_msgs import msg as em_msg
    from rosgraph_msgs.msg import Clock

    from em_exploration_ros.core.params_yaml import load_params
    from em_exploration_ros.core.world.simulation import WorldSimulation
    from em_exploration_ros.nodes.conversions import (seconds_to_time, serialized_dead_reckoning,
                                                      sonar_scan_to_msg)
    params = load_params(PARAMS_FILE)
    sim = WorldSimulation(params)
    frame = sim.sense(0)
    scan = sonar_scan_to_msg(frame, params.sensors.sonar_max_range_m,
                             [0] * params.world.num_robots)
    keyframes = [em_msg.Keyframe(
        index=index, previous_index=index - 1, odom_x=2.0, odom_y=0.05, odom_theta=0.02,
        odom_covariance=[4e-3, 1e-4, 2e-5, 4e-3, 3e-5, 1e-4],
        landmarks=[em_msg.KeyframeLandmark(landmark_id=7, range=6.5, bearing=0.4)],
        teammates=[em_msg.KeyframeTeammate(robot_id=1, x=4.2, y=-1.3, theta=0.3)])
        for index in (11, 12)]
    update = em_msg.TeamUpdate(
        step=120, sequence=9, robot_id=0, keyframes=keyframes,
        targets=[em_msg.TargetRecord(decision_index=4, x=42.0, y=17.0, planning_time=0.04,
                                     frontier_type=em_msg.TargetRecord.EXPLORATION)])
    # Odometry as the world publishes it: already serialized (nodes.odometry_cdr).
    return [Clock(clock=seconds_to_time(sim.stamp_s)), serialized_dead_reckoning(frame), scan,
            update]


def run_subscriber() -> int:
    """The hidden ``--subscriber`` mode: read every topic until SIGINT or SIGTERM."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from em_exploration_ros.nodes import lean_executor
    from em_exploration_ros.nodes.lean_node import LeanNode
    rclpy.init()
    node = LeanNode(f"dds_cost_subscriber_{os.getpid()}")
    for _label, topic, message_type, qos in topics():
        node.create_subscription(message_type, topic, lambda _message: None, qos)
    try:
        lean_executor.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def stop(processes: list[subprocess.Popen]) -> None:
    """Terminate the processes (SIGTERM, then SIGKILL after ``STOP_TIMEOUT_S``)."""
    for process in processes:
        process.terminate()
    for process in processes:
        try:
            process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    processes.clear()


def cpu_us(call: Callable[[], Any], times: int, pause_s: float = 0.0) -> list[float]:
    """The calling thread's CPU time [us] of each of ``times`` calls of ``call``."""
    samples = []
    for _ in range(times):
        start = time.thread_time_ns()
        call()
        samples.append((time.thread_time_ns() - start) / 1000.0)
        if pause_s:
            time.sleep(pause_s)
    return samples


def median_p90(samples: list[float]) -> tuple[float, float]:
    return statistics.median(samples), statistics.quantiles(samples, n=10)[-1]


def idle_wait_cost(executor_class: type, spins: int) -> tuple[list[float], str]:
    """CPU [us] of each ``spin_once(timeout_sec=0)`` with nothing ready, and the node's
    entity counts."""
    from nav_msgs.msg import Odometry

    from em_exploration_ros.nodes.lean_node import LeanNode
    from em_exploration_ros.nodes.qos import SENSOR_QOS
    node = LeanNode(f"dds_cost_idle_{executor_class.__name__}")
    for index in range(10):
        node.create_subscription(Odometry, f"/dds_cost/idle/in_{index}", lambda _m: None,
                                 SENSOR_QOS)
        node.create_publisher(Odometry, f"/dds_cost/idle/out_{index}", SENSOR_QOS)
    for _ in range(5):
        node.create_timer(3600.0, lambda: None)
    counts = ", ".join(f"{len(list(getattr(node, kind)))} {kind}" for kind in
                       ("subscriptions", "publishers", "timers", "services", "guards"))
    executor = executor_class(context=node.context)
    executor.add_node(node)
    try:
        cpu_us(lambda: executor.spin_once(timeout_sec=0), WARMUP_SPINS)
        return cpu_us(lambda: executor.spin_once(timeout_sec=0), spins), counts
    finally:
        executor.shutdown()
        node.destroy_node()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--subscribers", type=int, nargs="+", default=[0, 1, 2, 3, 4],
                        help="subscriber process counts to measure")
    parser.add_argument("--messages", type=int, default=2000,
                        help="measured publishes per message type and subscriber count")
    parser.add_argument("--spins", type=int, default=5000,
                        help="measured spin_once calls per executor")
    parser.add_argument("--domain-id", type=int, default=61)
    parser.add_argument("--subscriber", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.messages < 2 or args.spins < 2 or min(args.subscribers) < 0:
        parser.error("--messages and --spins need at least 2, --subscribers counts >= 0")
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if args.subscriber:
        return run_subscriber()

    import rclpy  # after the domain is set
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import serialize_message

    from em_exploration_ros.nodes.lean_executor import LeanExecutor
    from em_exploration_ros.nodes.lean_node import LeanNode

    rclpy.init()
    node = LeanNode("dds_cost_publisher")
    measured = topics()
    publishers = [node.create_publisher(message_type, topic, qos)
                  for _label, topic, message_type, qos in measured]
    messages = sample_messages()
    subscriber_command = [sys.executable, str(Path(__file__).resolve()), "--subscriber",
                          "--domain-id", str(args.domain_id)]
    subscribers: list[subprocess.Popen] = []
    results: dict[tuple[int, int], tuple[float, float]] = {}
    try:
        for count in args.subscribers:
            if count < len(subscribers):
                stop(subscribers)
            while len(subscribers) < count:
                subscribers.append(subprocess.Popen(subscriber_command,
                                                    stdout=subprocess.DEVNULL))
            started = time.monotonic()
            while any(p.get_subscription_count() != count for p in publishers):
                exited = [p.returncode for p in subscribers if p.poll() is not None]
                if exited or time.monotonic() - started > MATCH_TIMEOUT_S:
                    matched = [p.get_subscription_count() for p in publishers]
                    print(f"error: waiting for {count} subscribers per topic, the topics had "
                          f"{matched} after {time.monotonic() - started:.0f} s; exit codes "
                          f"of subscriber processes: {exited or 'none exited'}")
                    return 1
                time.sleep(0.1)
            for index, (publisher, message) in enumerate(zip(publishers, messages)):
                publish = functools.partial(publisher.publish, message)
                cpu_us(publish, WARMUP_MESSAGES, PUBLISH_PERIOD_S)
                results[count, index] = median_p90(cpu_us(publish, args.messages,
                                                          PUBLISH_PERIOD_S))
            print(f"{count} subscribers: done", flush=True)
        waits = {name: idle_wait_cost(executor_class, args.spins)
                 for name, executor_class in (("rclpy SingleThreadedExecutor",
                                               SingleThreadedExecutor),
                                              ("LeanExecutor", LeanExecutor))}
    finally:
        stop(subscribers)
        node.destroy_node()
        rclpy.try_shutdown()

    print(f"\npublish CPU per message [us], median / p90 ({args.messages} messages per cell, "
          f"{PUBLISH_PERIOD_S * 1000:g} ms apart), by subscriber processes:")
    print(f"{'message type (CDR bytes)':40s}"
          + "".join(f"{str(count) + ' subs':>14s}" for count in args.subscribers))
    for index, (label, _topic, _type, _qos) in enumerate(measured):
        cells = ("{:.0f} / {:.0f}".format(*results[count, index]) for count in args.subscribers)
        size = len(serialize_message(messages[index]))
        print(f"{f'{label} ({size})':40s}" + "".join(f"{cell:>14s}" for cell in cells))
    entities = next(iter(waits.values()))[1]
    print(f"\nexecutor spin_once(timeout_sec=0) with nothing ready, CPU per call [us] "
          f"({args.spins} calls; node: {entities}; {args.subscribers[-1]} subscriber "
          f"processes running):")
    for name, (samples, _entities) in waits.items():
        median, p90 = median_p90(samples)
        print(f"  {name:30s} median {median:6.1f}  p90 {p90:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
