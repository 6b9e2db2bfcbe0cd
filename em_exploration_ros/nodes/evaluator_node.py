"""em-evaluator: the outside observer of a run; the ROS shell of ``EvaluatorSession``.

The protocol (what is recorded, when the team metrics are evaluated, the stop rules, what
the run waits for before it ends, the exit codes 0, 3, 4, 5 and 130, the summary) is
``core/sessions/evaluator_session.py``'s. This node declares the parameters, subscribes to
the ground truth (``/world/ground_truth/robot_i``, ``/world/landmarks``, ``/world/status``,
``/world/link_counts`` in relay mode) and to what each robot publishes
(``/robot_i/estimated_path``, ``/robot_i/landmarks``, ``/robot_i/estimated_pose``,
``/robot_i/team/updates``, ``/robot_i/motion_command``, its liveliness), checks each message's
header and numbers, hands it to the session as core values (wall times from the steady clock),
and performs the effects: ``/evaluation/metrics``, ``/team/update_requests`` (it never
publishes anything a robot uses for its estimates or decisions), log lines, the summary JSON
(the summary so far while the run goes on, ``KeepSoFar``) and the final map PNG, the exit code.
When the sonar is not the paper's ideal one it also takes the truth of each robot's keyframe
scans (``/world/sonar_truth/robot_i``) and, without landmark identities, the landmarks each
robot tied to its own (``/robot_i/landmark_correspondences``): the summary's ``association``.

Run (with the simulation clock): ``python -m em_exploration_ros.nodes.evaluator_node
--ros-args -p use_sim_time:=true -p summary_path:=runs/x/summary.json``
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from builtin_interfaces.msg import Time
from em_exploration_msgs.msg import (ExplorationMetrics, LandmarkArray,
                                     LandmarkCorrespondences, MotionCommand, SonarTruth,
                                     TeamLinkCounts, TeamUpdate, TeamUpdateRequest, WorldStatus)
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path as PathMsg
from rclpy.clock import Clock, ClockType
from rclpy.task import Future
from std_msgs.msg import Header

from em_exploration_ros.core.agent.input_checks import frame_problem, size_problem
from em_exploration_ros.core.links.link_model import perfect_links
from em_exploration_ros.core.node_settings import EvaluatorNodeSettings
from em_exploration_ros.core.output_paths import output_path_problem
from em_exploration_ros.core.records.team_data import (MAX_LANDMARKS_PER_UPDATE,
                                                     InvalidTeamUpdate, LandmarkEstimate)
from em_exploration_ros.core.records.readings import UNIDENTIFIED, LandmarkReading
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.records.update_screening import only_sender
from em_exploration_ros.core.records.wire_model import sim_time_s
from em_exploration_ros.core.sessions.effects import Dropped, LogLine, warn
from em_exploration_ros.core.world.sensors import CLUTTER
from em_exploration_ros.core.sessions.evaluator_effects import (CommandReport, Effect, Finished,
                                                                KeepSoFar, PublishMetrics,
                                                                RequestUpdates)
from em_exploration_ros.core.sessions.evaluator_session import (EXIT_INTERRUPTED,
                                                                EvaluatorSession)
from em_exploration_ros.nodes.conversions import (MAP_FRAME, WORLD_FRAME, WORLD_NODE_NAME,
                                                  WORLD_STATUS_TOPIC, given_up_from_msg,
                                                  keyframe_covariance_from_msg,
                                                  landmark_array_to_msg,
                                                  landmark_positions_from_msg,
                                                  meeting_from_msg, odometry_codec,
                                                  odometry_pose, planar_path, robot_namespace,
                                                  serialized_path)
from em_exploration_ros.nodes.input_guard import (InputGuard, checked_team_update,
                                                  content_problem, deserialized, header_problem,
                                                  path_problem, publish_or_log,
                                                  screened_team_updates, serialized_size,
                                                  size_limited)
from em_exploration_ros.nodes.evaluator_outputs import (draw_pictures, metrics_to_msg,
                                                        replace_summary)
from em_exploration_ros.nodes.lean_node import LeanNode
from em_exploration_ros.nodes.message_bounds import motion_command_bytes
from em_exploration_ros.nodes.liveliness import watch_liveliness
from em_exploration_ros.nodes.log_lines import LineWriter
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.odometry_cdr import OdometryCodec
from em_exploration_ros.nodes.path_cdr import PathDecodeError, decode_path
from em_exploration_ros.nodes.qos import (COMMAND_QOS, ESTIMATE_READER_QOS, GROUND_TRUTH_QOS,
                                          LATCHED_QOS, LIVELINESS_LEASE_S, STREAM_QOS,
                                          TEAM_QOS)
from em_exploration_ros.nodes.ros_params import (declare_exploration_params,
                                                 declare_node_settings, refuse_unknown_overrides)
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.nodes.team_topics import LINK_COUNTS_TOPIC

#: Wall period of the session's watch (silence, liveliness, the world's end) [s].
_WATCH_PERIOD_S = 1.0
#: Longest reason a WorldStatus may give (longer statuses are dropped unread).
_MAX_REASON_CHARS = 200


def _stamp_ns(stamp: Time | tuple[int, int]) -> int:
    """A builtin_interfaces/Time or (sec, nanosec) as nanoseconds."""
    sec, nanosec = (stamp.sec, stamp.nanosec) if isinstance(stamp, Time) else stamp
    return sec * 1_000_000_000 + nanosec


def command_report_from_msg(message: MotionCommand, time_step_s: float) -> CommandReport:
    """What the evaluator reads in a robot's MotionCommand (``time_step_s`` [s]: the
    simulation step); ValueError for an unknown give-up reason."""
    stamp_s = sim_time_s(int(message.step), time_step_s)
    return CommandReport(
        int(message.robot_id), int(message.step), _stamp_ns(message.header.stamp),
        bool(message.finished), int(message.team_sequence), float(message.blocked_s),
        int(message.given_up_count), tuple(given_up_from_msg(g, stamp_s)
                                           for g in message.given_up),
        tuple(meeting_from_msg(m, int(message.robot_id)) for m in message.meetings),
        int(message.slam_recoveries))


class EvaluatorNode(LeanNode):
    """Team metrics, the run's stop rule and its summary (see ``EvaluatorSession``)."""

    def __init__(self) -> None:
        super().__init__("em_evaluator")
        self.inputs = InputGuard(self)
        install_validated_clock(self, self.inputs)
        settings = declare_node_settings(self, EvaluatorNodeSettings)
        self.summary_path = Path(settings.summary_path)
        self.map_png_path = Path(settings.map_png_path) if settings.map_png_path else (
            self.summary_path.with_name(f"{self.summary_path.stem}_map.png"))
        for path, what in ((self.summary_path, "summary_path"), (self.map_png_path,
                                                                 "map_png_path")):
            problem = output_path_problem(path, what)
            if problem:
                raise ValueError(problem)
        self.params = declare_exploration_params(self)
        self.wire = TeamWireFormat(self.params)
        refuse_unknown_overrides(self)
        self.num_robots = self.params.world.num_robots
        self.session = EvaluatorSession(self.params, settings, time.monotonic(),
                                        LIVELINESS_LEASE_S, WORLD_NODE_NAME,
                                        keep_so_far=True)
        self.done = Future()
        self._lines = LineWriter(self)
        self._create_interfaces()
        self.get_logger().info(f"{self.session.describe()}; summary -> {self.summary_path}")

    def _create_interfaces(self) -> None:
        if not perfect_links(self.params.links):  # first: taken before a step's ground truth
            self.create_subscription(TeamLinkCounts, LINK_COUNTS_TOPIC, self._on_link_counts,
                                     GROUND_TRUTH_QOS)
        self.metrics_pub = self.create_publisher(ExplorationMetrics, "/evaluation/metrics",
                                                 STREAM_QOS)
        self.request_pub = self.create_publisher(TeamUpdateRequest, "/team/update_requests",
                                                 TEAM_QOS)
        self.create_subscription(LandmarkArray, "/world/landmarks", self._on_true_landmarks_data,
                                 LATCHED_QOS, raw=True)
        status_bytes = serialized_size(WorldStatus(header=Header(frame_id=WORLD_FRAME),
                                                   reason="x" * _MAX_REASON_CHARS))
        self.create_subscription(WorldStatus, WORLD_STATUS_TOPIC, size_limited(
            self.inputs, WORLD_STATUS_TOPIC, WorldStatus, status_bytes, self._on_world_status),
            LATCHED_QOS, raw=True)
        # The largest valid estimates: a path with a pose per keyframe of the run, a
        # landmark set of the most landmarks an update may hold.
        keyframes = self.session.max_keyframes
        path_bytes = len(serialized_path(0.0, np.zeros(keyframes), np.zeros((keyframes, 3))))
        landmarks_bytes = serialized_size(landmark_array_to_msg(0.0, MAP_FRAME, [
            LandmarkEstimate(0, np.zeros(2), np.eye(2))] * MAX_LANDMARKS_PER_UPDATE))
        pose_bytes = serialized_size(PoseWithCovarianceStamped(header=Header(
            frame_id=MAP_FRAME)))
        for robot in range(self.num_robots):
            ns = robot_namespace(robot)
            truth_topic = f"/world/ground_truth/{ns}"
            truth_codec = odometry_codec(WORLD_FRAME, f"{ns}/base_link")
            self.create_subscription(Odometry, truth_topic, size_limited(
                self.inputs, truth_topic, Odometry, truth_codec.size,
                lambda data, r=robot, c=truth_codec: self._on_truth_data(r, c, data), raw=True),
                GROUND_TRUTH_QOS, raw=True)
            path_topic, landmarks_topic = f"/{ns}/estimated_path", f"/{ns}/landmarks"
            self.create_subscription(
                PathMsg, path_topic, size_limited(
                    self.inputs, path_topic, PathMsg, path_bytes,
                    lambda data, r=robot: self._on_path(r, data), raw=True),
                ESTIMATE_READER_QOS, raw=True)
            self.create_subscription(
                LandmarkArray, landmarks_topic, size_limited(
                    self.inputs, landmarks_topic, LandmarkArray, landmarks_bytes,
                    lambda m, r=robot: self._on_landmark_estimates(r, m)),
                ESTIMATE_READER_QOS, raw=True)
            pose_topic = f"/{ns}/estimated_pose"
            self.create_subscription(
                PoseWithCovarianceStamped, pose_topic, size_limited(
                    self.inputs, pose_topic, PoseWithCovarianceStamped, pose_bytes,
                    lambda m, r=robot: self._on_keyframe_estimate(r, m)),
                ESTIMATE_READER_QOS, raw=True)
            updates_topic = f"/{ns}/team/updates"  # read raw: a flood is screened first
            self.create_subscription(TeamUpdate, updates_topic, screened_team_updates(
                self.inputs, updates_topic, self.session.run_problem, only_sender(robot),
                self.session.next_expected, lambda m, r=robot: self._on_team_update(r, m)),
                TEAM_QOS, raw=True)
            command_topic = f"/{ns}/motion_command"
            self.create_subscription(MotionCommand, command_topic, size_limited(
                self.inputs, command_topic, MotionCommand, motion_command_bytes(),
                lambda m, r=robot: self._on_command(r, m)), COMMAND_QOS, raw=True)
        if self.session.association is not None:
            self._subscribe_association()
        watch_liveliness(self, list(range(self.num_robots)), lambda robot, alive, restarted:
                         self._perform(self.session.liveliness(robot, alive, restarted,
                                                               time.monotonic())))
        self.create_timer(_WATCH_PERIOD_S, self._watch,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _subscribe_association(self) -> None:
        """The sonar is not ideal: the truth of each robot's keyframe scans and, without
        landmark identities, the landmarks each robot tied to its own (association counts)."""
        truth_bytes = serialized_size(SonarTruth(
            header=Header(frame_id=f"{robot_namespace(self.num_robots)}/base_link"),
            range=[0.0] * MAX_LANDMARKS_PER_UPDATE, bearing=[0.0] * MAX_LANDMARKS_PER_UPDATE,
            source=[0] * MAX_LANDMARKS_PER_UPDATE))
        ties_bytes = serialized_size(LandmarkCorrespondences(
            header=Header(frame_id=MAP_FRAME), own_landmark_ids=[0] * MAX_LANDMARKS_PER_UPDATE,
            teammate_landmark_ids=[0] * MAX_LANDMARKS_PER_UPDATE))
        for robot in range(self.num_robots):
            ns = robot_namespace(robot)
            truth_topic = f"/world/sonar_truth/{ns}"
            self.create_subscription(SonarTruth, truth_topic, size_limited(
                self.inputs, truth_topic, SonarTruth, truth_bytes,
                lambda m, r=robot: self._on_sonar_truth(r, m)), GROUND_TRUTH_QOS, raw=True)
            if self.params.sensors.landmark_ids:
                continue
            ties_topic = f"/{ns}/landmark_correspondences"
            self.create_subscription(LandmarkCorrespondences, ties_topic, size_limited(
                self.inputs, ties_topic, LandmarkCorrespondences, ties_bytes,
                lambda m, r=robot: self._on_correspondences(r, m)), COMMAND_QOS, raw=True)

    # -- inputs ----------------------------------------------------------------------------

    def _on_true_landmarks_data(self, data: bytes) -> None:
        """The world's landmarks, serialized: read only while the evaluator waits for them (a
        flood of /world/landmarks cost it 6 ms per message on average, up to 80 ms)."""
        if self.session.evaluator is None:
            message = deserialized(self.inputs, "/world/landmarks", LandmarkArray, data)
            if message is not None:
                self._on_true_landmarks(message)

    def _on_true_landmarks(self, message: LandmarkArray) -> None:
        if self.session.evaluator is not None or not self.inputs.check(
                "/world/landmarks", header_problem(message.header, WORLD_FRAME),
                content_problem(message)):
            return
        ids = [int(lm.landmark_id) for lm in message.landmarks]
        positions = np.array([[lm.x, lm.y] for lm in message.landmarks]).reshape(-1, 2)
        self._perform(self.session.true_landmarks(ids, positions, message.radius,
                                                  time.monotonic()), "/world/landmarks")

    def _on_truth_data(self, robot: int, codec: OdometryCodec, data: bytes) -> None:
        """A robot's serialized ground truth: read in one struct when it is in the world's
        own form (``nodes.odometry_cdr``), otherwise as a message with every check."""
        topic = f"/world/ground_truth/{robot_namespace(robot)}"
        truth = codec.decode(data)
        if truth is not None:
            self._take_truth(robot, topic, _stamp_ns(truth.stamp), truth.pose)
            return
        message = deserialized(self.inputs, topic, Odometry, data)
        if message is None or not self.inputs.check(
                topic, header_problem(message.header, WORLD_FRAME),
                frame_problem(message.child_frame_id, f"{robot_namespace(robot)}/base_link",
                              "child_frame_id"),
                content_problem(message)):
            return
        self._take_truth(robot, topic, _stamp_ns(message.header.stamp), odometry_pose(message))

    def _take_truth(self, robot: int, topic: str, stamp_ns: int, pose: np.ndarray) -> None:
        step, problem = self.session.step_of(stamp_ns)
        if self.inputs.check(topic, problem):
            self._perform(self.session.true_pose(robot, step, pose, time.monotonic()), topic)

    def _on_path(self, robot: int, data: bytes) -> None:
        """A robot's serialized trajectory, read with NumPy (``nodes.path_cdr``)."""
        topic = f"/{robot_namespace(robot)}/estimated_path"
        try:
            path = decode_path(data)
        except PathDecodeError as error:
            self.inputs.drop(topic, f"malformed path: {error}")
            return
        if path is None:
            self.inputs.drop(topic, "pose frame_ids differ from the path's")
            return
        if self.inputs.check(topic, path_problem(path, MAP_FRAME)):
            stamps_s, poses = planar_path(path)
            self._perform(self.session.path_estimate(robot, _stamp_ns(path.stamp), stamps_s,
                                                     poses, time.monotonic()), topic)

    def _on_landmark_estimates(self, robot: int, message: LandmarkArray) -> None:
        topic = f"/{robot_namespace(robot)}/landmarks"
        if self.inputs.check(topic, header_problem(message.header, MAP_FRAME),
                             size_problem(len(message.landmarks), MAX_LANDMARKS_PER_UPDATE,
                                          "landmarks"), content_problem(message)):
            self._perform(self.session.landmark_estimate(
                robot, _stamp_ns(message.header.stamp), landmark_positions_from_msg(message),
                time.monotonic()), topic)

    def _on_keyframe_estimate(self, robot: int, message: PoseWithCovarianceStamped) -> None:
        """A robot's latest keyframe with its covariance: the covariance is what is read."""
        topic = f"/{robot_namespace(robot)}/estimated_pose"
        if self.inputs.check(topic, header_problem(message.header, MAP_FRAME),
                             content_problem(message)):
            self._perform(self.session.keyframe_covariance(
                robot, _stamp_ns(message.header.stamp), keyframe_covariance_from_msg(message),
                time.monotonic()), topic)

    def _on_sonar_truth(self, robot: int, message: SonarTruth) -> None:
        """Where each detection of a robot's keyframe scan came from (the world's truth)."""
        topic = f"/world/sonar_truth/{robot_namespace(robot)}"
        if not self.inputs.check(
                topic, self.session.run_problem(int(message.run_id)),
                header_problem(message.header, f"{robot_namespace(robot)}/base_link"),
                f"robot_id {message.robot_id} on robot {robot}'s topic"
                if message.robot_id != robot else None,
                f"{len(message.range)} ranges, {len(message.bearing)} bearings"
                if len(message.range) != len(message.bearing) else None,
                content_problem(message)):
            return
        readings = tuple(LandmarkReading(UNIDENTIFIED, float(r), float(b), 0.0, 0.0)
                         for r, b in zip(message.range, message.bearing))
        sources = tuple(CLUTTER if s == SonarTruth.CLUTTER else int(s)
                        for s in message.source)
        self._perform(self.session.sonar_truth(robot, _stamp_ns(message.header.stamp),
                                               int(message.step), readings, sources,
                                               time.monotonic()), topic)

    def _on_correspondences(self, robot: int, message: LandmarkCorrespondences) -> None:
        """The teammates' landmarks a robot tied to its own while answering a step."""
        topic = f"/{robot_namespace(robot)}/landmark_correspondences"
        if not self.inputs.check(
                topic, self.session.run_problem(int(message.run_id)),
                header_problem(message.header, MAP_FRAME),
                f"robot_id {message.robot_id} on robot {robot}'s topic"
                if message.robot_id != robot else None,
                f"{len(message.own_landmark_ids)} own landmarks, "
                f"{len(message.teammate_landmark_ids)} teammates'"
                if len(message.own_landmark_ids) != len(message.teammate_landmark_ids)
                else None):
            return
        pairs = [(int(own), int(theirs)) for own, theirs in
                 zip(message.own_landmark_ids, message.teammate_landmark_ids)]
        self._perform(self.session.correspondences(robot, _stamp_ns(message.header.stamp),
                                                   int(message.step), pairs,
                                                   time.monotonic()), topic)

    def _on_link_counts(self, message: TeamLinkCounts) -> None:
        if not self.inputs.check(LINK_COUNTS_TOPIC,
                                 self.session.run_problem(int(message.run_id))):
            return
        counts = {"sent": int(message.sent), "on_time": int(message.on_time),
                  "late": int(message.late), "never": int(message.never)}
        self._perform(self.session.link_counts(int(message.step), counts), LINK_COUNTS_TOPIC)

    def _on_world_status(self, message: WorldStatus) -> None:
        stamp_step, problem = self.session.step_of(_stamp_ns(message.header.stamp))
        if self.inputs.check(WORLD_STATUS_TOPIC, self.session.run_problem(int(message.run_id)),
                             header_problem(message.header, WORLD_FRAME), problem):
            self._perform(self.session.world_status(int(message.step), stamp_step,
                                                    message.stepping_over, message.reason),
                          WORLD_STATUS_TOPIC)

    def _on_team_update(self, robot: int, message: TeamUpdate) -> None:
        """A record whose head ``screened_team_updates`` passed (of this run)."""
        topic = f"/{robot_namespace(robot)}/team/updates"
        try:
            update = checked_team_update(message, self.wire)
        except InvalidTeamUpdate as error:
            self.inputs.drop(topic, f"rejected a team update: {error}")
            return
        self._perform(self.session.team_update(robot, update, time.monotonic()), topic)

    def _on_command(self, robot: int, message: MotionCommand) -> None:
        topic = f"/{robot_namespace(robot)}/motion_command"
        try:
            report, problem = command_report_from_msg(message, self.session.time_step_s), None
        except ValueError as error:
            report, problem = None, str(error)
        if self.inputs.check(topic, self.session.run_problem(int(message.run_id)),
                             header_problem(message.header, f"{robot_namespace(robot)}/base_link"),
                             content_problem(message), problem):
            self._perform(self.session.command(robot, report, time.monotonic()), topic)

    def _watch(self) -> None:
        topic = f"/world/ground_truth/{robot_namespace(0)}"
        publishers = frozenset(info.node_name for info in
                               self.get_publishers_info_by_topic(WORLD_STATUS_TOPIC))
        self._perform(self.session.tick(time.monotonic(), self.count_publishers(topic) > 0,
                                        publishers))

    # -- effects ---------------------------------------------------------------------------

    def _perform(self, effects: list[Effect], topic: str = "") -> None:
        """Do what the session asked, in order; ``topic``: where the input came from."""
        for effect in effects:
            if isinstance(effect, Dropped):
                self.inputs.drop(topic, effect.reason)
            elif isinstance(effect, LogLine):
                self._lines.write(effect)
            elif isinstance(effect, PublishMetrics):
                self.metrics_pub.publish(metrics_to_msg(effect))
            elif isinstance(effect, RequestUpdates):
                for gap in effect.gaps:
                    request = TeamUpdateRequest(run_id=self.session.settings.run_id,
                                                requester_id=TeamUpdateRequest.OBSERVER,
                                                robot_id=gap.robot_id,
                                                first_sequence=gap.first_sequence,
                                                last_sequence=gap.last_sequence)
                    request.header.stamp = self.get_clock().now().to_msg()
                    publish_or_log(self.request_pub, request, self, "a request for updates")
            elif isinstance(effect, KeepSoFar):
                self._keep_so_far(effect)
            elif isinstance(effect, Finished):
                self._write(effect)

    def _keep_so_far(self, effect: KeepSoFar) -> None:
        """The summary so far replaces the summary file (a full disk: the previous one is
        kept, and said at most every few seconds)."""
        try:
            replace_summary(self.summary_path, effect.summary)
        except OSError as error:
            self._lines.write(warn(f"could not keep the summary so far: {error}",
                                   "summary so far"))

    def _write(self, finished: Finished) -> None:
        """The summary JSON (replacing the summary so far), the map and the timeline; then
        ``done`` completes."""
        replace_summary(self.summary_path, finished.summary)
        log = self.get_logger()
        log.info(f"summary: {self.summary_path}")
        if self.session.evaluator is not None:
            for picture in draw_pictures(
                    finished.summary, self.session.map_layers(finished.summary.stop_reason),
                    self.summary_path, self.map_png_path):
                log.info(f"picture: {picture}")
        if not self.done.done():
            self.done.set_result(finished.exit_code)


def main(args: list[str] | None = None) -> int:
    """Entry point of em-evaluator; returns the exit code (see ``EvaluatorSession``)."""
    return run_node(EvaluatorNode, "em_evaluator", args, wrap_up=_keep_what_was_measured)


def _keep_what_was_measured(node: EvaluatorNode) -> int:
    """After Ctrl-C (rclpy's handler ends the spin) or SIGTERM the summary so far is still
    written; returns the node's exit code."""
    node._perform(node.session.finish("interrupted", EXIT_INTERRUPTED, time.monotonic(),
                                      publish=False))
    return node.session.exit_code


if __name__ == "__main__":
    sys.exit(main())
