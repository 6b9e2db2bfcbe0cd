"""em-robot: one robot's process: team SLAM, virtual map, planner and motion control.

A thin shell around ``core.agent.robot_agent.RobotAgent``. Inputs: its own sonar and dead
reckoning from the world simulator, robot 0's launch pose (the mission's map anchor), and
its teammates' team updates. It never subscribes to ground truth. Besides its team
updates and what users see, it publishes its TF ``map`` -> ``robot_i/odom`` ->
``robot_i/base_link`` every step (nodes/tf_publishing.py).

Lockstep: each SonarScan carries the world's barrier (``team_sequences``). The node
processes a step only when it holds every teammate's updates up to the barrier, asking
for missing ones again (TeamUpdateRequest) while it waits; a teammate silent past
``barrier_timeout_s`` is skipped with a warning. In real-time mode the barrier is empty
and steps are processed as they come.

Run: ``python -m em_exploration_ros.nodes.robot_node --ros-args -r __ns:=/robot_0
-p robot_id:=0 -p use_sim_time:=true --params-file config/exploration.yaml``
"""
from __future__ import annotations

import sys
import time

import numpy as np
from em_exploration_msgs.msg import (LandmarkArray, MotionCommand, SonarScan, TeamUpdate,
                                     TeamUpdateRequest)
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from em_exploration_ros.core.virtual_map.cell_uncertainty import cell_covariances_from_poses
from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.agent.team_data import (InvalidTeamUpdate, LandmarkEstimate,
                                               TeamUpdateInbox)
from em_exploration_ros.core.sim.wire_model import (command_to_twist, sim_time_s,
                                                twist_to_increment_covariance)
from em_exploration_ros.nodes import tf_publishing, visualization
from em_exploration_ros.nodes.conversions import (MAP_FRAME, landmark_array_to_msg,
                                                  landmark_reading_from_msg,
                                                  odometry_pose, odometry_twist_covariance,
                                                  path_to_msg, quaternion_to_yaw,
                                                  robot_namespace, seconds_to_time,
                                                  team_update_from_msg, team_update_to_msg,
                                                  teammate_reading_from_msg, time_to_seconds)
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.qos import LATCHED_QOS, SENSOR_QOS, TEAM_QOS
from em_exploration_ros.nodes.ros_params import declare_exploration_params


class RobotNode(Node):
    """One robot of the team (see module docstring)."""

    def __init__(self) -> None:
        super().__init__("em_robot")
        self.robot_id = self.declare_parameter(
            "robot_id", 0, ParameterDescriptor(description="Id of this robot (0-based).",
                                               read_only=True)).value
        self.barrier_timeout_s = self.declare_parameter(
            "barrier_timeout_s", 10.0, ParameterDescriptor(
                description="Lockstep: wall seconds to wait for teammates' updates named by "
                "the world's barrier before going on without them.")).value
        self.request_period_s = self.declare_parameter(
            "request_period_s", 0.5, ParameterDescriptor(
                description="Wall seconds between two requests for missing team updates.")).value
        self.params = declare_exploration_params(self)
        self.num_robots = self.params.world.num_robots
        if not 0 <= self.robot_id < self.num_robots:
            raise ValueError(f"robot_id {self.robot_id} is not in 0..{self.num_robots - 1}")
        self.time_step_s = self.params.motion.time_step_s
        self.agent: RobotAgent | None = None
        self.inbox = TeamUpdateInbox(self.robot_id, self.num_robots)
        self.rejected_updates = 0
        self._scans: dict[int, SonarScan] = {}
        self._odometry: dict[int, Odometry] = {}
        self._next_step: int | None = None
        self._waiting_since: float | None = None
        self._last_request = 0.0
        self._barrier: dict[int, int] = {}
        self._create_interfaces()
        self.get_logger().info(
            f"robot {self.robot_id} of {self.num_robots} ready (planner "
            f"{self.params.planner.name}); waiting for the mission anchor and the world")

    def _create_interfaces(self) -> None:
        ns = robot_namespace(self.robot_id)
        self.command_pub = self.create_publisher(MotionCommand, f"/{ns}/motion_command",
                                                 SENSOR_QOS)
        self.update_pub = self.create_publisher(TeamUpdate, f"/{ns}/team/updates", TEAM_QOS)
        self.request_pub = self.create_publisher(TeamUpdateRequest, "/team/update_requests",
                                                 TEAM_QOS)
        self.path_pub = self.create_publisher(Path, f"/{ns}/estimated_path", LATCHED_QOS)
        self.landmarks_pub = self.create_publisher(LandmarkArray, f"/{ns}/landmarks",
                                                   LATCHED_QOS)
        self.grid_pub = self.create_publisher(OccupancyGrid, f"/{ns}/virtual_map", LATCHED_QOS)
        self.markers_pub = self.create_publisher(MarkerArray, f"/{ns}/markers", LATCHED_QOS)
        self.target_pub = self.create_publisher(PointStamped, f"/{ns}/target", LATCHED_QOS)
        self.tf_pub = tf_publishing.create_tf_publisher(self)
        self.create_subscription(PoseStamped, "/mission/anchor_pose", self._on_anchor,
                                 LATCHED_QOS)
        self.create_subscription(SonarScan, f"/{ns}/sonar", self._on_scan, SENSOR_QOS)
        self.create_subscription(Odometry, f"/{ns}/odom", self._on_odometry, SENSOR_QOS)
        self.create_subscription(TeamUpdateRequest, "/team/update_requests",
                                 self._on_update_request, TEAM_QOS)
        for teammate in range(self.num_robots):
            if teammate != self.robot_id:
                self.create_subscription(
                    TeamUpdate, f"/{robot_namespace(teammate)}/team/updates",
                    lambda message, sender=teammate: self._on_team_update(sender, message),
                    TEAM_QOS)
        # Wall (steady) time: in lockstep the sim clock stands still while the world waits.
        self.create_timer(0.1, self._maintain, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- callbacks -------------------------------------------------------------------------

    def _on_anchor(self, message: PoseStamped) -> None:
        if self.agent is not None:
            return
        p = message.pose
        anchor = np.array([p.position.x, p.position.y, quaternion_to_yaw(p.orientation)])
        if not np.all(np.isfinite(anchor)):
            self.get_logger().error(f"rejected a non-finite mission anchor {anchor.tolist()}")
            return
        self.agent = RobotAgent(self.robot_id, self.params, anchor)
        self.get_logger().info(f"map anchored at robot 0's launch pose {anchor.round(3).tolist()}")
        self._process_ready_steps()

    def _on_scan(self, message: SonarScan) -> None:
        if message.robot_id != self.robot_id:
            self.get_logger().warn(f"ignored a sonar scan addressed to robot {message.robot_id}")
            return
        if len(message.team_sequences) not in (0, self.num_robots):
            self.get_logger().warn(
                f"ignored scan {message.step}: {len(message.team_sequences)} barrier entries "
                f"for {self.num_robots} robots")
            return
        self._scans[int(message.step)] = message
        self._process_ready_steps()

    def _on_odometry(self, message: Odometry) -> None:
        step = int(round(time_to_seconds(message.header.stamp) / self.time_step_s))
        self._odometry[step] = message
        self._process_ready_steps()

    def _on_team_update(self, sender: int, message: TeamUpdate) -> None:
        try:
            self.inbox.receive(team_update_from_msg(message), sender)
        except InvalidTeamUpdate as error:
            self.rejected_updates += 1
            self.get_logger().warn(f"rejected a team update from /robot_{sender}: {error}")
            return
        self._process_ready_steps()

    def _on_update_request(self, message: TeamUpdateRequest) -> None:
        if message.robot_id != self.robot_id or self.agent is None:
            return
        resent = self.agent.outbox.resend(int(message.first_sequence), int(message.last_sequence))
        for update in resent:
            self.update_pub.publish(team_update_to_msg(update))
        if resent:
            self.get_logger().info(
                f"re-sent updates {resent[0].sequence}..{resent[-1].sequence} for robot "
                f"{message.requester_id}")

    def _maintain(self) -> None:
        """Ask again for missing team updates; give up waiting on silent teammates."""
        if self._waiting_since is None:
            return
        now = time.monotonic()
        if now - self._last_request >= self.request_period_s:
            self._last_request = now
            for gap in self.inbox.missing(self._barrier):
                request = TeamUpdateRequest(requester_id=self.robot_id, robot_id=gap.robot_id,
                                            first_sequence=gap.first_sequence,
                                            last_sequence=gap.last_sequence)
                request.header.stamp = self.get_clock().now().to_msg()
                self.request_pub.publish(request)
        if now - self._waiting_since > self.barrier_timeout_s:
            self.get_logger().warn(
                f"step {self._next_step}: teammates' updates {self._barrier} still missing "
                f"after {self.barrier_timeout_s} s; going on without them")
            self._barrier = {}
            self._process_ready_steps(ignore_barrier=True)

    # -- stepping ------------------------------------------------------------------------

    def _process_ready_steps(self, ignore_barrier: bool = False) -> None:
        """Process every step whose sensor data (and barrier) is complete, in order."""
        while self.agent is not None:
            if self._next_step is None and self._scans:
                self._next_step = min(self._scans)
            step = self._next_step
            if step is None or step not in self._scans or step not in self._odometry:
                return
            scan = self._scans[step]
            limits = {robot: int(seq) for robot, seq in enumerate(scan.team_sequences)
                      if robot != self.robot_id}
            if limits and not ignore_barrier and not self.inbox.holds_up_to(limits):
                if self._waiting_since is None:
                    self._waiting_since = time.monotonic()
                self._barrier = limits
                return
            self._waiting_since, ignore_barrier = None, False
            self._step(scan, self._odometry.pop(step), limits or None)
            del self._scans[step]
            self._next_step = step + 1

    def _step(self, scan: SonarScan, odometry: Odometry, limits: dict[int, int] | None) -> None:
        agent = self.agent
        step = int(scan.step)
        stamp_s = sim_time_s(step, self.time_step_s)
        agent.apply_team_updates(self.inbox.pop_ready(limits))
        decisions_before = len(agent.decisions)
        command = agent.step(StepInput(
            step, stamp_s, odometry_pose(odometry),
            twist_to_increment_covariance(odometry_twist_covariance(odometry), self.time_step_s),
            tuple(landmark_reading_from_msg(r) for r in scan.landmarks),
            tuple(teammate_reading_from_msg(r) for r in scan.teammates)))
        update = agent.take_outgoing()
        if update is not None:
            self.update_pub.publish(team_update_to_msg(update))
        self._publish_transforms(stamp_s, odometry)
        linear_x, angular_z = command_to_twist(command.turn_rad, command.forward_m,
                                               self.time_step_s)
        reply = MotionCommand(robot_id=self.robot_id, step=step,
                              team_sequence=agent.outbox.last_sequence, finished=command.finished)
        reply.header = scan.header
        reply.twist.linear.x, reply.twist.angular.z = linear_x, angular_z
        self.command_pub.publish(reply)
        if step % self.params.slam.keyframe_interval_steps == 0:
            self._publish_estimates(stamp_s)
        if len(agent.decisions) != decisions_before:
            self._publish_decision(stamp_s)

    # -- what users see --------------------------------------------------------------------

    def _publish_transforms(self, stamp_s: float, odometry: Odometry) -> None:
        """/tf ``map`` -> ``odom`` -> ``base_link`` of this step, once the robot is anchored."""
        pose = self.agent.current_pose()
        if pose is not None:
            self.tf_pub.publish(tf_publishing.tf_message(stamp_s, tf_publishing.robot_transforms(
                self.robot_id, pose, odometry_pose(odometry))))

    def _publish_estimates(self, stamp_s: float) -> None:
        agent = self.agent
        slam = agent.slam
        indices, poses = slam.trajectory(self.robot_id)
        interval = self.params.slam.keyframe_interval_steps
        stamps = [sim_time_s(int(i) * interval, self.time_step_s) for i in indices]
        self.path_pub.publish(path_to_msg(stamp_s, np.array(stamps), poses))
        landmarks = [LandmarkEstimate(lid, position, slam.landmark_covariance(lid))
                     for lid, position in sorted(slam.landmark_estimates().items())]
        self.landmarks_pub.publish(landmark_array_to_msg(
            stamp_s, MAP_FRAME, landmarks, self.params.world.landmark_radius_m))

    def _publish_decision(self, stamp_s: float) -> None:
        agent = self.agent
        target = agent.target
        if target is not None:
            point = PointStamped()
            point.header.stamp = seconds_to_time(stamp_s)
            point.header.frame_id = MAP_FRAME
            point.point.x, point.point.y = float(target.position[0]), float(target.position[1])
            self.target_pub.publish(point)
        self.grid_pub.publish(visualization.occupancy_grid_to_msg(agent.grid, stamp_s))
        slam = agent.slam
        robots = range(self.num_robots)
        poses = np.concatenate([slam.trajectory(robot)[1] for robot in robots])
        pose_covariances = np.concatenate([slam.trajectory_covariances(robot) for robot in robots])
        geometry = agent.grid.geometry
        covariances, observed = cell_covariances_from_poses(
            geometry, poses, pose_covariances, self.params.sensors, self.params.map)
        centres = geometry.cell_centers().reshape(-1, 2)[observed.ravel()]
        self.markers_pub.publish(visualization.marker_array(
            stamp_s,
            visualization.ellipse_markers(centres, covariances.reshape(-1, 2, 2)[observed.ravel()],
                                          stamp_s),
            visualization.frontier_markers(agent.last_candidates, target, stamp_s),
            visualization.landmark_markers(slam.landmark_estimates(),
                                           self.params.world.landmark_radius_m, stamp_s)))


def main(args: list[str] | None = None) -> int:
    """Entry point of em-robot; returns the exit code (2 for invalid parameters)."""
    return run_node(RobotNode, "em_robot", args)


if __name__ == "__main__":
    sys.exit(main())
