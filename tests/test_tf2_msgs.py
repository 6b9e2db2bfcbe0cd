"""The venv's tf2_msgs (built from msg_schemas/tf2_msgs/ unless the environment provides one)
is ROS 2 Jazzy's: same type description hash, registered in the ament index, usable by rclpy."""
from __future__ import annotations

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from tf2_msgs.msg import TFMessage

from em_exploration_ros.bag_format.interface_index import read_type_hash
from em_exploration_ros.nodes.tf_publishing import tf_message, truth_transforms

TYPE = "tf2_msgs/msg/TFMessage"
#: The hash a ROS 2 Jazzy node reports for /tf (`ros2 topic info /tf --verbose`).
JAZZY_TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_type_hash_equals_upstream() -> None:
    assert read_type_hash(TYPE) == JAZZY_TFMESSAGE_HASH
    # rosbags computes the hash independently from its own copy of Jazzy's definitions.
    assert get_typestore(Stores.ROS2_JAZZY).hash_rihs01(TYPE) == JAZZY_TFMESSAGE_HASH


def test_registered_and_round_trips() -> None:
    definition = Path(get_package_share_directory("tf2_msgs")) / "msg" / "TFMessage.msg"
    assert "geometry_msgs/TransformStamped[] transforms" in definition.read_text()
    message = tf_message(3.2, truth_transforms([[1.0, 2.0, 0.5], [4.0, 5.0, -1.0]]))
    assert deserialize_message(serialize_message(message), TFMessage) == message
