"""em-robot: one robot's process: team SLAM, virtual map, planner and motion control.

The ROS shell of ``core.sessions.robot_session.RobotSession``, which owns the robot's
``RobotAgent`` and its team protocol (lockstep barrier, gap requests, re-sends, relay mode,
rejoin after a restart, the world watch; see its docstring). Inputs: its own sonar and dead
reckoning from the world simulator, robot 0's launch pose (the mission's map anchor), its
teammates' team updates and requests (in relay mode, what the world's link relay delivers on
``/robot_<i>/team/delivered_*``), their liveliness (``nodes/liveliness.py``) and a 10 Hz
wall-time tick. It never subscribes to ground truth. The node checks every message before
it touches any state (frames, stamps, sizes and numbers here and in ``nodes/input_guard``;
steps and barriers by the session), drops unusable ones with a throttled WARN, converts the
rest to core data, hands them to the session with the wall and world times, and performs
the effects it returns: the MotionCommand, team updates and requests, copies of a restarted
teammate's stream, its journals in ``state_dir`` (``nodes/record_journal.py``), what users
see (``nodes/robot_outputs.py``: TF ``map`` -> ``robot_i/odom`` -> ``robot_i/base_link``,
path, landmarks, target, virtual map, markers), log lines and its exit (code 4 when the world
left the graph for good).

Run: ``python -m em_exploration_ros.nodes.robot_node --ros-args -r __ns:=/robot_0
-p robot_id:=0 -p use_sim_time:=true --params-file config/exploration.yaml``
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np
from em_exploration_msgs.msg import (LandmarkDetection, SonarScan, TeamUpdate, TeamUpdateRequest,
                                     TeammateDetection)
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.task import Future
from std_msgs.msg import Header

from em_exploration_ros.core.agent.input_checks import (first_problem, frame_problem,
                                                        landmark_reading_problem, size_problem,
                                                        stamp_step_problem)
from em_exploration_ros.core.links.link_model import FrameKind
from em_exploration_ros.core.node_settings import RobotNodeSettings
from em_exploration_ros.core.records.team_data import (MAX_READINGS_PER_KEYFRAME,
                                                       InvalidTeamUpdate)
from em_exploration_ros.core.records.team_data import TeamUpdate as TeamRecord
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.records.update_screening import only_sender, team_member
from em_exploration_ros.core.records.wire_model import nanoseconds_to_seconds
from em_exploration_ros.core.sessions import robot_effects as fx
from em_exploration_ros.core.sessions.effects import Dropped, LogLine
from em_exploration_ros.core.sessions.robot_session import OdometryInput, RobotSession
from em_exploration_ros.nodes.conversions import (MAP_FRAME, odometry_codec,
                                                  planar_odometry_from_msg, quaternion_to_yaw,
                                                  robot_namespace, scan_input_from_msg)
from em_exploration_ros.nodes.input_guard import (LOG_PERIOD_S, InputGuard,
                                                  checked_team_update, content_problem,
                                                  deserialized, header_problem,
                                                  screened_team_updates, serialized_size,
                                                  size_limited)
from em_exploration_ros.nodes.lean_node import LeanNode
from em_exploration_ros.nodes.liveliness import offer_liveliness, watch_liveliness
from em_exploration_ros.nodes.log_lines import LineWriter
from em_exploration_ros.nodes.message_bounds import request_bytes
from em_exploration_ros.nodes.message_info import MessageInfo, publication_sequence
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.odometry_cdr import PlanarOdometry
from em_exploration_ros.nodes.qos import LATCHED_QOS, SENSOR_QOS, TEAM_QOS
from em_exploration_ros.nodes.record_journal import RecordJournal, robot_journals
from em_exploration_ros.nodes.recorder_presence import topics_not_recorded
from em_exploration_ros.nodes.robot_outputs import RobotOutputs
from em_exploration_ros.nodes.ros_params import (declare_exploration_params,
                                                 declare_node_settings, refuse_unknown_overrides)
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.nodes.team_topics import (delivered_requests_topic,
                                                  delivered_updates_topic)

EXIT_OK = 0


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
        self.journals = robot_journals(self.settings.state_dir, self.robot_id, self.params,
                                       self.wire, self.get_logger())
        self.session = RobotSession(self.robot_id, self.params, self.settings,
                                    journaled=self.journals is not None,
                                    log_period_s=LOG_PERIOD_S, started_s=time.monotonic())
        self.relay_mode = self.session.relay_mode
        self.exit_code = EXIT_OK
        self.done = Future()
        self._ns = robot_namespace(self.robot_id)
        self._lines = LineWriter(self)
        self._create_interfaces()
        self.get_logger().info(
            f"robot {self.robot_id} of {self.num_robots} ready (planner "
            f"{self.params.planner.name}); waiting for the mission anchor and the world")

    def _create_interfaces(self) -> None:
        ns = self._ns
        self.outputs = RobotOutputs(self, self.robot_id, self.params, self.wire, self.relay_mode,
                                    self.settings.run_id)
        self.create_subscription(PoseStamped, "/mission/anchor_pose", self._on_anchor,
                                 LATCHED_QOS)
        # Read raw: a scan longer than the largest valid one (every reading a keyframe may
        # hold, every teammate, a barrier entry per robot) is dropped before it is read.
        scan_topic = f"/{ns}/sonar"
        scan_bytes = serialized_size(SonarScan(
            header=Header(frame_id=f"{ns}/base_link"),
            landmarks=[LandmarkDetection()] * MAX_READINGS_PER_KEYFRAME,
            teammates=[TeammateDetection()] * (self.num_robots - 1),
            team_sequences=[0] * self.num_robots))
        self.create_subscription(SonarScan, scan_topic, size_limited(
            self.inputs, scan_topic, SonarScan, scan_bytes, self._on_scan), SENSOR_QOS, raw=True)
        odom_topic = f"/{ns}/odom"
        self._odom_codec = odometry_codec(f"{ns}/odom", f"{ns}/base_link")
        self.create_subscription(Odometry, odom_topic, size_limited(
            self.inputs, odom_topic, Odometry, self._odom_codec.size, self._on_odometry_data,
            raw=True), SENSOR_QOS, raw=True)
        # Team topics are read raw: requests longer than the largest valid one are dropped
        # unread, records are screened by their head before they are read.
        requests_topic = "/team/update_requests"
        self.create_subscription(TeamUpdateRequest, requests_topic, size_limited(
            self.inputs, requests_topic, TeamUpdateRequest, request_bytes(),
            self._on_update_request), TEAM_QOS, raw=True)
        teammates = [r for r in range(self.num_robots) if r != self.robot_id]
        run_problem = self.session.run_problem
        if self.relay_mode:
            updates_topic = delivered_updates_topic(self.robot_id)
            self.create_subscription(TeamUpdate, updates_topic, screened_team_updates(
                self.inputs, updates_topic, run_problem, team_member(self.num_robots), None,
                self._on_delivered_update, with_info=True), TEAM_QOS, raw=True)
            requests_topic = delivered_requests_topic(self.robot_id)
            self.create_subscription(TeamUpdateRequest, requests_topic, size_limited(
                self.inputs, requests_topic, TeamUpdateRequest, request_bytes(),
                self._on_delivered_request, with_info=True), TEAM_QOS, raw=True)
        else:
            history_topic = f"/{ns}/team/history"
            self.create_subscription(TeamUpdate, history_topic, screened_team_updates(
                self.inputs, history_topic, run_problem, only_sender(self.robot_id), None,
                self._on_own_history), TEAM_QOS, raw=True)
            for teammate in teammates:
                topic = f"/{robot_namespace(teammate)}/team/updates"
                self.create_subscription(TeamUpdate, topic, screened_team_updates(
                    self.inputs, topic, run_problem, only_sender(teammate),
                    self.session.inbox.next_expected,
                    lambda message, sender=teammate: self._on_team_update(sender, message)),
                    TEAM_QOS, raw=True)
        self.alive_pub = offer_liveliness(self, self.robot_id)
        watch_liveliness(self, teammates, lambda *change: self._perform(
            self.session.teammate_liveliness(*change)))
        # Wall (steady) time: in lockstep the sim clock stands still while the world waits.
        self.create_timer(0.1, self._maintain, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- inputs ----------------------------------------------------------------------------

    def _times(self) -> tuple[float, int]:
        """Wall time [s, monotonic] and the world's step, for the session (told first, while
        it waits for the recorder, which of this robot's topics the recorder misses)."""
        if self.session.awaits_recorder:
            self.session.recorder_topics(topics_not_recorded(self))
        return time.monotonic(), self._world_step()

    def _world_step(self) -> int:
        """The step of the world's clock (/clock, validated), as far as it reached here."""
        return int(self.get_clock().now().nanoseconds // round(self.time_step_s * 1e9))

    def _on_anchor(self, message: PoseStamped) -> None:
        if self.session.agent is not None:
            return
        p = message.pose
        anchor = np.array([p.position.x, p.position.y, quaternion_to_yaw(p.orientation)])
        if self.inputs.check("/mission/anchor_pose", header_problem(message.header, MAP_FRAME),
                             content_problem(message)):
            self._perform(self.session.anchor(anchor, *self._times()))

    def scan_problem(self, message: SonarScan) -> str | None:
        """Reason to drop a sonar scan: addressed to another robot, wrong frame or stamp,
        implausible step, barrier, array sizes, ids or numbers."""
        robot, session, step = self.robot_id, self.session, int(message.step)
        stamp_ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        return ((f"scan addressed to robot {message.robot_id}"
                 if message.robot_id != robot else None)
                or header_problem(message.header, f"{self._ns}/base_link")
                or session.sensor_step_problem(step, False, self._world_step())
                or stamp_step_problem(stamp_ns, step, self.time_step_s)
                or session.barrier_problem(message.team_sequences, step)
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

    def _of_this_run(self, topic: str, message: SonarScan | TeamUpdateRequest) -> bool:
        """False for a message of another run (dropped, with the throttled WARN)."""
        return self.inputs.check(topic, self.session.run_problem(int(message.run_id)))

    def _on_scan(self, message: SonarScan) -> None:
        step = int(message.step)
        if not self._of_this_run(f"/{self._ns}/sonar", message):
            return
        if message.robot_id == self.robot_id and self.session.processed(step):
            self._perform(self.session.scan_again(step))  # our answer did not arrive
        elif self.inputs.check(f"/{self._ns}/sonar", self.scan_problem(message)):
            self._perform(self.session.scan(scan_input_from_msg(message), *self._times()))

    def _on_odometry_data(self, data: bytes) -> None:
        """Serialized dead reckoning: read in one struct when it is in the world's own form
        (``nodes.odometry_cdr``), otherwise as a message with every check."""
        odometry = self._odom_codec.decode(data)
        if odometry is not None:
            self._take_odometry(odometry)
            return
        ns = self._ns
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
        if self.session.processed(step):
            return  # a re-sent step this robot already answered
        if self.inputs.check(f"/{self._ns}/odom", *message_problems,
                             self.session.sensor_step_problem(step, True, self._world_step()),
                             stamp_step_problem(stamp_ns, step, self.time_step_s)):
            self._perform(self.session.odometry(
                step, OdometryInput(odometry.pose, odometry.twist_covariance), *self._times()))

    def _record(self, message: TeamUpdate) -> TeamRecord | InvalidTeamUpdate:
        """A received record as core data, or why its message is refused."""
        try:
            return checked_team_update(message, self.wire)
        except InvalidTeamUpdate as error:
            return error

    def _on_team_update(self, sender: int, message: TeamUpdate) -> None:
        """A teammate's record whose head ``screened_team_updates`` passed (of this run)."""
        topic = f"/{robot_namespace(sender)}/team/updates"
        self._perform(self.session.team_update(self._record(message), sender, *self._times()),
                      topic)

    def _on_delivered_update(self, message: TeamUpdate, info: MessageInfo) -> None:
        """A record the links delivered whose head ``screened_team_updates`` passed."""
        self._perform(self.session.delivered_update(
            int(message.robot_id), self._record(message), publication_sequence(info),
            *self._times()), delivered_updates_topic(self.robot_id))

    def _on_delivered_request(self, message: TeamUpdateRequest, info: MessageInfo) -> None:
        if not self._of_this_run(delivered_requests_topic(self.robot_id), message):
            return
        self._perform(self.session.delivered_request(
            int(message.requester_id), int(message.robot_id), int(message.first_sequence),
            int(message.last_sequence), publication_sequence(info), *self._times()),
            delivered_requests_topic(self.robot_id))

    def _on_update_request(self, message: TeamUpdateRequest) -> None:
        if not self._of_this_run("/team/update_requests", message):
            return
        self._perform(self.session.update_request(
            int(message.requester_id), int(message.robot_id), int(message.first_sequence),
            int(message.last_sequence), time.monotonic()), "/team/update_requests")

    def _on_own_history(self, message: TeamUpdate) -> None:
        """A copy of this robot's record whose head ``screened_team_updates`` passed."""
        self._perform(self.session.own_history(self._record(message)))

    def _maintain(self) -> None:
        """The session's 10 Hz tick, with whether the world publishes this robot's scans
        when the session wants to know."""
        now, world_step = self._times()
        present = (self.count_publishers(f"/{self._ns}/sonar") > 0
                   if self.session.world_check_due(now) else None)
        self._perform(self.session.tick(now, world_step, present))

    # -- effects ---------------------------------------------------------------------------

    def _perform(self, effects: list, topic: str = "") -> None:
        """Perform the session's effects in order (``topic``: the input's, for a drop)."""
        agent, outputs = self.session.agent, self.outputs
        for effect in effects:
            kind = type(effect)
            if kind is LogLine:
                self._lines.write(effect)
            elif kind is fx.PublishCorrespondences:
                outputs.correspondences(effect)
            elif kind is fx.SendCommand:
                outputs.command(effect.reply, effect.again)
            elif kind is fx.PublishUpdate:
                outputs.update(effect.record, effect.what)
            elif kind is fx.PublishRequest:
                outputs.request(effect.owner, effect.first_sequence, effect.last_sequence)
            elif kind is fx.SendFrame and effect.frame.kind == FrameKind.REQUEST:
                gap = effect.frame.payload
                outputs.request(gap.robot_id, gap.first_sequence, gap.last_sequence)
            elif kind is fx.SendFrame:
                record = effect.frame.payload
                outputs.update(record, f"team record {record.sequence} (teammates will ask "
                                       f"for it again)")
            elif kind is fx.PublishHistory:
                outputs.history(effect.requester, effect.records)
            elif kind is fx.StartJournal:
                self._journal(effect.journal).start(effect.records, effect.fresh)
            elif kind is fx.AppendJournal:
                self._journal(effect.journal).append(effect.record)
            elif kind is fx.ReadJournals:
                own, team = self.journals
                self._perform(self.session.journals_read(own.read_back(), team.read_back(),
                                                         *self._times()))
            elif kind is fx.PublishTransforms:
                outputs.transforms(agent, effect.stamp_s, effect.odom_pose)
            elif kind is fx.PublishEstimates:
                outputs.estimates(agent, effect.stamp_s, effect.latest)
            elif kind is fx.PublishDecision:
                outputs.decision(agent, effect.stamp_s)
            elif kind is Dropped:
                self.inputs.drop(topic, effect.reason)
            elif kind is fx.Exit:
                self.exit_code = effect.code
                if not self.done.done():
                    self.done.set_result(effect.code)

    def _journal(self, journal: fx.Journal) -> RecordJournal:
        """The node's journal of that kind (the session asks only when it has them)."""
        return self.journals[0 if journal == fx.Journal.OWN else 1]



def main(args: list[str] | None = None) -> int:
    """Entry point of em-robot; returns the exit code (2 for invalid parameters, 4 when
    its world left the graph for good)."""
    return run_node(RobotNode, "em_robot", args, wrap_up=_log_graph)


def _log_graph(node: RobotNode) -> int:
    """At the end (Ctrl-C, SIGTERM, world gone): what the team graph holds, for the run's
    logs; returns the node's exit code."""
    line = node.session.team_graph_line()
    if line is not None:
        node._lines.write(line)
    return node.exit_code


if __name__ == "__main__":
    sys.exit(main())
