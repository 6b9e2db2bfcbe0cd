"""Whether em-record listens to everything a node publishes.

Most of the system's topics are volatile: a subscription that matches late never gets what
was published before. A recording that holds a run from its first step therefore needs the
recorder subscribed to every topic of the world and of every robot before the first step
is published or answered (``wait_for_recorder`` of em-world and em-robot, set by
``run_team.sh --record``). em-record subscribes to topics as it discovers their publishers;
a node finds the recorder's subscriptions in the ROS graph by the recorder's node name.
"""
from __future__ import annotations

from rclpy.node import Node

#: The node name of em-record (``tools/record.py``).
RECORDER_NODE_NAME = "em_record"


def topics_not_recorded(node: Node) -> list[str]:
    """The topics ``node`` publishes on that no subscription of the recorder covers yet
    (as the node's graph shows them), sorted; empty once the recorder listens to all."""
    topics = sorted({publisher.topic_name for publisher in node.publishers})
    return [topic for topic in topics
            if not any(info.node_name == RECORDER_NODE_NAME
                       for info in node.get_subscriptions_info_by_topic(topic))]
