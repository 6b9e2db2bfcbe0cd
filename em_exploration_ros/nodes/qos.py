"""Quality-of-service profiles of the system's topics, each chosen for what the data is.

| profile | used for | why |
|---|---|---|
| ``SENSOR_QOS`` (reliable, keep last 50, volatile) | /robot_<i>/sonar, /robot_<i>/odom, /robot_<i>/motion_command | lockstep needs every step; a small queue absorbs bursts; old steps are useless to a late joiner |
| ``TEAM_QOS`` (reliable, keep all, volatile) | /robot_<i>/team/updates, /team/update_requests | team data must arrive; losses and late joins are repaired by the sequence-number resend protocol, so durability is not needed |
| ``LATCHED_QOS`` (reliable, keep last 1, transient local) | /world/landmarks, /robot_<i>/virtual_map, /robot_<i>/markers, /robot_<i>/target | state whose last value a late subscriber (RViz, Foxglove) needs at once |
| ``ESTIMATE_QOS`` (reliable, keep last ``ESTIMATE_DEPTH`` = 100, transient local) | /robot_<i>/estimated_path, /robot_<i>/landmarks | as latched, and a reader that matched late (the evaluator, when discovery packets were lost) still gets the estimates of the last 100 keyframes (200 simulated seconds), so its evaluations as of each keyframe are the same whatever the network did. 20 keyframes were too few once the lockstep team ran at 25x: when Fast DDS misses a participant's first announcements, the evaluator discovers the robots about 3 s (75 simulated seconds) late, and its first evaluation found no estimate of its keyframe left |
| ``ESTIMATE_READER_QOS`` (as ``ESTIMATE_QOS`` with depth ``GROUND_TRUTH_DEPTH``) | the evaluator's readers of /robot_<i>/estimated_path and /robot_<i>/landmarks | the lockstep world does not wait for the evaluator: a flooded or loaded evaluator fell more than 20 keyframes (40 simulated seconds) behind the robots, its keep-last-20 queue dropped the estimates it had not taken yet, and an evaluation read an older estimate; now it may lag as far behind on estimates as on ground truth |
| ``CLOCK_QOS`` (best effort, keep last 1) | /clock | the ROS 2 convention for /clock; only the newest time matters |
| ``TF_QOS``, ``TF_STATIC_QOS`` | /tf, /tf_static | tf2's own profiles (below), which every tf2 listener, RViz and Foxglove expect |
| ``LIVELINESS_QOS`` (reliable, keep last 1, volatile, automatic liveliness with a ``LIVELINESS_LEASE_S`` lease) | /robot_<i>/alive (no data) | the middleware asserts each robot process's liveliness; a process that dies, is stopped or wedges (its participant no longer asserts) is reported lost to the world, the teammates and the evaluator within the lease |
| ``GROUND_TRUTH_QOS`` (reliable, keep last ``GROUND_TRUTH_DEPTH`` = 3000, transient local) | /world/ground_truth/robot_<i> | the evaluator needs every true pose: from the first step even when its reader matched late (the world waits until the evaluator's subscriptions show in the graph, but under load the middleware matched them seconds later and the first steps were lost), and while it lags behind a fast lockstep world (a keep-last-100 queue lost 100 steps at a real-time factor of 7); 3000 steps are 600 s of simulation, about 2 MB per robot in the world |
| ``STREAM_QOS`` (reliable, keep all, volatile) | /evaluation/metrics | the evaluator's output stream: every sample for a live subscriber |
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
ESTIMATE_DEPTH = 100
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
#: Steps of ground truth the world keeps for a late or lagging reader.
GROUND_TRUTH_DEPTH = 3000
GROUND_TRUTH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=GROUND_TRUTH_DEPTH,
                              reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: The evaluator's readers of the estimates: as deep as its ground-truth reader (one estimate
#: per keyframe, at most one keyframe per step), so that it can lag as far behind.
ESTIMATE_READER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=GROUND_TRUTH_DEPTH,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: /tf as tf2's TransformBroadcaster offers it (reliable, keep last 100, volatile): transforms
#: that change are re-sent all the time, so a late subscriber only waits for the next ones.
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
#: /tf_static as tf2's StaticTransformBroadcaster offers it (reliable, transient local, keep
#: last 1): published once, kept for every late subscriber. The same profile as LATCHED_QOS.
TF_STATIC_QOS = LATCHED_QOS
LIVELINESS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE,
                            liveliness=LivelinessPolicy.AUTOMATIC,
                            liveliness_lease_duration=Duration(seconds=LIVELINESS_LEASE_S))
