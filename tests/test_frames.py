"""The frame tree's transforms (core/frames.py) and the TF messages built from them."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import TransformStamped

from em_exploration_ros.core.frames import map_in_world, odom_in_map
from em_exploration_ros.core.geometry import compose
from em_exploration_ros.nodes.conversions import quaternion_to_yaw, time_to_seconds
from em_exploration_ros.nodes.tf_publishing import (anchor_transform, robot_transforms,
                                                    tf_message, truth_transforms)


def _pose(transform: TransformStamped) -> np.ndarray:
    t = transform.transform
    return np.array([t.translation.x, t.translation.y, quaternion_to_yaw(t.rotation)])


def test_map_in_world_maps_the_anchor_onto_itself() -> None:
    anchor_in_map = np.array([1.0, -2.0, 0.3])
    shift = np.array([10.0, 5.0, -1.2])  # a map frame that is not the world frame
    anchor_in_world = compose(shift, anchor_in_map)
    np.testing.assert_allclose(map_in_world(anchor_in_world, anchor_in_map), shift, atol=1e-12)
    # In the simulation the anchor is the true launch pose: map coincides with world.
    np.testing.assert_allclose(map_in_world(anchor_in_map, anchor_in_map), np.zeros(3),
                               atol=1e-12)


def test_odom_in_map_composes_back_to_the_estimate() -> None:
    base_in_map = np.array([12.0, 30.0, 2.9])
    base_in_odom = np.array([11.5, 31.0, -3.0])
    correction = odom_in_map(base_in_map, base_in_odom)
    np.testing.assert_allclose(compose(correction, base_in_odom), base_in_map, atol=1e-12)


def test_tf_message_chains_every_robot_frame() -> None:
    base_in_map = np.array([3.0, 4.0, 0.5])
    base_in_odom = np.array([2.0, 4.5, 0.4])
    message = tf_message(12.4, [*robot_transforms(2, base_in_map, base_in_odom),
                                *truth_transforms([np.zeros(3), np.ones(3), base_in_map]),
                                anchor_transform(np.zeros(3), np.zeros(3))])
    by_child = {t.child_frame_id: t for t in message.transforms}
    assert {t.header.frame_id: t.child_frame_id for t in message.transforms
            if t.child_frame_id.startswith("robot_2/")} == {
        "map": "robot_2/odom", "robot_2/odom": "robot_2/base_link",
        "world": "robot_2/base_link_truth"}
    assert all(time_to_seconds(t.header.stamp) == 12.4 for t in message.transforms)
    chained = compose(_pose(by_child["robot_2/odom"]), _pose(by_child["robot_2/base_link"]))
    np.testing.assert_allclose(chained, base_in_map, atol=1e-12)
    np.testing.assert_allclose(_pose(by_child["robot_1/base_link_truth"]), np.ones(3),
                               atol=1e-12)
    assert by_child["map"].header.frame_id == "world"
