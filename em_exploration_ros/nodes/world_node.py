"""em-world: the world simulator node, a thin shell around ``core.world.simulation.WorldSimulation``.

It is the system's clock and its only source of ground truth. Topics (QoS from nodes/qos.py):

- ``/clock`` (rosgraph_msgs/Clock): the simulation time of the current step;
- ``/mission/anchor_pose`` (PoseStamped, latched, frame ``map``): robot 0's launch pose;
- ``/tf_static`` ``world`` -> ``map`` (from the anchor) and ``/tf`` ``world`` ->
  ``robot_i/base_link_truth`` every step (nodes/tf_publishing.py);
- per robot i: ``/robot_i/sonar`` (SonarScan), ``/robot_i/odom`` (Odometry, REP-105
  ``robot_i/odom`` -> ``robot_i/base_link``), subscribes ``/robot_i/motion_command``;
- ground truth, under ``/world`` only: ``/world/ground_truth/robot_i`` (Odometry, frame
  ``world``, every step), ``/world/landmarks`` (LandmarkArray, latched) and
  ``/world/markers`` (MarkerArray, latched: landmarks and the map border).

Lockstep mode (default): once every robot is connected (and the evaluator and the recorder
listen, if required), for ``startup_settle_s`` (or ``startup_timeout_s`` passed),
step k publishes /clock, every robot's sonar (with the barrier ``team_sequences``) and
odometry, and the ground truth; it then waits until every live robot has answered step k
with a MotionCommand (``core.sessions.lockstep.LockstepBarrier``). A robot whose answer is
missing gets the step's sensor messages again every ``step_resend_s`` (the same messages,
so a missed start or a lost packet changes nothing), after the step's /clock again; a robot
still silent after ``robot_timeout_s`` wall seconds (``liveliness_grace_s`` once its
liveliness lease expired, ``nodes/liveliness.py``) is *lost*: the world logs ``robot <i>
lost: <why>`` and stops waiting for it (zero motion). A lost robot that answers again
(recovered, or restarted with the same id) rejoins at the pose where its vehicle stopped.
The commands are applied in robot id order and the world advances: the same order as
``core.sessions.team_runner.TeamRunner.step_once``, so em-sim and the ROS system draw the same
noise.

Relay mode (``links.*`` not perfect): the world is also the link relay between the robots
(``nodes/team_relay.py``): it hears their team data, closes step k only once it heard
every team message the answers count, transmits step k's frames with the true positions
of step k, and delivers what arrives before publishing step k+1 (whose SonarScan carries
the delivery counts).

Real-time mode: a wall timer advances the world every ``time_step_s / realtime_factor``
seconds with each robot's latest command (none yet: stand still); no barrier.

Stepping ends at the run's final step (``final_step``) or when every robot finished or
stopped; the node keeps spinning so late subscribers still get the latched topics.

Run: ``python -m em_exploration_ros.nodes.world_node --ros-args --params-file
config/exploration.yaml -p world.num_robots:=3``
"""
from __future__ import annotations

import sys
import time

import numpy as np
from em_exploration_msgs.msg import LandmarkArray, MotionCommand, SonarScan, WorldStatus
from geometry_msgs.msg import Point, PoseStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from em_exploration_ros.core.agent.liveness import UnseenLiveliness
from em_exploration_ros.core.agent.input_checks import command_problem, command_sequence_problem
from em_exploration_ros.core.records.team_data import MAX_SEQUENCE_LEAD
from em_exploration_ros.core.node_settings import LOCKSTEP, REALTIME, WorldNodeSettings
from em_exploration_ros.core.evaluation.run_monitor import final_step
from em_exploration_ros.core.links.link_model import perfect_links
from em_exploration_ros.core.sessions.lockstep import STAND_STILL, LockstepBarrier, StepAnswer
from em_exploration_ros.core.world.simulation import WorldSimulation
from em_exploration_ros.core.records.team_data import LandmarkEstimate
from em_exploration_ros.core.world.world import World
from em_exploration_ros.nodes.conversions import (MAP_FRAME, WORLD_FRAME, WORLD_NODE_NAME,
                                                  WORLD_STATUS_TOPIC,
                                                  landmark_array_to_msg, robot_namespace,
                                                  seconds_to_time, serialized_dead_reckoning,
                                                  serialized_odometry, sonar_scan_to_msg,
                                                  yaw_to_quaternion)
from em_exploration_ros.nodes import tf_publishing
from em_exploration_ros.nodes.lean_node import LeanNode
from em_exploration_ros.nodes.liveliness import watch_liveliness
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.recorder_presence import topics_not_recorded
from em_exploration_ros.nodes.qos import (CLOCK_QOS, GROUND_TRUTH_QOS, LATCHED_QOS,
                                          LIVELINESS_LEASE_S, SENSOR_QOS)
from em_exploration_ros.nodes.input_guard import (InputGuard, content_problem, header_problem,
                                                  listened)
from em_exploration_ros.nodes.ros_params import (declare_exploration_params,
                                                 declare_node_settings, refuse_unknown_overrides)
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.nodes.team_relay import TeamRelay

#: Wall period of the timer that checks start-up connections and robot timeouts [s].
_POLL_PERIOD_S = 0.05
#: A progress line every this many steps.
_LOG_EVERY_STEPS = 500
#: Height of the landmark cylinders drawn in /world/markers [m].
_MARKER_HEIGHT_M = 1.0



def world_markers(world: World, stamp_s: float) -> MarkerArray:
    """Landmarks as cylinders (true radius) and the mission border, frame ``world``."""
    def marker(marker_id: int, marker_type: int, rgba: tuple[float, ...]) -> Marker:
        m = Marker(ns="world", id=marker_id, type=marker_type, action=Marker.ADD)
        m.header.stamp = seconds_to_time(stamp_s)
        m.header.frame_id = WORLD_FRAME
        m.color = ColorRGBA(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
        m.pose.orientation.w = 1.0
        return m

    border = marker(0, Marker.LINE_STRIP, (0.2, 0.2, 0.2, 1.0))
    border.scale.x = 0.2
    corners = [(0.0, 0.0), (world.width_m, 0.0), (world.width_m, world.height_m),
               (0.0, world.height_m), (0.0, 0.0)]
    border.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in corners]
    markers = [border]
    diameter = 2.0 * max(world.landmark_radius_m, 0.05)
    for landmark_id, (x, y) in zip(world.landmark_ids, world.landmarks):
        cylinder = marker(1 + int(landmark_id), Marker.CYLINDER, (0.45, 0.3, 0.15, 1.0))
        cylinder.pose.position.x, cylinder.pose.position.y = float(x), float(y)
        cylinder.pose.position.z = _MARKER_HEIGHT_M / 2.0
        cylinder.scale.x = cylinder.scale.y = diameter
        cylinder.scale.z = _MARKER_HEIGHT_M
        markers.append(cylinder)
    return MarkerArray(markers=markers)


class WorldNode(LeanNode):
    """The world simulator (see module docstring)."""

    def __init__(self) -> None:
        super().__init__(WORLD_NODE_NAME)
        self.inputs = InputGuard(self)
        install_validated_clock(self, self.inputs)
        self.settings = declare_node_settings(self, WorldNodeSettings)
        self.clock_mode = self.settings.clock_mode
        self.realtime_factor = self.settings.realtime_factor
        self.startup_timeout_s = self.settings.startup_timeout_s
        self.startup_settle_s = self.settings.startup_settle_s
        self.wait_for_evaluator = self.settings.wait_for_evaluator
        robot_timeout_s, max_sim_time_s = (self.settings.robot_timeout_s,
                                           self.settings.max_sim_time_s)
        liveliness_grace_s = self.settings.liveliness_grace_s
        step_resend_s = self.settings.step_resend_s
        self.wait_for_recorder = self.settings.wait_for_recorder
        self.params = declare_exploration_params(self)
        refuse_unknown_overrides(self)
        self.num_robots = self.params.world.num_robots
        self.final_step = final_step(self.params, max_sim_time_s)
        self.sim = WorldSimulation(self.params)
        self.barrier = LockstepBarrier(self.num_robots, robot_timeout_s, step_resend_s,
                                       liveliness_grace_s)
        #: Per robot, the current step's sonar scan and serialized dead reckoning.
        self._step_messages: list[tuple[SonarScan, bytes] | None] = [None] * self.num_robots
        self._unseen = UnseenLiveliness(self.num_robots, LIVELINESS_LEASE_S)
        self._latest = [STAND_STILL] * self.num_robots
        self.running = False
        self.stepping_over = False
        self._started_wall_s = time.monotonic()
        self._ready_since_s: float | None = None
        self._frames_wait_since_s: float | None = None
        self._team_lost_since_s: float | None = None
        self.relay = (None if perfect_links(self.params.links) else
                      TeamRelay(self, self.params, self.inputs, lambda: self.sim.step,
                                self._check_step_complete))
        self._create_interfaces()
        self._publish_mission()
        self._poll_timer = self.create_timer(_POLL_PERIOD_S, self._poll)
        self._tick_timer = None
        self.get_logger().info(
            f"world ready: {self.num_robots} robots, {self.sim.world.num_landmarks} landmarks, "
            f"{self.params.world.width_m:g} m x {self.params.world.height_m:g} m, seed "
            f"{self.params.run.seed}, {self.clock_mode}"
            + ("" if self.relay is None else f", team data relayed through the link model "
               f"({self.params.links})")
            + "; waiting for the robots to connect")

    def _create_interfaces(self) -> None:
        self.clock_pub = self.create_publisher(Clock, "/clock", CLOCK_QOS)
        self.anchor_pub = self.create_publisher(PoseStamped, "/mission/anchor_pose", LATCHED_QOS)
        self.landmarks_pub = self.create_publisher(LandmarkArray, "/world/landmarks",
                                                   LATCHED_QOS)
        self.markers_pub = self.create_publisher(MarkerArray, "/world/markers", LATCHED_QOS)
        self.status_pub = self.create_publisher(WorldStatus, WORLD_STATUS_TOPIC, LATCHED_QOS)
        self.tf_pub = tf_publishing.create_tf_publisher(self)
        self.tf_static_pub = tf_publishing.create_tf_static_publisher(self)
        self.sonar_pubs, self.odom_pubs, self.truth_pubs, self.command_subs = [], [], [], []
        for robot in range(self.num_robots):
            ns = robot_namespace(robot)
            self.sonar_pubs.append(self.create_publisher(SonarScan, f"/{ns}/sonar", SENSOR_QOS))
            self.odom_pubs.append(self.create_publisher(Odometry, f"/{ns}/odom", SENSOR_QOS))
            self.truth_pubs.append(self.create_publisher(
                Odometry, f"/world/ground_truth/{ns}", GROUND_TRUTH_QOS))
            self.command_subs.append(self.create_subscription(
                MotionCommand, f"/{ns}/motion_command",
                lambda message, robot=robot: self._on_command(robot, message), SENSOR_QOS))
        watch_liveliness(self, list(range(self.num_robots)), self._on_liveliness)

    def _publish_mission(self) -> None:
        """The latched mission set-up at the first step's time: robot 0's launch pose, the
        landmarks, the markers, and the static ``world`` -> ``map`` transform it defines."""
        world = self.sim.world
        stamp_s = self.sim.stamp_s
        anchor = PoseStamped()
        anchor.header.stamp = seconds_to_time(stamp_s)
        anchor.header.frame_id = MAP_FRAME
        start = world.start_poses[0]
        anchor.pose.position.x, anchor.pose.position.y = float(start[0]), float(start[1])
        anchor.pose.orientation = yaw_to_quaternion(float(start[2]))
        self.anchor_pub.publish(anchor)
        self.tf_static_pub.publish(tf_publishing.tf_message(
            stamp_s, [tf_publishing.anchor_transform(start, start)]))
        landmarks = [LandmarkEstimate(int(i), p, np.zeros((2, 2)))
                     for i, p in zip(world.landmark_ids, world.landmarks)]
        self.landmarks_pub.publish(landmark_array_to_msg(stamp_s, WORLD_FRAME, landmarks,
                                                         world.landmark_radius_m))
        self.markers_pub.publish(world_markers(world, stamp_s))

    # -- start-up ---------------------------------------------------------------------------

    def robot_started(self, robot: int) -> bool:
        """True when robot ``robot``'s node runs: it listens to its sensors (and, in relay
        mode, to what the links deliver to it) and publishes its commands."""
        return ((self.relay is None or self.relay.robot_listens(robot))
                and self.sonar_pubs[robot].get_subscription_count() >= 1
                and self.odom_pubs[robot].get_subscription_count() >= 1
                and self.command_subs[robot].get_publisher_count() >= 1)

    def robot_connected(self, robot: int) -> bool:
        """True when robot ``robot`` runs and its team updates have their listeners (the
        teammates, plus the evaluator if required)."""
        teammates = self.num_robots - 1 if self.relay is None else 1  # relay: the world hears
        listeners = teammates + (1 if self.wait_for_evaluator else 0)
        return (self.robot_started(robot) and self.count_subscribers(
            f"/{robot_namespace(robot)}/team/updates") >= listeners)

    def _evaluator_connected(self) -> bool:
        return all(pub.get_subscription_count() >= 1 for pub in self.truth_pubs)

    def _observers_connected(self) -> bool:
        return ((not self.wait_for_evaluator or self._evaluator_connected())
                and (not self.wait_for_recorder or not topics_not_recorded(self)))

    def _try_start(self) -> None:
        connected = [self.robot_connected(r) for r in range(self.num_robots)]
        ready = all(connected) and self._observers_connected()
        now = time.monotonic()
        if not ready:
            self._ready_since_s = None
        elif self._ready_since_s is None:
            self._ready_since_s = now
        waited = now - self._started_wall_s
        settled = ready and now - self._ready_since_s >= self.startup_settle_s
        if not settled and waited < self.startup_timeout_s:
            return
        # Only a robot that does not run is missing; one whose team updates lack a listener
        # only because a teammate is missing goes on.
        missing = [r for r in range(self.num_robots) if not self.robot_started(r)]
        if missing:
            for robot in missing:  # run_team.sh --respawn restarts each (a wedged start)
                self._log_lost(robot, f"not connected after {self.startup_timeout_s:g} s "
                                      f"(treated as stopped)")
            self.barrier.stop(missing)
        if not self._observers_connected():
            self.get_logger().warn("the evaluator or the recorder does not listen yet; "
                                   "starting anyway")
        self.running = True
        self._unseen.first_step(now)
        self.get_logger().info(f"all set after {waited:.1f} s: stepping ({self.clock_mode})")
        self._publish_status(False, f"stepping ({self.clock_mode})")
        self._publish_step()
        if self.clock_mode == REALTIME:
            period = self.params.motion.time_step_s / self.realtime_factor
            self._tick_timer = self.create_timer(period, self._realtime_tick)
        else:
            self._check_step_complete()

    # -- stepping ---------------------------------------------------------------------------

    def _poll(self) -> None:
        """Start-up: wait for the connections; lockstep: enforce the robot timeout."""
        if not self.running:
            self._try_start()
            return
        if self.stepping_over or self.clock_mode == REALTIME:
            self._poll_timer.cancel()
            return
        now = time.monotonic()
        self._suspect_the_unseen(now)
        due = self.barrier.due_for_resend(now)
        if due:
            # /clock is best effort: a robot stopped while the world went on without it
            # missed every tick, and resumes only at a step the world's clock reached.
            self.clock_pub.publish(Clock(clock=seconds_to_time(self.sim.stamp_s)))
        for robot in due:
            self._send_step_messages(robot)
        for robot in self.barrier.expire(now):
            self._log_lost(robot, f"no answer to step {self.barrier.step} in time"
                                  + (" (liveliness lost)" if robot in self.barrier.suspects
                                     else ""))
        self._check_step_complete()

    def _suspect_the_unseen(self, now_s: float) -> None:
        """A robot whose liveliness was not reported a lease into the run is suspect, as if
        its liveliness had been lost (``liveliness_grace_s`` to answer a step instead of
        ``robot_timeout_s``) until it is reported. A robot that died before the middleware
        reported its liveliness was otherwise waited for ``robot_timeout_s``, and a team of
        such robots one after the other."""
        for robot in self._unseen.due(now_s):
            if robot in self.barrier.stopped:
                continue
            self.barrier.suspect(robot, now_s)
            self.get_logger().warn(
                f"robot {robot}: no liveliness seen {LIVELINESS_LEASE_S:g} s into the run; "
                f"given {self.barrier.suspect_timeout_s:g} s to answer until it is")

    def command_problem(self, robot: int, message: MotionCommand) -> str | None:
        """Reason to drop a motion command received on robot ``robot``'s topic: another
        robot's id or frame, a bad stamp, a twist beyond the robot's kinematics, or a
        barrier entry (team_sequence) behind the robot's last one or implausibly ahead."""
        motion = self.params.motion
        twist = message.twist
        last_sequence = (self._latest[robot].team_sequence if self.clock_mode == REALTIME
                         else self.barrier.team_sequences[robot])
        return ((f"robot_id {message.robot_id} on robot {robot}'s topic"
                 if message.robot_id != robot else None)
                or header_problem(message.header, f"{robot_namespace(robot)}/base_link")
                or command_problem(twist.linear.x, twist.angular.z, motion.speed_mps,
                                   motion.max_turn_per_step_rad, motion.time_step_s)
                or content_problem(message)
                or command_sequence_problem(message.team_sequence, last_sequence,
                                            MAX_SEQUENCE_LEAD))

    def _log_lost(self, robot: int, why: str) -> None:
        """The line run_team.sh --respawn reacts to (it restarts the robot's process)."""
        self.get_logger().warn(f"robot {robot} lost: {why}; the team goes on without it "
                               f"(zero motion) until it answers again")

    def _on_liveliness(self, robot: int, alive: bool, restarted: bool) -> None:
        if alive:
            self._unseen.seen(robot)
            if restarted:
                self.barrier.restarted(robot, time.monotonic())
            else:
                self.barrier.trust(robot, time.monotonic())
            self.get_logger().info(f"robot {robot}: liveliness asserted"
                                   + (" by a new process (restarted)" if restarted else ""))
            return
        self.barrier.suspect(robot, time.monotonic())
        self.get_logger().warn(
            f"robot {robot}: liveliness lost (process dead, stopped or wedged, or its "
            f"assertions lost on the network)")

    def _on_command(self, robot: int, message: MotionCommand) -> None:
        topic = f"/{robot_namespace(robot)}/motion_command"
        if not self.inputs.check(topic, self.command_problem(robot, message)):
            return
        answer = StepAnswer(float(message.twist.linear.x), float(message.twist.angular.z),
                            int(message.team_sequence), bool(message.finished),
                            int(message.team_messages), int(message.team_requests))
        if self.clock_mode == REALTIME:
            self._latest[robot] = answer
            return
        if not self.running or self.stepping_over:
            return
        outcome = self.barrier.answer(robot, int(message.step), answer, time.monotonic())
        if outcome == LockstepBarrier.REJOINED:
            self.get_logger().info(f"robot {robot} rejoined at step {self.barrier.step} "
                                   f"(answered step {message.step})")
        elif outcome == LockstepBarrier.CONFLICT:
            self.inputs.drop(topic, f"a second, different answer of robot {robot} to step "
                                    f"{message.step}: the first stands (another publisher "
                                    f"on its topic?)")
        elif outcome == LockstepBarrier.FUTURE:
            self.get_logger().warn(f"ignored a {outcome} command of robot {robot} for step "
                                   f"{message.step} (current step {self.barrier.step})")
        elif outcome != LockstepBarrier.ACCEPTED:
            self.get_logger().debug(f"ignored a {outcome} command of robot {robot} for step "
                                    f"{message.step}")
        self._check_step_complete()

    def _check_step_complete(self) -> None:
        """Lockstep: advance as long as every live robot has answered the current step."""
        while (self.running and not self.stepping_over and self.barrier.complete
               and self._relay_heard_step() and self._lost_team_waited_for()):
            answers = self.barrier.close()
            self._advance(answers, self.barrier.all_done)

    def _lost_team_waited_for(self) -> bool:
        """False while the world still waits for a team whose every unfinished robot is lost
        to come back (``lost_team_wait_s``; run_team.sh --respawn restarts them): without
        the wait, a team wedged at once ended its mission before any restart."""
        if not self.barrier.team_lost:
            self._team_lost_since_s = None
            return True
        now = time.monotonic()
        if self._team_lost_since_s is None:
            self._team_lost_since_s = now
            if self.settings.lost_team_wait_s > 0:
                self.get_logger().warn(
                    f"every robot that has not finished is lost; waiting up to "
                    f"{self.settings.lost_team_wait_s:g} s for one to come back before "
                    f"ending the mission")
        return now - self._team_lost_since_s >= self.settings.lost_team_wait_s

    def _relay_heard_step(self) -> bool:
        """Relay mode: True once the relay heard every team message the step's answers count
        (they travel on other topics than the answers, so they may come later), or
        ``robot_timeout_s`` passed (logged: the step goes on without them)."""
        if self.relay is None:
            return True
        missing = self.relay.missing_from(self.barrier.answers())
        now = time.monotonic()
        if not missing:
            self._frames_wait_since_s = None
            return True
        if self._frames_wait_since_s is None:
            self._frames_wait_since_s = now
        if now - self._frames_wait_since_s < self.barrier.robot_timeout_s:
            return False
        self.get_logger().warn(f"step {self.barrier.step}: team messages of robots {missing} "
                               f"counted in their answers never reached the relay; going on "
                               f"without them (not waited for again)")
        self.relay.write_off(self.barrier.answers())
        self._frames_wait_since_s = None
        return True

    def _realtime_tick(self) -> None:
        self._advance(self._latest, all(answer.finished for answer in self._latest))
        if self.stepping_over:
            self._tick_timer.cancel()

    def _advance(self, answers: list[StepAnswer], everyone_done: bool) -> None:
        """Apply one command per robot (id order), advance and publish the next step."""
        if self.stepping_over:
            return
        if everyone_done:
            self._end_stepping("every robot finished or stopped")
            return
        if self.relay is not None:
            self.relay.transmit(self.sim.step, self.sim.true_positions())
        for robot, answer in enumerate(answers):
            self.sim.apply_command(robot, answer.linear_x, answer.angular_z)
        self.sim.advance()
        self._publish_step()

    def log_links(self) -> None:
        """Relay mode: one line with what the links did so far."""
        if self.relay is not None:
            self.get_logger().info(self.relay.summary_line(self.sim.step))

    def _end_stepping(self, reason: str) -> None:
        self.stepping_over = True
        self.log_links()
        self.get_logger().info(f"stepping over at step {self.sim.step} (t = {self.sim.stamp_s:g}"
                               f" s): {reason}; still serving the latched topics until stopped")
        self._publish_status(True, reason)

    def _publish_status(self, stepping_over: bool, reason: str) -> None:
        """/world/status: the current step, whether stepping is over for good, and why."""
        header = Header(stamp=seconds_to_time(self.sim.stamp_s), frame_id=WORLD_FRAME)
        self.status_pub.publish(WorldStatus(header=header, step=self.sim.step,
                                            stepping_over=stepping_over, reason=reason))

    def _send_step_messages(self, robot: int) -> None:
        """(Re-)send the current step's sonar and odometry of ``robot``."""
        scan, odometry = self._step_messages[robot]
        self.sonar_pubs[robot].publish(scan)
        self.odom_pubs[robot].publish(odometry)

    def _publish_step(self) -> None:
        """/clock, what the links deliver before the step (relay mode), then every robot's
        sensors and ground truth for the current step."""
        sim = self.sim
        if self.relay is not None:
            self.relay.deliver(sim.step, sim.step >= self.final_step)
        stamp = seconds_to_time(sim.stamp_s)
        self.clock_pub.publish(Clock(clock=stamp))
        lockstep = self.clock_mode == LOCKSTEP
        sequences = list(self.barrier.team_sequences) if lockstep else []
        max_range = self.params.sensors.sonar_max_range_m
        for robot in range(self.num_robots):
            frame = sim.sense(robot)
            scan = sonar_scan_to_msg(frame, max_range, sequences)
            if self.relay is not None:
                scan.delivered_updates, scan.delivered_requests = \
                    self.relay.delivered_counts(robot)
            self._step_messages[robot] = (scan, serialized_dead_reckoning(frame))
            self._send_step_messages(robot)
            self.truth_pubs[robot].publish(serialized_odometry(
                sim.stamp_s, sim.true_pose(robot), WORLD_FRAME,
                f"{robot_namespace(robot)}/base_link"))
        if listened(self.tf_pub):
            self.tf_pub.publish(tf_publishing.tf_message(
                sim.stamp_s, tf_publishing.truth_transforms(
                    [sim.true_pose(robot) for robot in range(self.num_robots)])))
        if sim.step % _LOG_EVERY_STEPS == 0:
            self.get_logger().info(f"step {sim.step} (t = {sim.stamp_s:g} s)" + (
                "" if self.relay is None else f"; {self.relay.summary_line(sim.step)}"))
        if sim.step >= self.final_step:
            self._end_stepping(f"final step {self.final_step} reached")
        elif lockstep:
            self.barrier.open(sim.step, time.monotonic())


def main(args: list[str] | None = None) -> int:
    """Entry point of em-world; returns the exit code (2 for invalid parameters)."""
    return run_node(WorldNode, WORLD_NODE_NAME, args, wrap_up=_log_links)


def _log_links(node: WorldNode) -> int:
    """At the end (Ctrl-C, SIGTERM): what the links did, for the run's logs."""
    node.log_links()
    return 0


if __name__ == "__main__":
    sys.exit(main())
