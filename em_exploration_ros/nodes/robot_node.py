"""em-robot: one robot's process: team SLAM, virtual map, planner and motion control.

A thin shell around ``core.agent.robot_agent.RobotAgent``. Inputs: its own sonar and dead
reckoning from the world simulator, robot 0's launch pose (the mission's map anchor), and
its teammates' team updates. It never subscribes to ground truth. Besides its team
updates and what users see, it publishes its TF ``map`` -> ``robot_i/odom`` ->
``robot_i/base_link`` every step (nodes/tf_publishing.py).

Lockstep: each SonarScan carries the world's barrier (``team_sequences``). The node
processes a step only when it holds every teammate's updates up to the barrier, asking
for missing ones again (TeamUpdateRequest) while it waits; a teammate silent past
``barrier_timeout_s`` is skipped with a warning, and not waited for again until the
records given up on arrive (``TeamUpdateInbox.waive``: their sender may be dead). In
real-time mode the barrier is empty and steps are processed as they come. A step the world
sends again (its barrier repair) is answered again with the same command.

Relay mode (``links.*`` not perfect): the robot hears no teammate directly. The world's
link relay (``nodes/team_relay.py``) delivers teammates' records and requests on
``/robot_<i>/team/delivered_updates`` and ``/robot_<i>/team/delivered_requests``; each
SonarScan says how many it has delivered in all, and the step waits for those instead of
the barrier's sequence numbers (counted by the deliveries' publication sequence numbers,
``core.links.delivery_tally``; after ``barrier_timeout_s`` the missing ones are written
off, not waited for again). The robot sends at steps only, as em-sim
(``core.links.link_sender.LinkSender``: gap request, broadcast re-sends, new update), and
its MotionCommand counts what it has published (``team_messages``, ``team_requests``).

Liveliness (``nodes/liveliness.py``): the node offers its own and logs a warning when a
teammate's is lost. Rejoin: a node whose first step is not step 0 was restarted after a
crash. It asks its teammates for its own earlier stream (``/team/update_requests`` with
itself as requester; each teammate re-sends what it holds on ``/robot_<i>/team/history``),
waits until it holds it up to the sequence number the world's barrier names for it, then
resumes (``RobotAgent.resume``): its graph, targets and numbering continue where its stream
left off and its published path holds its whole history. With ``state_dir`` set, the robot
also journals every record it makes there (``core.agent.stream_journal``) and a restarted
process reads its stream back from its journal first, so it rejoins even when no teammate
holds it (the whole team restarted, or every teammate out of range).

Every message is checked before it touches any state (``scan_problem``, the dead
reckoning's frames, stamp and numbers, ``core.agent.input_checks``); unusable ones are dropped with a
throttled WARN, so the sensor data kept for coming steps stays bounded. Requests for
re-sends are rate-limited per requester and merged (``core.links.resend``). A world that
leaves the ROS graph is logged at once; after ``world_lost_timeout_s`` the robot exits
with code 4.

Run: ``python -m em_exploration_ros.nodes.robot_node --ros-args -r __ns:=/robot_0
-p robot_id:=0 -p use_sim_time:=true --params-file config/exploration.yaml``
"""
from __future__ import annotations

import math
import pathlib
import sys
import time
from collections.abc import Callable

import numpy as np
from em_exploration_msgs.msg import (LandmarkArray, MotionCommand, SonarScan, TeamUpdate,
                                     TeamUpdateRequest)
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from rclpy.clock import Clock, ClockType
from rclpy.task import Future
from visualization_msgs.msg import MarkerArray

from em_exploration_ros.core.planning.frontiers import Frontier
from em_exploration_ros.core.virtual_map.cell_uncertainty import cell_covariances_from_poses
from em_exploration_ros.core.agent.rejoin import (OwnHistoryRecovery, StreamArchive,
                                                  keyframe_ranges, records_beyond_the_team,
                                                  step_to_resume_at)
from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.agent.input_checks import (MAX_STEP_LEAD, RejectionLog,
                                                        barrier_problem, first_problem,
                                                        frame_problem, history_request_problem,
                                                        landmark_reading_problem, request_problem,
                                                        size_problem, stamp_step_problem,
                                                        step_problem)
from em_exploration_ros.core.links.delivery_tally import RECORDS, REQUESTS, DeliveryTally
from em_exploration_ros.core.links.link_sender import LinkSender
from em_exploration_ros.core.links.resend import ResendScheduler
from em_exploration_ros.core.agent.stream_journal import JournalIdentity, mission_fingerprint
from em_exploration_ros.core.records.team_data import (MAX_READINGS_PER_KEYFRAME,
                                                     MAX_SEQUENCE_LEAD, InvalidTeamUpdate,
                                                     LandmarkEstimate, TeamUpdateInbox)
from em_exploration_ros.core.records.team_data import TeamUpdate as TeamRecord
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.agent.world_watch import WorldEvent, WorldWatch
from em_exploration_ros.core.node_settings import RobotNodeSettings
from em_exploration_ros.core.links.link_model import FrameKind, perfect_links
from em_exploration_ros.core.records.wire_model import (command_to_twist, nanoseconds_to_seconds,
                                                sim_time_s, twist_to_increment_covariance)
from em_exploration_ros.nodes import tf_publishing, visualization
from em_exploration_ros.nodes.conversions import (MAP_FRAME, given_up_to_msg,
                                                  landmark_array_to_msg,
                                                  landmark_reading_from_msg,
                                                  odometry_codec, planar_odometry_from_msg,
                                                  quaternion_to_yaw,
                                                  robot_namespace, seconds_to_time, serialized_path,
                                                  team_update_to_msg,
                                                  teammate_reading_from_msg)
from em_exploration_ros.nodes.lean_node import LeanNode
from em_exploration_ros.nodes.liveliness import offer_liveliness, watch_liveliness
from em_exploration_ros.nodes.message_info import MessageInfo, publication_sequence
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.odometry_cdr import PlanarOdometry
from em_exploration_ros.nodes.record_journal import RecordJournal
from em_exploration_ros.nodes.recorder_presence import topics_not_recorded
from em_exploration_ros.nodes.qos import ESTIMATE_QOS, LATCHED_QOS, SENSOR_QOS, TEAM_QOS
from em_exploration_ros.nodes.input_guard import (LOG_PERIOD_S, InputGuard,
                                                  checked_team_update, content_problem,
                                                  deserialized, header_problem, listened,
                                                  publish_or_log, size_limited)
from em_exploration_ros.nodes.ros_params import (declare_exploration_params,
                                                 declare_node_settings, refuse_unknown_overrides)
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.nodes.team_topics import (delivered_requests_topic,
                                                  delivered_updates_topic, history_copies_topic)

EXIT_OK, EXIT_WORLD_GONE = 0, 4
#: Steps without an estimate of its own pose (10 s simulated) before a robot says so; again
#: after twice, four times, ... as many.
UNANCHORED_WARN_STEPS = 50


def requester_name(requester_id: int) -> str:
    """How a log line names the sender of a TeamUpdateRequest."""
    if requester_id == TeamUpdateRequest.OBSERVER:
        return "the evaluator (observer)"
    return f"robot {requester_id}"


def delivered_counts(scan: SonarScan) -> tuple[int, int]:
    """Relay mode: the records and requests the link relay had delivered to the robot in all
    when the world published ``scan``."""
    return int(scan.delivered_updates), int(scan.delivered_requests)


class RobotNode(LeanNode):
    """One robot of the team (see module docstring)."""

    def __init__(self) -> None:
        super().__init__("em_robot")
        self.inputs = InputGuard(self)
        install_validated_clock(self, self.inputs)
        self.settings = declare_node_settings(self, RobotNodeSettings)
        self.robot_id = self.settings.robot_id
        self.params = declare_exploration_params(self)
        refuse_unknown_overrides(self)
        self.num_robots = self.params.world.num_robots
        if not 0 <= self.robot_id < self.num_robots:
            raise ValueError(f"robot_id {self.robot_id} is not in 0..{self.num_robots - 1}")
        self.time_step_s = self.params.motion.time_step_s
        self.wire = TeamWireFormat(self.params)
        self.agent: RobotAgent | None = None
        self.inbox = TeamUpdateInbox(self.robot_id, self.num_robots)
        self.resends = ResendScheduler(self.settings.resend_interval_s)
        self.relay_mode = not perfect_links(self.params.links)
        self.link_sender = LinkSender(self.robot_id, self.params)
        self.team_messages = self.team_requests = 0
        self.deliveries = DeliveryTally()  # relay mode
        self.archive = StreamArchive(self.robot_id, self.num_robots)
        self.journal, self.team_journal = self._make_journals()
        self._recovery: OwnHistoryRecovery | None = None
        self._served_history: dict[int, float] = {}
        self._served_history_log = RejectionLog(LOG_PERIOD_S)
        self._last_reply: MotionCommand | None = None
        self.rejected_updates = 0
        self._slam_recoveries_logged = 0
        self.exit_code = EXIT_OK
        self.done = Future()
        self._scans: dict[int, SonarScan] = {}
        self._odometry: dict[int, PlanarOdometry] = {}
        self._next_step: int | None = None
        self._waiting_since: float | None = None
        self._last_request = 0.0
        self._barrier: dict[int, int] = {}
        self._world_watch = WorldWatch(self.settings.world_lost_timeout_s)
        self._recorder_wait_since: float | None = None
        self._recorder_listens = not self.settings.wait_for_recorder
        self._next_world_check_s = 0.0
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
        self.tf_pub = tf_publishing.create_tf_publisher(self)
        self.create_subscription(PoseStamped, "/mission/anchor_pose", self._on_anchor,
                                 LATCHED_QOS)
        self.create_subscription(SonarScan, f"/{ns}/sonar", self._on_scan, SENSOR_QOS)
        odom_topic = f"/{ns}/odom"
        self._odom_codec = odometry_codec(f"{ns}/odom", f"{ns}/base_link")
        self.create_subscription(Odometry, odom_topic, size_limited(
            self.inputs, odom_topic, Odometry, self._odom_codec.size, self._on_odometry_data,
            raw=True), SENSOR_QOS, raw=True)
        self.create_subscription(TeamUpdateRequest, "/team/update_requests",
                                 self._on_update_request, TEAM_QOS)
        teammates = [r for r in range(self.num_robots) if r != self.robot_id]
        if self.relay_mode:
            self.history_pubs = {}  # copies of a teammate's records go through the relay
            self.history_copies_pub = self.create_publisher(
                TeamUpdate, history_copies_topic(self.robot_id), TEAM_QOS)
            self.create_subscription(TeamUpdate, delivered_updates_topic(self.robot_id),
                                     self._on_delivered_update, TEAM_QOS)
            self.create_subscription(TeamUpdateRequest, delivered_requests_topic(self.robot_id),
                                     self._on_delivered_request, TEAM_QOS)
        else:
            self.create_subscription(TeamUpdate, f"/{ns}/team/history", self._on_own_history,
                                     TEAM_QOS)
            self.history_pubs = {r: self.create_publisher(
                TeamUpdate, f"/{robot_namespace(r)}/team/history", TEAM_QOS)
                for r in teammates}
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
        if not self.inputs.check("/mission/anchor_pose", header_problem(message.header, MAP_FRAME),
                                 content_problem(message)):
            return
        self.agent = RobotAgent(self.robot_id, self.params, anchor)
        self._world_heard()  # the anchor is the world's
        self.get_logger().info(f"map anchored at robot 0's launch pose {anchor.round(3).tolist()}")
        self._process_ready_steps()

    def _sensor_step_problem(self, step: int, pending: dict) -> str | None:
        """Reason to drop sensor data of ``step``: outside the run, stale, too far ahead
        (``core.agent.input_checks.step_problem``: more than ``MAX_STEP_LEAD`` steps, unless
        the world's clock is there already) or no room left in ``pending``."""
        lead = MAX_STEP_LEAD
        if self._next_step is not None and step > self._next_step + lead:
            lead = max(lead, self._world_step() - self._next_step)
        return (step_problem(step, self._next_step, self.params.run.max_steps, lead)
                or (size_problem(len(pending) + 1, MAX_STEP_LEAD, "pending steps")
                    if step not in pending else None))

    def _world_step(self) -> int:
        """The step of the world's clock (/clock, validated), as far as it reached here."""
        return int(self.get_clock().now().nanoseconds // round(self.time_step_s * 1e9))

    def scan_problem(self, message: SonarScan) -> str | None:
        """Reason to drop a sonar scan: addressed to another robot, wrong frame or stamp,
        implausible step, barrier, array sizes, ids or numbers."""
        robot = self.robot_id
        expected_next = {r: self.inbox.next_expected(r) for r in range(self.num_robots)
                         if r != robot}
        stamp_ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        return ((f"scan addressed to robot {message.robot_id}"
                 if message.robot_id != robot else None)
                or header_problem(message.header, f"{robot_namespace(robot)}/base_link")
                or self._sensor_step_problem(message.step, self._scans)
                or stamp_step_problem(stamp_ns, message.step, self.time_step_s)
                or barrier_problem(message.team_sequences, self.num_robots, expected_next,
                                   MAX_SEQUENCE_LEAD, own=(robot, int(message.step)))
                or size_problem(len(message.landmarks), MAX_READINGS_PER_KEYFRAME,
                                "landmark readings")
                or size_problem(len(message.teammates), self.num_robots - 1,
                                "teammate readings")
                or content_problem(message)
                or first_problem(landmark_reading_problem(r.range, r.range_variance,
                                                          r.bearing_variance, r.landmark_id)
                                 for r in message.landmarks)
                or first_problem(f"teammate id {r.robot_id} is not a teammate"
                                 for r in message.teammates
                                 if not 0 <= r.robot_id < self.num_robots
                                 or r.robot_id == robot))

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
        if message.robot_id == self.robot_id and self._processed(int(message.step)):
            # The world sent the step again: our answer did not arrive. Answer again.
            if self._last_reply is not None and self._last_reply.step == message.step:
                publish_or_log(self.command_pub, self._last_reply, self,
                               f"the command of step {message.step} again")
            return
        if not self.inputs.check(f"/{robot_namespace(self.robot_id)}/sonar",
                                 self.scan_problem(message)):
            return
        self._scans[int(message.step)] = message
        self._drop_stale_while_recovering(int(message.step))
        self._world_heard()
        self._process_ready_steps()

    def _on_odometry_data(self, data: bytes) -> None:
        """Serialized dead reckoning: read in one struct when it is in the world's own form
        (``nodes.odometry_cdr``), otherwise as a message with every check."""
        odometry = self._odom_codec.decode(data)
        if odometry is not None:
            self._take_odometry(odometry)
            return
        ns = robot_namespace(self.robot_id)
        message = deserialized(self.inputs, f"/{ns}/odom", Odometry, data)
        if message is not None:
            self._take_odometry(
                planar_odometry_from_msg(message), header_problem(message.header, f"{ns}/odom"),
                frame_problem(message.child_frame_id, f"{ns}/base_link", "child_frame_id"),
                content_problem(message))

    def _take_odometry(self, odometry: PlanarOdometry, *message_problems: str | None) -> None:
        """Dead reckoning of a step, unless ``message_problems`` (frames, numbers), its stamp
        off the step grid or an implausible step give a reason to drop it."""
        stamp_ns = odometry.stamp[0] * 1_000_000_000 + odometry.stamp[1]
        stamp_s = nanoseconds_to_seconds(stamp_ns)
        step = int(round(stamp_s / self.time_step_s)) if math.isfinite(stamp_s) else -1
        if self._processed(step):
            return  # a re-sent step this robot already answered
        if not self.inputs.check(f"/{robot_namespace(self.robot_id)}/odom", *message_problems,
                                 self._sensor_step_problem(step, self._odometry),
                                 stamp_step_problem(stamp_ns, step, self.time_step_s)):
            return
        self._odometry[step] = odometry
        self._drop_stale_while_recovering(step)
        self._process_ready_steps()

    def _drop_stale_while_recovering(self, step: int) -> None:
        """While a restarted robot recovers its stream, the world goes on without it (its
        vehicle stands still) and may run thousands of steps ahead: keep only the newest
        step's sensor data, so that it resumes at the world's open step instead of
        replaying stale steps it could never catch up with."""
        if self._recovery is None or self._next_step is None or step <= self._next_step:
            return
        self._resume_at(step)

    def _resume_at(self, step: int) -> None:
        """Make ``step`` the next one to process: the sensor data of earlier steps goes."""
        for pending in (self._scans, self._odometry):
            for old in [k for k in pending if k < step]:
                del pending[old]
        self._next_step = step

    def _on_team_update(self, sender: int, message: TeamUpdate) -> None:
        self._file_team_update(f"/{robot_namespace(sender)}/team/updates", message, sender)
        self._process_ready_steps()

    def _file_team_update(self, topic: str, message: TeamUpdate, sender: int | None) -> None:
        """Check a teammate's record and file it in the inbox (dropped with a WARN if bad)."""
        try:
            self.inbox.receive(checked_team_update(message, self.wire), sender)
        except InvalidTeamUpdate as error:
            self.rejected_updates += 1
            self.inputs.drop(topic, f"rejected a team update: {error}")

    def _on_delivered_update(self, message: TeamUpdate, info: MessageInfo) -> None:
        """Relay mode: a record the links delivered (a teammate's, or a copy of this robot's
        own after a restart)."""
        self.deliveries.heard(RECORDS, publication_sequence(info))
        if message.robot_id == self.robot_id:
            self._on_own_history(message)
        else:
            self._file_team_update(delivered_updates_topic(self.robot_id), message, None)
        self._process_ready_steps()

    def _on_delivered_request(self, message: TeamUpdateRequest, info: MessageInfo) -> None:
        """Relay mode: a request the links delivered: a teammate's for this robot's records
        (re-sent at a coming step, ``LinkSender``) or a restarted teammate's for its own."""
        self.deliveries.heard(REQUESTS, publication_sequence(info))
        asker, owner = int(message.requester_id), int(message.robot_id)
        topic = delivered_requests_topic(self.robot_id)
        if asker == owner:
            self._serve_history(topic, message)
        elif self.inputs.check(topic, f"request for robot {owner}'s records"
                               if owner != self.robot_id else None,
                               request_problem(asker, message.first_sequence,
                                               message.last_sequence, self.robot_id,
                                               self.num_robots, TeamUpdateRequest.OBSERVER)):
            self._file_link_request(asker, message)
        self._process_ready_steps()

    def _file_link_request(self, asker: int, message: TeamUpdateRequest) -> None:
        if self.agent is not None:
            self.link_sender.file_request(asker, int(message.first_sequence),
                                          int(message.last_sequence),
                                          self.agent.outbox.last_sequence)

    def _on_own_history(self, message: TeamUpdate) -> None:
        """A teammate's copy of one of this robot's earlier records (after a restart)."""
        if self._recovery is None:
            return
        try:
            self._recovery.receive(checked_team_update(message, self.wire))
        except InvalidTeamUpdate as error:
            self.rejected_updates += 1
            self.get_logger().warn(f"rejected a relayed record of this robot's history: {error}")

    def _serve_history(self, topic: str, request: TeamUpdateRequest) -> None:
        """Re-send what this robot holds of a restarted teammate's stream (the records it
        applied, then those the barrier still holds back), the teammate's request checked
        first (``history_request_problem``), at most once per ``request_period_s`` per
        teammate, logged at most once per ``LOG_PERIOD_S`` per teammate. Nothing tells a
        forged request from a real one (DDS carries no identity without security), so that
        bound is what a forger gets."""
        requester = int(request.requester_id)
        if not self.inputs.check(topic, history_request_problem(
                requester, int(request.first_sequence), int(request.last_sequence),
                self.robot_id, self.num_robots)):
            return
        now = time.monotonic()
        if now - self._served_history.get(requester, -float("inf")) < self.settings.request_period_s:
            return
        self._served_history[requester] = now
        held = self.archive.held(requester) + self.inbox.held_back(requester)
        publisher = (self.history_copies_pub if self.relay_mode
                     else self.history_pubs[requester])
        for update in held:
            publish_or_log(publisher, team_update_to_msg(update, self.wire), self,
                           f"robot {requester}'s record {update.sequence}")
        served = self._served_history_log.note(str(requester), now)
        if served is not None:
            times = f" ({served} times since the last line)" if served > 1 else ""
            self.get_logger().info(f"robot {requester} asked for its own stream (restarted): "
                                   f"re-sent the {len(held)} records of it this robot "
                                   f"holds{times}")

    def _on_update_request(self, message: TeamUpdateRequest) -> None:
        """File a teammate's (or the evaluator's) request for some of this robot's updates;
        they are re-sent by ``_send_due_resends``, rate-limited per requester. A restarted
        teammate asking for its own stream gets what this robot holds of it."""
        asker, owner = int(message.requester_id), int(message.robot_id)
        if self.relay_mode and asker != TeamUpdateRequest.OBSERVER:
            return  # a teammate's request reaches this robot through the links
        if asker == owner == self.robot_id:  # its own request after a restart, heard back
            return
        if asker == owner:
            self._serve_history("/team/update_requests", message)
            return
        if message.robot_id != self.robot_id:
            return  # addressed to a teammate
        problem = request_problem(message.requester_id, message.first_sequence,
                                  message.last_sequence, self.robot_id, self.num_robots,
                                  TeamUpdateRequest.OBSERVER)
        if not self.inputs.check("/team/update_requests", problem) or self.agent is None:
            return
        if self.relay_mode:  # re-sent at a coming step, through the links
            self._file_link_request(asker, message)
            return
        self.resends.request(message.requester_id, int(message.first_sequence),
                             int(message.last_sequence), self.agent.outbox.last_sequence)
        self._send_due_resends()

    def _send_due_resends(self) -> None:
        if self.agent is None:
            return
        for due in self.resends.due(time.monotonic()):
            resent = self.agent.outbox.resend(due.first_sequence, due.last_sequence)
            sent = sum(self._publish_update(update, f"re-sent update {update.sequence}")
                       for update in resent)
            if resent:
                self.get_logger().info(
                    f"re-sent {sent} of updates {resent[0].sequence}..{resent[-1].sequence} "
                    f"for {requester_name(due.requester_id)}",
                    throttle_duration_sec=LOG_PERIOD_S)

    def _maintain(self) -> None:
        """Re-send what was asked for; ask again for missing team updates (or, after a
        restart, for this robot's own stream); give up waiting on silent teammates; notice a
        world that left the graph."""
        if not self.relay_mode:  # relay mode: re-sends go at steps (LinkSender)
            self._send_due_resends()
        self._watch_world()
        if self._recorder_wait_since is not None and not self._recorder_listens:
            self._process_ready_steps()
        elif self._next_step is not None and any(step > self._next_step for step in self._scans):
            self._process_ready_steps()  # the world's clock may have reached a later step
        now = time.monotonic()
        if self._recovery is not None:
            if self._recovery.complete(now):
                self._process_ready_steps()
            elif (self._recovery.short_of
                  and now - self._last_request >= self.settings.request_period_s):
                self._last_request = now
                self._request_own_history()
            return
        # Missing records are asked for while the step waits for them, and after it stopped
        # waiting (``waive``) until they arrive.
        wanted = self.inbox.waived()
        if self._waiting_since is not None:
            wanted.update({robot: max(limit, wanted.get(robot, 0))
                           for robot, limit in self._barrier.items()})
        if (not self.relay_mode and wanted
                and now - self._last_request >= self.settings.request_period_s):
            self._last_request = now
            for gap in self.inbox.missing(wanted):
                self._publish_request(gap.robot_id, gap.first_sequence, gap.last_sequence)
        if self._waiting_since is None:
            return
        if now - self._waiting_since > self.settings.barrier_timeout_s:
            missing = "teammates' updates " + ", ".join(
                f"robot {gap.robot_id} #{gap.first_sequence}-{gap.last_sequence}"
                for gap in self.inbox.missing(self._barrier))
            self.inbox.waive(self._barrier)  # not waited for again at every step
            scan = self._scans.get(self._next_step)
            if self.relay_mode and scan is not None:
                needed = delivered_counts(scan)
                missing = (f"deliveries of the link relay (records, requests: held "
                           f"{self.deliveries.held()} of {needed})")
                self.deliveries.write_off(needed)  # not waited for again at every step
            self.get_logger().warn(
                f"step {self._next_step}: {missing} still missing after "
                f"{self.settings.barrier_timeout_s} s; going on without them")
            self._barrier = {}
            self._process_ready_steps(ignore_barrier=True)

    def _watch_world(self) -> None:
        """Once a second: is the world (the publisher of this robot's sonar) on the graph?
        Log when it leaves or comes back; exit (code 4) when it stayed away too long."""
        now = time.monotonic()
        if now < self._next_world_check_s:
            return
        self._next_world_check_s = now + 1.0
        topic = f"/{robot_namespace(self.robot_id)}/sonar"
        self._log_world_event(self._world_watch.update(self.count_publishers(topic) > 0, now),
                              topic)

    def _world_heard(self) -> None:
        """A message of the world arrived, so it is there: a world that leaves before the
        once-a-second graph check first saw it is still noticed when it leaves."""
        self._log_world_event(self._world_watch.update(True, time.monotonic()),
                              f"/{robot_namespace(self.robot_id)}/sonar")

    def _log_world_event(self, event: WorldEvent | None, topic: str) -> None:
        log = self.get_logger()
        if event == WorldEvent.LOST:
            log.warn(f"the world left the ROS graph (no publisher of {topic}); waiting up to "
                     f"{self.settings.world_lost_timeout_s:g} s for it to come back")
        elif event == WorldEvent.BACK:
            log.info("the world is back on the ROS graph")
        elif event == WorldEvent.GONE:
            log.error(f"the world has been gone for {self.settings.world_lost_timeout_s:g} s; "
                      f"exiting (code {EXIT_WORLD_GONE})")
            self.exit_code = EXIT_WORLD_GONE
            self.done.set_result(EXIT_WORLD_GONE)

    # -- stepping ------------------------------------------------------------------------

    def _request_own_history(self) -> None:
        self._publish_request(self.robot_id, 1, 0)

    def _publish_request(self, owner: int, first_sequence: int, last_sequence: int) -> None:
        """Ask robot ``owner`` for records ``first..last`` of its stream (counted)."""
        request = TeamUpdateRequest(requester_id=self.robot_id, robot_id=owner,
                                    first_sequence=first_sequence, last_sequence=last_sequence)
        request.header.stamp = self.get_clock().now().to_msg()
        if publish_or_log(self.request_pub, request, self, "a request for team updates"):
            self.team_requests += 1

    def _publish_update(self, update: TeamRecord, what: str) -> bool:
        """Publish a record of this robot's stream on its update topic (counted)."""
        sent = publish_or_log(self.update_pub, team_update_to_msg(update, self.wire), self, what)
        self.team_messages += sent
        return sent

    def _make_journals(self) -> tuple[RecordJournal | None, RecordJournal | None]:
        """This robot's journals in ``state_dir`` (its own stream, the teammates' records it
        applied), None without a ``state_dir``."""
        if not self.settings.state_dir:
            return None, None
        identity = JournalIdentity(self.robot_id, self.num_robots,
                                   mission_fingerprint(self.params))
        stem = pathlib.Path(self.settings.state_dir) / f"robot_{self.robot_id}"
        logger = self.get_logger()
        return (RecordJournal(stem.with_suffix(".journal"), identity, self.wire, logger,
                              "stream journal"),
                RecordJournal(stem.with_suffix(".team.journal"), identity, self.wire, logger,
                              "team journal"))

    def _read_journals(self, team_holds: list[int]) -> None:
        """After a restart: this robot's earlier records and the teammates' records it had
        applied, from its own journals (``team_holds``: the world's barrier), checked as
        received ones are; the teammates' copies fill what they lack."""
        if self.journal is None:
            return
        own = self._file_journaled(self.journal, team_holds, self._recovery.receive)
        teammates = self._file_journaled(self.team_journal, team_holds, self.inbox.receive)
        # Applied by the earlier process: the archive holds them from now on, so they are
        # served to a restarted teammate and not journaled again when applied.
        self.archive.keep(teammates)
        self.team_journal.start(teammates, fresh=False)
        self.get_logger().info(
            f"read {len(own)} records of this robot's stream from its journal "
            f"{self.journal.path} (the team holds it up to sequence "
            f"{self._recovery.needed_sequence}) and {len(teammates)} of its teammates' "
            f"from {self.team_journal.path}")

    def _file_journaled(self, journal: RecordJournal, team_holds: list[int],
                        file: Callable[[TeamRecord], object]) -> list[TeamRecord]:
        """File a journal's usable records (``_journaled_records``) with ``file`` up to the
        first one it refuses (WARN); returns those filed."""
        taken = []
        for update in self._journaled_records(journal, team_holds):
            try:
                file(update)
            except InvalidTeamUpdate as error:
                self.get_logger().warn(f"{journal.what} {journal.path}: record "
                                       f"{update.robot_id}/{update.sequence} refused ({error}); "
                                       f"not read on")
                break
            taken.append(update)
        return taken

    def _journaled_records(self, journal: RecordJournal, team_holds: list[int]
                           ) -> list[TeamRecord]:
        """A journal's usable records; none if they cannot be this run's (WARN)."""
        contents = journal.read()
        if contents.problem is not None:
            self.get_logger().warn(f"{journal.what}: {contents.problem}")
        updates = journal.decoded(contents)
        # (Without a barrier, in real-time mode, there is nothing to check them against.)
        foreign = records_beyond_the_team(updates, team_holds) if team_holds else None
        if foreign is not None:
            self.get_logger().warn(f"{journal.what} {journal.path}: {foreign}")
            return []
        return updates

    def _start_recovery(self, scan: SonarScan) -> None:
        """This process starts in the middle of a run: it was restarted after a crash."""
        barrier = list(scan.team_sequences)
        needed = int(barrier[self.robot_id]) if barrier else 0
        now = time.monotonic()
        self._recovery = OwnHistoryRecovery(self.robot_id, self.num_robots, needed, now,
                                            self.settings.rejoin_settle_s,
                                            self.settings.rejoin_timeout_s)
        self.get_logger().warn(
            f"first step is {scan.step}, not 0: restarted in a running team; asking the "
            f"teammates for this robot's stream (the team holds it up to sequence {needed})")
        self._read_journals(barrier)
        self._last_request = now
        self._request_own_history()

    def _resume(self) -> None:
        recovery, self._recovery = self._recovery, None
        history = recovery.history()
        if recovery.short_of:
            self.get_logger().error(
                f"resuming without {recovery.short_of} records of this robot's stream (up to "
                f"sequence {recovery.needed_sequence}): no teammate sent them; they are "
                f"re-sent empty, and the motion since the last keyframe recovered is linked "
                f"with the odometry covariance of every step since")
        self.agent.resume(history, recovery.needed_sequence, self._next_step)
        if self.journal is not None:
            self.journal.start(self.agent.outbox.resend(1, 0), fresh=False)
        self._log_slam_recoveries()
        keyframes = np.array([keyframe.index for update in history
                              for keyframe in update.keyframes], dtype=int)
        self.get_logger().info(
            f"rejoined: recovered {len(history)} records of this robot's stream (keyframes "
            f"{keyframe_ranges(keyframes)}, {len(self.agent.decisions)} targets); continuing "
            f"at sequence {self.agent.outbox.last_sequence + 1}")

    def _process_ready_steps(self, ignore_barrier: bool = False) -> None:
        """Process every step whose sensor data (and barrier) is complete, in order."""
        while self.agent is not None:
            if self._next_step is None and self._scans:
                self._next_step = min(self._scans)
                first = self._scans[self._next_step]
                if self._next_step > 0:
                    # Restarted: the deliveries before this process subscribed are not its own.
                    self.deliveries.start_at(delivered_counts(first))
                    self._start_recovery(first)
                elif self.journal is not None:
                    self.journal.start((), fresh=True)
                    self.team_journal.start((), fresh=True)
            if self._recovery is not None:
                if not self._recovery.complete(time.monotonic()):
                    return
                self._resume()
            step = self._next_step
            if step is None:
                return
            if step not in self._scans or step not in self._odometry:
                if not self._skip_to_the_worlds_step():
                    return
                step = self._next_step
            if not self._recorder_listens and not self._recorder_listening():
                return
            scan = self._scans[step]
            limits = {robot: int(seq) for robot, seq in enumerate(scan.team_sequences)
                      if robot != self.robot_id and not self.relay_mode}
            if not ignore_barrier and not self._team_data_held(scan, limits):
                if self._waiting_since is None:
                    self._waiting_since = time.monotonic()
                self._barrier = limits
                return
            self._waiting_since, ignore_barrier = None, False
            self._step(scan, self._odometry.pop(step), limits or None)
            del self._scans[step]
            self._next_step = step + 1

    def _skip_to_the_worlds_step(self) -> bool:
        """While the sensor data of the awaited step is missing: if a later step is complete
        and the world's clock reached it, the world went on without this robot (it was wedged,
        stopped or starved; ``core.agent.rejoin.step_to_resume_at``): drop the older data and
        resume at that step, with one moving step's odometry covariance for the motion since
        (``RobotAgent.skip_steps``). Returns True if it skipped."""
        awaited = self._next_step
        if all(step <= awaited for step in self._scans):  # the usual case: nothing later
            return False
        resume_at = step_to_resume_at(awaited, self._scans.keys() & self._odometry.keys(),
                                      self._world_step())
        if resume_at is None:
            return False
        self._resume_at(resume_at)
        self._waiting_since = None
        self.agent.skip_steps()
        self.get_logger().warn(
            f"the world went on without this robot: resuming at step {resume_at}, "
            f"{resume_at - awaited} steps after step {awaited}, whose sensor data is lost "
            f"(the world held the vehicle still meanwhile)")
        return True

    def _team_data_held(self, scan: SonarScan, limits: dict[int, int]) -> bool:
        """True when this robot holds the team data it must apply before the scan's step:
        in relay mode everything the links delivered (``SonarScan.delivered_*``), otherwise
        every teammate's records up to the barrier ``limits``."""
        if not self.relay_mode:
            return not limits or self.inbox.holds_up_to(limits)
        return self.deliveries.holds(delivered_counts(scan))

    def _recorder_listening(self) -> bool:
        """Before the first step: True once the recorder subscribes to every topic this robot
        publishes, or ``recorder_wait_s`` passed (logged). Most topics are volatile: what is
        published before the recorder's subscription matched never reaches it. Until then
        the step waits (``_maintain`` looks again; the world re-sends the step)."""
        missing = topics_not_recorded(self)
        now = time.monotonic()
        if self._recorder_wait_since is None:
            self._recorder_wait_since = now
        waited = now - self._recorder_wait_since
        if not missing:
            self.get_logger().info(f"the recorder listens to every topic of this robot after "
                                   f"{waited:.1f} s: answering the first step")
        elif waited >= self.settings.recorder_wait_s:
            self.get_logger().warn(
                f"the recorder does not listen to {', '.join(missing)} after {waited:.1f} s; "
                "answering the first step anyway (the recording misses what these topics "
                "carry before it subscribes)")
        else:
            return False
        self._recorder_listens = True
        return True

    def _step(self, scan: SonarScan, odometry: PlanarOdometry,
              limits: dict[int, int] | None) -> None:
        agent = self.agent
        step = int(scan.step)
        stamp_s = sim_time_s(step, self.time_step_s)
        released = self.inbox.pop_ready(limits)
        agent.apply_team_updates(released)
        for update in self.archive.keep(released):
            if self.team_journal is not None:
                self.team_journal.append(update)
        decisions_before, given_up_before = len(agent.decisions), len(agent.given_up)
        command = agent.step(StepInput(
            step, stamp_s, odometry.pose,
            twist_to_increment_covariance(odometry.twist_covariance, self.time_step_s),
            tuple(landmark_reading_from_msg(r) for r in scan.landmarks),
            tuple(teammate_reading_from_msg(r) for r in scan.teammates)))
        self._warn_if_unanchored(agent.steps_unanchored)
        update = agent.take_outgoing()
        if update is not None and self.journal is not None:
            self.journal.append(update)
        if self.relay_mode:
            self._send_frames(step, update)
        elif update is not None:
            self._publish_update(update, f"team update {update.sequence} (teammates will ask "
                                         f"for it again)")
        self._publish_transforms(stamp_s, odometry)
        linear_x, angular_z = command_to_twist(command.turn_rad, command.forward_m,
                                               self.time_step_s)
        reply = MotionCommand(robot_id=self.robot_id, step=step,
                              team_sequence=agent.outbox.last_sequence,
                              team_messages=self.team_messages, team_requests=self.team_requests,
                              finished=command.finished,
                              blocked_s=float(agent.blocked_s),
                              given_up_count=len(agent.given_up),
                              given_up=[given_up_to_msg(g)
                                        for g in agent.given_up[given_up_before:]])
        reply.header = scan.header
        reply.twist.linear.x, reply.twist.angular.z = linear_x, angular_z
        publish_or_log(self.command_pub, reply, self, f"the command of step {step}")
        self._last_reply = reply
        if step % self.params.slam.keyframe_interval_steps == 0:
            self._publish_estimates(stamp_s)
        if len(agent.decisions) != decisions_before:
            self._publish_decision(stamp_s)
        self._log_slam_recoveries()

    def _warn_if_unanchored(self, steps: int) -> None:
        """A robot without an estimate of its own pose stands still: say so after
        ``UNANCHORED_WARN_STEPS`` such steps, and again after 2x, 4x, ... as many."""
        intervals, rest = divmod(steps, UNANCHORED_WARN_STEPS)
        if steps == 0 or rest or intervals & (intervals - 1):
            return
        self.get_logger().warn(
            f"no estimate of this robot's own pose for {steps} steps "
            f"({steps * self.time_step_s:g} s): nothing the team holds ties its trajectory "
            f"to the map (for a robot other than 0, a teammate's reading of it); it stands "
            f"still until a teammate's reading of it arrives")

    def _log_slam_recoveries(self) -> None:
        """A warning for every SLAM update re-solved in batch since the last call."""
        recoveries = self.agent.slam.recoveries
        for recovery in recoveries[self._slam_recoveries_logged:]:
            self.get_logger().warning(recovery.describe())
        self._slam_recoveries_logged = len(recoveries)

    def _send_frames(self, step: int, update: TeamRecord | None) -> None:
        """Relay mode: publish what this robot sends at ``step`` (``LinkSender``, as em-sim):
        a gap request, the due re-sends, its new update."""
        for frame in self.link_sender.frames(step, self.inbox, self.agent.outbox, update):
            if frame.kind == FrameKind.REQUEST:
                gap = frame.payload
                self._publish_request(gap.robot_id, gap.first_sequence, gap.last_sequence)
            else:
                self._publish_update(frame.payload, f"team record {frame.payload.sequence} "
                                                    f"(teammates will ask for it again)")

    # -- what users see --------------------------------------------------------------------

    def _publish_transforms(self, stamp_s: float, odometry: PlanarOdometry) -> None:
        """/tf ``map`` -> ``odom`` -> ``base_link`` of this step, once the robot is anchored."""
        pose = self.agent.current_pose()
        if pose is not None and listened(self.tf_pub):
            transforms = tf_publishing.robot_transforms(self.robot_id, pose, odometry.pose)
            publish_or_log(self.tf_pub, tf_publishing.tf_message(stamp_s, transforms), self,
                           "the robot's transforms")

    def _publish_estimates(self, stamp_s: float) -> None:
        agent = self.agent
        slam = agent.slam
        indices, poses = slam.trajectory(self.robot_id)
        interval = self.params.slam.keyframe_interval_steps
        stamps = [sim_time_s(int(i) * interval, self.time_step_s) for i in indices]
        self.path_pub.publish(serialized_path(stamp_s, np.array(stamps), poses))
        landmarks = [LandmarkEstimate(lid, position, slam.landmark_covariance(lid))
                     for lid, position in sorted(slam.landmark_estimates().items())]
        self.landmarks_pub.publish(landmark_array_to_msg(
            stamp_s, MAP_FRAME, landmarks, self.params.world.landmark_radius_m))

    def _publish_decision(self, stamp_s: float) -> None:
        """The target, the virtual map and the markers of a new decision, each only if
        someone subscribes (the markers cost a robot more CPU than its decision; a viewer
        that subscribes later gets the next decision's)."""
        agent = self.agent
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
            self._publish_markers(stamp_s, target)

    def _publish_markers(self, stamp_s: float, target: Frontier | None) -> None:
        """Covariance ellipses of the virtual map's cells, frontiers and landmarks."""
        agent = self.agent
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
    """Entry point of em-robot; returns the exit code (2 for invalid parameters, 4 when
    its world left the graph for good)."""
    return run_node(RobotNode, "em_robot", args, wrap_up=_log_graph)


def _log_graph(node: RobotNode) -> int:
    """At the end (Ctrl-C, SIGTERM, world gone): what the team graph holds, for the run's
    logs; returns the node's exit code."""
    node.log_team_graph()
    return node.exit_code


if __name__ == "__main__":
    sys.exit(main())
