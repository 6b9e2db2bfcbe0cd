"""Robot liveliness over DDS: each robot process offers it, the world, the teammates and
the evaluator watch it.

A robot creates a publisher on ``/robot_<i>/alive`` (std_msgs/Empty, never written) with
automatic liveliness and a ``LIVELINESS_LEASE_S`` lease (``nodes/qos.py``): its DDS
participant asserts it from the middleware's own threads, so a busy Python process stays
alive while a dead, stopped (SIGSTOP) or wedged one (a middleware deadlock) is reported
lost within the lease, before it even disappears from the graph. Watchers subscribe with
the same QoS and get a callback whenever a robot's liveliness changes; when it is gained
from a writer never seen before (its endpoint id in the graph) while one was seen earlier,
the robot's process was restarted (``core.agent.liveness.LivelinessWriters``: at most
``MAX_LIVELINESS_WRITERS`` writers remembered per robot, with one WARN when a flood of
identities makes it forget some).
"""
from __future__ import annotations

from typing import Callable

from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.event_handler import SubscriptionEventCallbacks
from std_msgs.msg import Empty

from em_exploration_ros.core.agent.liveness import LivelinessWriters
from em_exploration_ros.nodes.conversions import robot_namespace
from em_exploration_ros.nodes.qos import LIVELINESS_QOS


def alive_topic(robot: int) -> str:
    """The topic whose liveliness stands for robot ``robot``'s process."""
    return f"/{robot_namespace(robot)}/alive"


def offer_liveliness(node: Node, robot: int) -> Publisher:
    """The publisher that makes ``node`` count as robot ``robot``'s live process."""
    return node.create_publisher(Empty, alive_topic(robot), LIVELINESS_QOS)


def watch_liveliness(node: Node, robots: list[int],
                     on_change: Callable[[int, bool, bool], None]) -> None:
    """Call ``on_change(robot, alive, restarted)`` when a robot's liveliness is gained or
    lost; ``restarted``: gained from a new process of a robot seen before."""
    seen = LivelinessWriters(robots)
    for robot in robots:
        def changed(info, robot: int = robot) -> None:
            if info.alive_count_change > 0:
                restarted, note = seen.gained(robot, (
                    bytes(endpoint.endpoint_gid)
                    for endpoint in node.get_publishers_info_by_topic(alive_topic(robot))))
                if note is not None:
                    node.get_logger().warn(f"{alive_topic(robot)}: {note}")
                on_change(robot, True, restarted)
            elif info.alive_count_change < 0 or info.not_alive_count_change > 0:
                on_change(robot, info.alive_count > 0, False)
        node.create_subscription(
            Empty, alive_topic(robot), lambda _message: None, LIVELINESS_QOS,
            event_callbacks=SubscriptionEventCallbacks(liveliness=changed))
