"""The TF tree of a recorded team run, decoded and checked (shared by the team tests).

For every robot the recording's /tf must hold, at the simulation time of each step the
robot processed, ``map`` -> ``robot_i/odom`` -> ``robot_i/base_link`` (one message, one
stamp), and the world's ``world`` -> ``robot_i/base_link_truth`` at the same stamps; with
/tf_static's ``world`` -> ``map`` the estimate chain lands next to the true pose.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rclpy.serialization import deserialize_message
from tf2_msgs.msg import TFMessage

from em_exploration_ros.bag_format.bag_reader import BagScanner
from em_exploration_ros.core.geometry import compose
from em_exploration_ros.nodes.conversions import quaternion_to_yaw

#: (parent frame, child frame) -> {stamp [ns]: pose (x, y, theta)}
Edges = dict[tuple[str, str], dict[int, np.ndarray]]


def recorded_transforms(bag: Path) -> tuple[Edges, Edges]:
    """The transforms of /tf and of /tf_static in a recording."""
    tf: Edges = {}
    static: Edges = {}
    for channel, message in BagScanner(bag).messages():
        if channel.topic not in ("/tf", "/tf_static"):
            continue
        edges = tf if channel.topic == "/tf" else static
        for t in deserialize_message(message.data, TFMessage).transforms:
            stamp = t.header.stamp.sec * 10**9 + t.header.stamp.nanosec
            pose = np.array([t.transform.translation.x, t.transform.translation.y,
                             quaternion_to_yaw(t.transform.rotation)])
            edges.setdefault((t.header.frame_id, t.child_frame_id), {})[stamp] = pose
    return tf, static


def assert_frame_chains(bag: Path, num_robots: int, max_error_m: float) -> None:
    """Every robot's estimate chain exists at every step (but the first) and lies within
    ``max_error_m`` of its true pose; the static world -> map is there."""
    tf, static = recorded_transforms(bag)
    [map_in_world] = static[("world", "map")].values()
    for robot in range(num_robots):
        odom, base, truth = (f"robot_{robot}/odom", f"robot_{robot}/base_link",
                             f"robot_{robot}/base_link_truth")
        corrections, dead_reckoning = tf[("map", odom)], tf[(odom, base)]
        true_poses = tf[("world", truth)]
        assert corrections.keys() == dead_reckoning.keys(), robot  # published together
        common = sorted(corrections.keys() & true_poses.keys())
        # Every step but possibly the first (a teammate of robot 0 has no map pose before
        # its first step is processed): the robots answer their first step only once the
        # recorder listens to all their topics (run_team.sh --record sets wait_for_recorder).
        assert len(common) >= len(true_poses) - 1 > 10, (robot, len(common), len(true_poses))
        errors = [np.hypot(*(compose(compose(map_in_world, corrections[t]),
                                     dead_reckoning[t])[:2] - true_poses[t][:2]))
                  for t in common]
        assert max(errors) <= max_error_m, (robot, max(errors))
