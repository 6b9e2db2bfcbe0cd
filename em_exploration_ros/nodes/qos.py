"""Quality-of-service profiles of the system's topics, each chosen for what the data is.

| profile | used for | why |
|---|---|---|
| ``SENSOR_QOS`` (reliable, keep last 50, volatile) | /robot_<i>/sonar, /robot_<i>/odom, /robot_<i>/motion_command | lockstep needs every step; a small queue absorbs bursts; old steps are useless to a late joiner |
| ``TEAM_QOS`` (reliable, keep all, volatile) | /robot_<i>/team/updates, /team/update_requests | team data must arrive; losses and late joins are repaired by the sequence-number resend protocol, so durability is not needed |
| ``LATCHED_QOS`` (reliable, keep last 1, transient local) | /world/landmarks, /robot_<i>/virtual_map, /robot_<i>/markers, /robot_<i>/target | state whose last value a late subscriber (RViz, Foxglove) needs at once |
| ``ESTIMATE_QOS`` (reliable, keep last ``ESTIMATE_DEPTH`` = 20, transient local) | /robot_<i>/estimated_path, /robot_<i>/landmarks | as latched, and a reader that matched late (the evaluator, when discovery packets were lost) still gets the estimates of the last 20 keyframes, so its evaluations as of each keyframe are the same whatever the network did |
| ``CLOCK_QOS`` (best effort, keep last 1) | /clock | the ROS 2 convention for /clock; only the newest time matters |
| ``LIVELINESS_QOS`` (reliable, keep last 1, volatile, automatic liveliness with a ``LIVELINESS_LEASE_S`` lease) | /robot_<i>/alive (no data) | the middleware asserts each robot process's liveliness; a process that dies, is stopped or wedges (its participant no longer asserts) is reported lost to the world, the teammates and the evaluator within the lease |
| ``STREAM_QOS`` (reliable, keep all, volatile) | /world/ground_truth/robot_<i>, /evaluation/metrics | evaluation streams: the evaluator needs every true pose even when it lags behind a fast lockstep world (a keep-last-100 queue lost 100 steps at a real-time factor of 7) |
"""
from rclpy.duration import Duration
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)

#: Lease of a robot's liveliness [s]: a robot whose participant did not assert liveliness
#: for this long is reported lost (Fast DDS asserts it at 2/3 of the lease).
LIVELINESS_LEASE_S = 3.0

SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
TEAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
#: Keyframes of estimates a late reader of ESTIMATE_QOS still gets.
ESTIMATE_DEPTH = 20
ESTIMATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=ESTIMATE_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)
STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
LIVELINESS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE,
                            liveliness=LivelinessPolicy.AUTOMATIC,
                            liveliness_lease_duration=Duration(seconds=LIVELINESS_LEASE_S))
