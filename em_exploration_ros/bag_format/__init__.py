"""ROS-free reading and writing of rosbag2-compatible MCAP recordings.

The modules here follow the conventions of rosbag2's MCAP storage plugin (ROS 2 Jazzy):
header profile ``ros2``, one ``ros2msg`` schema per message type holding the complete
definition text, ``cdr`` channels whose metadata carries ``offered_qos_profiles`` and
``topic_type_hash``, and a ``rosbag2`` metadata record with the serialized bag metadata.
Nothing in this package imports rclpy; the ROS side lives in ``em_exploration_ros.tools``.
"""
