"""What a robot publishes (ROS side), when its session asks (``core.sessions.robot_effects``):
its MotionCommand, team updates, requests and copies of a restarted teammate's records, and
what users and the evaluator see: its TF, estimated path, landmarks and latest keyframe's
pose with its marginal covariance (``estimated_pose``) at keyframe steps, and the target,
virtual map and markers of each new decision, from the robot's ``RobotAgent``; without
landmark identities, the teammates' landmarks it tied to its own
(``landmark_correspondences``, for the evaluator's association counts).

Messages only users look at (transforms, target, grid, markers) are built only when someone
subscribes; the markers cost a robot more CPU than its decision, and a viewer that
subscribes later gets the next decision's.
"""
from __future__ import annotations

import numpy as np
from em_exploration_msgs.msg import (LandmarkArray, LandmarkCorrespondences, MotionCommand,
                                     TeamUpdate, TeamUpdateRequest)
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Path
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from em_exploration_ros.core.agent.robot_agent import RobotAgent
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.records.team_data import LandmarkEstimate
from em_exploration_ros.core.records.team_data import TeamUpdate as TeamRecord
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.records.wire_model import sim_time_s
from em_exploration_ros.core.sessions.robot_effects import (CommandReply, KeyframeEstimate,
                                                            PublishCorrespondences)
from em_exploration_ros.core.virtual_map.cell_uncertainty import cell_covariances_from_poses
from em_exploration_ros.nodes import tf_publishing, visualization
from em_exploration_ros.nodes.conversions import (MAP_FRAME, given_up_to_msg,
                                                  keyframe_estimate_to_msg,
                                                  landmark_array_to_msg, meeting_to_msg,
                                                  robot_namespace, seconds_to_time,
                                                  serialized_path,
                                                  team_update_to_msg)
from em_exploration_ros.nodes.input_guard import listened, publish_or_log
from em_exploration_ros.nodes.qos import COMMAND_QOS, ESTIMATE_QOS, LATCHED_QOS, TEAM_QOS
from em_exploration_ros.nodes.team_topics import history_copies_topic


class RobotOutputs:
    """The publishers of robot ``robot_id`` (module docstring); ``relay_mode``: copies of a
    teammate's records go through the link relay."""

    def __init__(self, node: Node, robot_id: int, params: ExplorationParams,
                 wire: TeamWireFormat, relay_mode: bool, run_id: int) -> None:
        ns = robot_namespace(robot_id)
        self._node = node
        self._run_id = run_id  # carried by every project message it publishes
        self._robot_id = robot_id
        self._params = params
        self._wire = wire
        self.command_pub = node.create_publisher(MotionCommand, f"/{ns}/motion_command",
                                                 COMMAND_QOS)
        # Only without landmark identities does a robot tie teammates' landmarks to its own.
        self.correspondences_pub = None if params.sensors.landmark_ids else node.create_publisher(
            LandmarkCorrespondences, f"/{ns}/landmark_correspondences", COMMAND_QOS)
        self.update_pub = node.create_publisher(TeamUpdate, f"/{ns}/team/updates", TEAM_QOS)
        self.request_pub = node.create_publisher(TeamUpdateRequest, "/team/update_requests",
                                                 TEAM_QOS)
        teammates = [r for r in range(params.world.num_robots) if r != robot_id]
        self._copies_pub = (node.create_publisher(TeamUpdate, history_copies_topic(robot_id),
                                                  TEAM_QOS) if relay_mode else None)
        self._history_pubs = {} if relay_mode else {
            r: node.create_publisher(TeamUpdate, f"/{robot_namespace(r)}/team/history",
                                     TEAM_QOS) for r in teammates}
        self.path_pub = node.create_publisher(Path, f"/{ns}/estimated_path", ESTIMATE_QOS)
        self.pose_pub = node.create_publisher(PoseWithCovarianceStamped,
                                              f"/{ns}/estimated_pose", ESTIMATE_QOS)
        self.landmarks_pub = node.create_publisher(LandmarkArray, f"/{ns}/landmarks",
                                                   ESTIMATE_QOS)
        self.grid_pub = node.create_publisher(OccupancyGrid, f"/{ns}/virtual_map", LATCHED_QOS)
        self.markers_pub = node.create_publisher(MarkerArray, f"/{ns}/markers", LATCHED_QOS)
        self.target_pub = node.create_publisher(PointStamped, f"/{ns}/target", LATCHED_QOS)
        self.tf_pub = tf_publishing.create_tf_publisher(node)

    def command(self, reply: CommandReply, again: bool) -> None:
        """The MotionCommand answering a step (``again``: once more)."""
        message = MotionCommand(
            run_id=self._run_id, robot_id=reply.robot_id, step=reply.step,
            team_sequence=reply.team_sequence,
            team_messages=reply.team_messages, team_requests=reply.team_requests,
            finished=reply.finished, blocked_s=reply.blocked_s,
            given_up_count=reply.given_up_count,
            given_up=[given_up_to_msg(g) for g in reply.given_up],
            slam_recoveries=reply.slam_recoveries,
            meetings=[meeting_to_msg(m) for m in reply.meetings])
        message.header.stamp.sec, message.header.stamp.nanosec = reply.stamp
        message.header.frame_id = f"{robot_namespace(self._robot_id)}/base_link"
        message.twist.linear.x, message.twist.angular.z = reply.linear_x, reply.angular_z
        publish_or_log(self.command_pub, message, self._node,
                       f"the command of step {reply.step}" + (" again" if again else ""))

    def correspondences(self, effect: PublishCorrespondences) -> None:
        """The teammates' landmarks tied to own ones while answering a step (evaluator)."""
        message = LandmarkCorrespondences(
            run_id=self._run_id, robot_id=self._robot_id, step=effect.step,
            own_landmark_ids=[int(own) for own, _ in effect.pairs],
            teammate_landmark_ids=[int(theirs) for _, theirs in effect.pairs])
        message.header.stamp.sec, message.header.stamp.nanosec = effect.stamp
        message.header.frame_id = MAP_FRAME
        publish_or_log(self.correspondences_pub, message, self._node,
                       f"the landmark correspondences of step {effect.step}")

    def update(self, record: TeamRecord, what: str) -> None:
        """A record of this robot's stream on its update topic."""
        publish_or_log(self.update_pub, self._record_msg(record), self._node, what)

    def request(self, owner: int, first_sequence: int, last_sequence: int) -> None:
        """A request to robot ``owner`` for records ``first..last`` of its stream."""
        request = TeamUpdateRequest(run_id=self._run_id, requester_id=self._robot_id,
                                    robot_id=owner,
                                    first_sequence=first_sequence, last_sequence=last_sequence)
        request.header.stamp = self._node.get_clock().now().to_msg()
        publish_or_log(self.request_pub, request, self._node, "a request for team updates")

    def history(self, requester: int, records: tuple[TeamRecord, ...]) -> None:
        """Copies of a restarted teammate's records (through the relay in relay mode)."""
        publisher = (self._history_pubs[requester] if self._copies_pub is None
                     else self._copies_pub)
        for record in records:
            publish_or_log(publisher, self._record_msg(record), self._node,
                           f"robot {requester}'s record {record.sequence}")

    def _record_msg(self, record: TeamRecord) -> TeamUpdate:
        """A record of the team stream as the message of this run."""
        message = team_update_to_msg(record, self._wire)
        message.run_id = self._run_id
        return message

    def transforms(self, agent: RobotAgent, stamp_s: float, odom_pose: np.ndarray) -> None:
        """/tf ``map`` -> ``odom`` -> ``base_link`` of a step (sim time ``stamp_s``), once
        the robot is anchored."""
        pose = agent.current_pose()
        if pose is not None and listened(self.tf_pub):
            transforms = tf_publishing.robot_transforms(self._robot_id, pose, odom_pose)
            publish_or_log(self.tf_pub, tf_publishing.tf_message(stamp_s, transforms),
                           self._node, "the robot's transforms")

    def estimates(self, agent: RobotAgent, stamp_s: float,
                  latest: KeyframeEstimate | None) -> None:
        """The robot's latest keyframe with its covariance (first: the evaluator waits for
        the path and landmarks, then for it), estimated path (every keyframe) and
        landmarks."""
        if latest is not None:
            self.pose_pub.publish(keyframe_estimate_to_msg(latest))
        slam = agent.slam
        indices, poses = slam.trajectory(self._robot_id)
        interval = self._params.slam.keyframe_interval_steps
        time_step_s = self._params.motion.time_step_s
        stamps = [sim_time_s(int(i) * interval, time_step_s) for i in indices]
        self.path_pub.publish(serialized_path(stamp_s, np.array(stamps), poses))
        landmarks = [LandmarkEstimate(lid, position, slam.landmark_covariance(lid))
                     for lid, position in sorted(slam.landmark_estimates().items())]
        self.landmarks_pub.publish(landmark_array_to_msg(
            stamp_s, MAP_FRAME, landmarks, self._params.world.landmark_radius_m))

    def decision(self, agent: RobotAgent, stamp_s: float) -> None:
        """The target, the virtual map and the markers of a new decision, each only if
        someone subscribes."""
        target = agent.target
        if target is not None and listened(self.target_pub):
            point = PointStamped()
            point.header.stamp = seconds_to_time(stamp_s)
            point.header.frame_id = MAP_FRAME
            point.point.x, point.point.y = float(target.position[0]), float(target.position[1])
            self.target_pub.publish(point)
        if listened(self.grid_pub):
            self.grid_pub.publish(visualization.occupancy_grid_to_msg(agent.grid, stamp_s))
        if listened(self.markers_pub):
            self._markers(agent, stamp_s, target)

    def _markers(self, agent: RobotAgent, stamp_s: float, target: Frontier | None) -> None:
        """Covariance ellipses of the virtual map's cells, frontiers and landmarks."""
        slam = agent.slam
        robots = range(self._params.world.num_robots)
        poses = np.concatenate([slam.trajectory(robot)[1] for robot in robots])
        pose_covariances = np.concatenate([slam.trajectory_covariances(robot) for robot in robots])
        geometry = agent.grid.geometry
        covariances, observed = cell_covariances_from_poses(
            geometry, poses, pose_covariances, self._params.sensors, self._params.map)
        centres = geometry.cell_centers().reshape(-1, 2)[observed.ravel()]
        self.markers_pub.publish(visualization.marker_array(
            stamp_s,
            visualization.ellipse_markers(centres, covariances.reshape(-1, 2, 2)[observed.ravel()],
                                          stamp_s),
            visualization.frontier_markers(agent.last_candidates, target, stamp_s),
            visualization.landmark_markers(slam.landmark_estimates(),
                                           self._params.world.landmark_radius_m, stamp_s)))
