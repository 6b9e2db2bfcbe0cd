"""em-robot: one robot's process: team SLAM, virtual map, planner and motion control.

A thin shell around ``core.agent.robot_agent.RobotAgent``. Inputs: its own sonar and dead
reckoning from the world simulator, robot 0's launch pose (the mission's map anchor), and
its teammates' team updates. It never subscribes to ground truth.

Lockstep: each SonarScan carries the world's barrier (``team_sequences``). The node
processes a step only when it holds every teammate's updates up to the barrier, asking
for missing ones again (TeamUpdateRequest) while it waits; a teammate silent past
``barrier_timeout_s`` is skipped with a warning. In real-time mode the barrier is empty
and steps are processed as they come. A step the world sends again (its barrier repair) is
answered again with the same command.

Liveliness (``nodes/liveliness.py``): the node offers its own and logs a warning when a
teammate's is lost. Rejoin: a node whose first step is not step 0 was restarted after a
crash. It asks its teammates for its own earlier stream (``/team/update_requests`` with
itself as requester; each teammate re-sends what it holds on ``/robot_<i>/team/history``),
waits until it holds it up to the sequence number the world's barrier names for it, then
resumes (``RobotAgent.resume``): its graph, targets and numbering continue where its stream
left off and its published path holds its whole history.

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
from em_exploration_ros.core.agent.rejoin import (OwnHistoryRecovery, StreamArchive,
                                                  keyframe_ranges)
from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.agent.team_data import (InvalidTeamUpdate, LandmarkEstimate,
                                               TeamUpdateInbox)
from em_exploration_ros.core.sim.wire_model import (command_to_twist, sim_time_s,
                                                twist_to_increment_covariance)
from em_exploration_ros.nodes import visualization
from em_exploration_ros.nodes.conversions import (MAP_FRAME, landmark_array_to_msg,
                                                  landmark_reading_from_msg,
                                                  odometry_pose, odometry_twist_covariance,
                                                  path_to_msg, quaternion_to_yaw,
                                                  robot_namespace, seconds_to_time,
                                                  team_update_from_msg, team_update_to_msg,
                                                  teammate_reading_from_msg, time_to_seconds)
from em_exploration_ros.nodes.liveliness import offer_liveliness, watch_liveliness
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.qos import ESTIMATE_QOS, LATCHED_QOS, SENSOR_QOS, TEAM_QOS
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
        self.rejoin_settle_s = self.declare_parameter(
            "rejoin_settle_s", 1.0, ParameterDescriptor(
                description="After a restart: wall seconds to listen for teammates' copies of "
                "this robot's earlier stream before resuming.", read_only=True)).value
        self.rejoin_timeout_s = self.declare_parameter(
            "rejoin_timeout_s", 20.0, ParameterDescriptor(
                description="After a restart: wall seconds after which the robot resumes with "
                "what it recovered of its stream, even if records are missing.",
                read_only=True)).value
        self.params = declare_exploration_params(self)
        self.num_robots = self.params.world.num_robots
        if not 0 <= self.robot_id < self.num_robots:
            raise ValueError(f"robot_id {self.robot_id} is not in 0..{self.num_robots - 1}")
        self.time_step_s = self.params.motion.time_step_s
        self.agent: RobotAgent | None = None
        self.inbox = TeamUpdateInbox(self.robot_id, self.num_robots)
        self.archive = StreamArchive(self.robot_id, self.num_robots)
        self._recovery: OwnHistoryRecovery | None = None
        self._served_history: dict[int, float] = {}
        self._last_reply: MotionCommand | None = None
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
        self.path_pub = self.create_publisher(Path, f"/{ns}/estimated_path", ESTIMATE_QOS)
        self.landmarks_pub = self.create_publisher(LandmarkArray, f"/{ns}/landmarks",
                                                   ESTIMATE_QOS)
        self.grid_pub = self.create_publisher(OccupancyGrid, f"/{ns}/virtual_map", LATCHED_QOS)
        self.markers_pub = self.create_publisher(MarkerArray, f"/{ns}/markers", LATCHED_QOS)
        self.target_pub = self.create_publisher(PointStamped, f"/{ns}/target", LATCHED_QOS)
        self.create_subscription(PoseStamped, "/mission/anchor_pose", self._on_anchor,
                                 LATCHED_QOS)
        self.create_subscription(SonarScan, f"/{ns}/sonar", self._on_scan, SENSOR_QOS)
        self.create_subscription(Odometry, f"/{ns}/odom", self._on_odometry, SENSOR_QOS)
        self.create_subscription(TeamUpdateRequest, "/team/update_requests",
                                 self._on_update_request, TEAM_QOS)
        self.create_subscription(TeamUpdate, f"/{ns}/team/history", self._on_own_history,
                                 TEAM_QOS)
        teammates = [r for r in range(self.num_robots) if r != self.robot_id]
        self.history_pubs = {r: self.create_publisher(
            TeamUpdate, f"/{robot_namespace(r)}/team/history", TEAM_QOS) for r in teammates}
        for teammate in teammates:
            self.create_subscription(
                TeamUpdate, f"/{robot_namespace(teammate)}/team/updates",
                lambda message, sender=teammate: self._on_team_update(sender, message),
                TEAM_QOS)
        self.alive_pub = offer_liveliness(self, self.robot_id)
        watch_liveliness(self, teammates, self._on_teammate_liveliness)
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

    def _on_teammate_liveliness(self, teammate: int, alive: bool, restarted: bool) -> None:
        if alive:
            self.get_logger().info(f"teammate {teammate}: liveliness asserted"
                                   + (" by a new process (restarted)" if restarted else ""))
        else:
            self.get_logger().warn(f"teammate {teammate}: liveliness lost (process dead, stopped "
                                   f"or wedged, or its assertions lost on the network)")

    def _processed(self, step: int) -> bool:
        return self._next_step is not None and step < self._next_step

    def _on_scan(self, message: SonarScan) -> None:
        if message.robot_id != self.robot_id:
            self.get_logger().warn(f"ignored a sonar scan addressed to robot {message.robot_id}")
            return
        if self._processed(int(message.step)):
            # The world sent the step again: our answer did not arrive. Answer again.
            if self._last_reply is not None and self._last_reply.step == message.step:
                self.command_pub.publish(self._last_reply)
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
        if self._processed(step):
            return
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

    def _on_own_history(self, message: TeamUpdate) -> None:
        """A teammate's copy of one of this robot's earlier records (after a restart)."""
        if self._recovery is None:
            return
        try:
            self._recovery.receive(team_update_from_msg(message))
        except InvalidTeamUpdate as error:
            self.rejected_updates += 1
            self.get_logger().warn(f"rejected a relayed record of this robot's history: {error}")

    def _serve_history(self, requester: int) -> None:
        """Re-send what this robot holds of a restarted teammate's stream (at most once per
        ``request_period_s`` per teammate)."""
        now = time.monotonic()
        if now - self._served_history.get(requester, -float("inf")) < self.request_period_s:
            return
        self._served_history[requester] = now
        held = self.archive.held(requester)
        for update in held:
            self.history_pubs[requester].publish(team_update_to_msg(update))
        self.get_logger().info(f"robot {requester} restarted: re-sent the {len(held)} records "
                               f"of its stream this robot holds")

    def _on_update_request(self, message: TeamUpdateRequest) -> None:
        asker, owner = int(message.requester_id), int(message.robot_id)
        if asker == owner and asker in self.history_pubs:
            self._serve_history(asker)
            return
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
        """Ask again for missing team updates (or, after a restart, for this robot's own
        stream); give up waiting on silent teammates."""
        now = time.monotonic()
        if self._recovery is not None:
            if self._recovery.complete(now):
                self._process_ready_steps()
            elif self._recovery.short_of and now - self._last_request >= self.request_period_s:
                self._last_request = now
                self._request_own_history()
            return
        if self._waiting_since is None:
            return
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

    def _request_own_history(self) -> None:
        request = TeamUpdateRequest(requester_id=self.robot_id, robot_id=self.robot_id,
                                    first_sequence=1, last_sequence=0)
        request.header.stamp = self.get_clock().now().to_msg()
        self.request_pub.publish(request)

    def _start_recovery(self, scan: SonarScan) -> None:
        """This process starts in the middle of a run: it was restarted after a crash."""
        barrier = list(scan.team_sequences)
        needed = int(barrier[self.robot_id]) if barrier else 0
        now = time.monotonic()
        self._recovery = OwnHistoryRecovery(self.robot_id, self.num_robots, needed, now,
                                            self.rejoin_settle_s, self.rejoin_timeout_s)
        self.get_logger().warn(
            f"first step is {scan.step}, not 0: restarted in a running team; asking the "
            f"teammates for this robot's stream (the team holds it up to sequence {needed})")
        self._last_request = now
        self._request_own_history()

    def _resume(self) -> None:
        recovery, self._recovery = self._recovery, None
        history = recovery.history()
        if recovery.short_of:
            self.get_logger().error(
                f"resuming without {recovery.short_of} records of this robot's stream (up to "
                f"sequence {recovery.needed_sequence}): no teammate sent them")
        self.agent.resume(history)
        keyframes = np.array([keyframe.index for update in history
                              for keyframe in update.keyframes], dtype=int)
        self.get_logger().info(
            f"rejoined: recovered {len(history)} records of this robot's stream (keyframes "
            f"{keyframe_ranges(keyframes)}, {len(self.agent.decisions)} targets); continuing "
            f"at sequence {len(history) + 1}")

    def _process_ready_steps(self, ignore_barrier: bool = False) -> None:
        """Process every step whose sensor data (and barrier) is complete, in order."""
        while self.agent is not None:
            if self._next_step is None and self._scans:
                self._next_step = min(self._scans)
                if self._next_step > 0:
                    self._start_recovery(self._scans[self._next_step])
            if self._recovery is not None:
                if not self._recovery.complete(time.monotonic()):
                    return
                self._resume()
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
        released = self.inbox.pop_ready(limits)
        agent.apply_team_updates(released)
        self.archive.keep(released)
        decisions_before = len(agent.decisions)
        command = agent.step(StepInput(
            step, stamp_s, odometry_pose(odometry),
            twist_to_increment_covariance(odometry_twist_covariance(odometry), self.time_step_s),
            tuple(landmark_reading_from_msg(r) for r in scan.landmarks),
            tuple(teammate_reading_from_msg(r) for r in scan.teammates)))
        update = agent.take_outgoing()
        if update is not None:
            self.update_pub.publish(team_update_to_msg(update))
        linear_x, angular_z = command_to_twist(command.turn_rad, command.forward_m,
                                               self.time_step_s)
        reply = MotionCommand(robot_id=self.robot_id, step=step,
                              team_sequence=agent.outbox.last_sequence, finished=command.finished)
        reply.header = scan.header
        reply.twist.linear.x, reply.twist.angular.z = linear_x, angular_z
        self.command_pub.publish(reply)
        self._last_reply = reply
        if step % self.params.slam.keyframe_interval_steps == 0:
            self._publish_estimates(stamp_s)
        if len(agent.decisions) != decisions_before:
            self._publish_decision(stamp_s)

    # -- what users see --------------------------------------------------------------------

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
            visualization.ellipse_markers(centres, covariances.reshape(-1, 2, 2)[observed.ravel()],
                                          stamp_s),
            visualization.frontier_markers(agent.last_candidates, target, stamp_s),
            visualization.landmark_markers(slam.landmark_estimates(),
                                           self.params.world.landmark_radius_m, stamp_s)))

    def log_team_graph(self) -> None:
        """One line with the keyframes of every robot this robot's graph holds."""
        if self.agent is None:
            return
        parts = []
        for robot in range(self.num_robots):
            indices, _ = self.agent.slam.trajectory(robot)
            parts.append(f"robot {robot}: {keyframe_ranges(indices)}")
        self.get_logger().info("team graph keyframes: " + "; ".join(parts))


def main(args: list[str] | None = None) -> int:
    """Entry point of em-robot; returns the exit code (2 for invalid parameters)."""
    return run_node(RobotNode, "em_robot", args, wrap_up=_log_graph)


def _log_graph(node: RobotNode) -> int:
    """At the end (Ctrl-C, SIGTERM): what the team graph holds, for the run's logs."""
    node.log_team_graph()
    return 0


if __name__ == "__main__":
    sys.exit(main())
