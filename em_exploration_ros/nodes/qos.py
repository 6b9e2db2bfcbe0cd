"""Quality-of-service profiles of the system's topics, each chosen for what the data is.

| profile | used for | why |
|---|---|---|
| ``SENSOR_QOS`` (reliable, keep last 50, volatile) | /robot_<i>/sonar, /robot_<i>/odom, the world's reader of /robot_<i>/motion_command | lockstep needs every step; a small queue absorbs bursts; old steps are useless to a late joiner |
| ``COMMAND_QOS`` (reliable, keep last ``GROUND_TRUTH_DEPTH`` = 3000, transient local) | the robots' writers and the evaluator's readers of /robot_<i>/motion_command and /robot_<i>/landmark_correspondences | as ``SENSOR_QOS`` for the world (a volatile reader of a transient-local writer), and a restarted evaluator (``run_team.sh --respawn``) still gets each robot's answers since it died (their finished flags, the targets given up, the meetings: its summary's bookkeeping), as far back as the ground truth it gets |
| ``TEAM_QOS`` (reliable, keep last ``TEAM_DEPTH`` = 1000, volatile) | /robot_<i>/team/updates, /team/update_requests, /robot_<i>/team/history, the link relay's topics | team data must arrive; losses and late joins are repaired by the sequence-number resend protocol, so durability is not needed. The depth holds the largest burst one writer sends at once, a teammate's copy of a restarted robot's whole stream (one record per keyframe: 1000 records are 10000 steps at a keyframe every 10, 2000 simulated seconds; the default mission's stream is under 200 records, the 200 m one's under 600), and bounds what a flood leaves queued in each reader and writer (a flood that fills a reader's queue pushes its oldest records out; they are asked for again). Keep all was bounded only by Fast DDS's default resource limits (5000 samples): under em-fuzz on every topic (3000-3400 messages/s, team updates of up to 250 kB) the robots grew to 282-443 MB and the evaluator to 641 MB (docs/results.md, "Memory under a flood"), and a full writer refused publishes ("could not publish re-sent update" under a flood of well-formed requests) |
| ``LATCHED_QOS`` (reliable, keep last 1, transient local) | /world/landmarks, /robot_<i>/virtual_map, /robot_<i>/markers, /robot_<i>/target | state whose last value a late subscriber (RViz, Foxglove) needs at once |
| ``ESTIMATE_QOS`` (reliable, keep last ``ESTIMATE_DEPTH`` = 100, transient local) | /robot_<i>/estimated_path, /robot_<i>/landmarks, /robot_<i>/estimated_pose | as latched, and a reader that matched late (the evaluator, when discovery packets were lost) still gets the estimates of the last 100 keyframes (200 simulated seconds), so its evaluations as of each keyframe are the same whatever the network did. 20 keyframes were too few once the lockstep team ran at 25x: when Fast DDS misses a participant's first announcements, the evaluator discovers the robots about 3 s (75 simulated seconds) late, and its first evaluation found no estimate of its keyframe left |
| ``ESTIMATE_READER_QOS`` (as ``ESTIMATE_QOS`` with depth ``GROUND_TRUTH_DEPTH``) | the evaluator's readers of /robot_<i>/estimated_path, /robot_<i>/landmarks and /robot_<i>/estimated_pose | the lockstep world does not wait for the evaluator: a flooded or loaded evaluator fell more than 20 keyframes (40 simulated seconds) behind the robots, its keep-last-20 queue dropped the estimates it had not taken yet, and an evaluation read an older estimate; now it may lag as far behind on estimates as on ground truth |
| ``CLOCK_QOS`` (best effort, keep last 1) | /clock | the ROS 2 convention for /clock; only the newest time matters |
| ``TF_QOS``, ``TF_STATIC_QOS`` | /tf, /tf_static | tf2's own profiles (below), which every tf2 listener, RViz and Foxglove expect |
| ``LIVELINESS_QOS`` (reliable, keep last 1, volatile, automatic liveliness with a ``LIVELINESS_LEASE_S`` lease) | /robot_<i>/alive (no data) | the middleware asserts each robot process's liveliness; a process that dies, is stopped or wedges (its participant no longer asserts) is reported lost to the world, the teammates and the evaluator within the lease |
| ``GROUND_TRUTH_QOS`` (reliable, keep last ``GROUND_TRUTH_DEPTH`` = 3000, transient local) | /world/ground_truth/robot_<i>, /world/sonar_truth/robot_<i> (one per keyframe step) | the evaluator needs every true pose: from the first step even when its reader matched late (the world waits until the evaluator's subscriptions show in the graph, but under load the middleware matched them seconds later and the first steps were lost), and while it lags behind a fast lockstep world (a keep-last-100 queue lost 100 steps at a real-time factor of 7); 3000 steps are 600 s of simulation, about 2 MB per robot in the world |
| ``STREAM_QOS`` (reliable, keep last ``STREAM_DEPTH`` = 1000, volatile) | /evaluation/metrics | the evaluator's output stream: every sample for a live subscriber (one per evaluation, every 10 steps: 1000 samples are 10000 steps), bounded as ``TEAM_QOS`` is |

Every profile keeps a bounded number of samples (keep last): what a reader has not taken
yet and what a writer holds for its readers is at most the depth. The payloads themselves
are allocated per sample and freed when taken (``historyMemoryPolicy`` DYNAMIC in
config/fastdds_profiles.xml), so the memory a flood took is returned after it.
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
#: Team records (or requests) a reader or writer of the team topics holds at most.
TEAM_DEPTH = 1000
TEAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=TEAM_DEPTH,
                      reliability=ReliabilityPolicy.RELIABLE,
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
#: Metrics samples the evaluator's writer (and a reader) of /evaluation/metrics holds.
STREAM_DEPTH = 1000
STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: Steps of ground truth the world keeps for a late or lagging reader.
GROUND_TRUTH_DEPTH = 3000
#: A robot's answers (MotionCommand) its writer keeps for a late reader (a restarted
#: evaluator), as many steps as the ground truth.
COMMAND_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=GROUND_TRUTH_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
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
