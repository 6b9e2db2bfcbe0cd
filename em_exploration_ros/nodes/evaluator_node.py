"""em-evaluator: the outside observer of a run; a thin shell around ``core.evaluation.evaluator``.

Subscribes to the ground truth (``/world/ground_truth/robot_i``, ``/world/landmarks``) and to
what each robot publishes (``/robot_i/estimated_path``, ``/robot_i/landmarks``,
``/robot_i/team/updates`` for the chosen targets, ``/robot_i/motion_command`` for the
finished flags and the robots' own progress bookkeeping). It never publishes anything a
robot uses for its estimates or decisions; it only asks robots to re-send team updates it
missed, as robots do.

A simulation step is complete when the true poses of every robot at that step arrived; steps
are recorded in order. Every ``metrics_interval_s`` of simulation time (default 2 s = em-sim's
10 steps) the team metrics are evaluated from each robot's estimates as of the step before
(waiting up to ``estimate_wait_s`` for those of the last keyframe), so a seeded lockstep run
gives the same metrics every time, whatever the message timing. They are published on
``/evaluation/metrics`` (ExplorationMetrics) and kept; a progress line is logged every
``progress_interval_s``. Each evaluation goes to the run monitor
(``core.evaluation.run_monitor.RunMonitor``, the same stop rule and summary as em-sim). Once a
stop rule fired, the evaluator waits (up to ``estimate_wait_s``) until every robot's update
stream is complete up to the sequence the robot reported, so that the summary lists every
decision made before the stop step, and until every robot's motion command of the step before
is in; the summary holds the values of that step. The run ends,
with the summary JSON (em-sim's schema) and the final map PNG written, when:

- the team explored ratio reaches ``run.until_explored``, the team distance reaches
  ``run.max_distance_m``, or every robot reports ``finished``: exit code 0;
- every robot that is not lost reports ``finished`` while others were lost before they
  finished (a robot that rejoined is not lost): the run ended below ``run.until_explored``
  with part of the team gone; stop reason "every live robot finished; robots [...] lost",
  exit code 5 (``EXIT_ROBOTS_LOST``); the summary's per-robot ``status``, ``status_changes``
  and ``downtime_s`` show the losses;
- the run's final step (``run.max_steps`` or ``max_sim_time_s``, as the world) completed:
  exit code 0, the stop reason says so;
- no ground truth arrived for ``silence_timeout_s`` wall seconds (world or robots
  stopped), or sooner when the world said on /world/status that it stepped over and no stop
  rule fired here (``liveliness_grace_s`` later if every robot is lost, else
  ``estimate_wait_s``): exit code 3;
  Ctrl-C: the summary so far, exit code 130;
- the team neither travelled nor explored new area for ``run.stall_timeout_s`` of
  simulation time: stop reason "stalled: ...", exit code 4 (``EXIT_STALLED``).

Each robot's motion command carries its own progress bookkeeping (issue 17): the time its
odometry showed it blocked so far and the targets it gave up at that step. The summary's
``given_up`` lists those given up before the stop step and ``blocked_s`` is the value of the
command answering the step before it, as em-sim's agents hold them at that step (null for a
robot whose command of that step never arrived; for a restarted robot, its new process's).

Run (with the simulation clock): ``python -m em_exploration_ros.nodes.evaluator_node
--ros-args -p use_sim_time:=true -p summary_path:=runs/x/summary.json``
"""
from __future__ import annotations

import math
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
from em_exploration_msgs.msg import (ExplorationMetrics, LandmarkArray, MotionCommand,
                                     TeamLinkCounts, TeamUpdate, TeamUpdateRequest, WorldStatus)
from nav_msgs.msg import Odometry, Path as PathMsg
from std_msgs.msg import Header
from builtin_interfaces.msg import Time
from rclpy.clock import Clock, ClockType
from rclpy.task import Future

from em_exploration_ros.core.records.team_data import (MAX_LANDMARKS_PER_UPDATE,
                                                     MAX_SEQUENCE_LEAD, InvalidTeamUpdate,
                                                     LandmarkEstimate, MissingRange, RendezvousEvent, TargetRecord,
                                                     TeamUpdateInbox)
from em_exploration_ros.core.evaluation.evaluator import (TeamEvaluator, TeamMetrics, landmark_truth,
                                                          stamp_key)
from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers, evaluation_layers
from em_exploration_ros.core.evaluation.map_render import render_team_map
from em_exploration_ros.core.evaluation.rendezvous_stats import rendezvous_outcomes
from em_exploration_ros.core.agent.input_checks import (EVALUATOR_STEP_LEAD, first_problem,
                                                        frame_problem, id_problem,
                                                        command_sequence_problem, size_problem,
                                                        stamp_step_problem, step_problem)
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.agent.world_watch import WorldEvent, WorldWatch
from em_exploration_ros.core.agent.liveness import LOST, TeamLiveness, UnseenLiveliness
from em_exploration_ros.core.evaluation.run_monitor import (DecisionEntry, RobotProgressRecord,
                                                            RunMonitor, TeamFinished,
                                                            every_live_robot_finished)
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, RunSummary
from em_exploration_ros.core.node_settings import EvaluatorNodeSettings
from em_exploration_ros.core.output_paths import output_path_problem
from em_exploration_ros.core.links.link_model import perfect_links
from em_exploration_ros.core.records.wire_model import sim_time_s
from em_exploration_ros.nodes.conversions import (MAP_FRAME, WORLD_FRAME, WORLD_NODE_NAME,
                                                  WORLD_STATUS_TOPIC, given_up_from_msg,
                                                  landmark_array_to_msg,
                                                  landmark_positions_from_msg,
                                                  odometry_codec, odometry_pose, planar_path,
                                                  robot_namespace, serialized_path,
                                                  seconds_to_time,
                                                  time_to_seconds)
from em_exploration_ros.nodes.lean_node import LeanNode
from em_exploration_ros.nodes.liveliness import watch_liveliness
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.odometry_cdr import OdometryCodec
from em_exploration_ros.nodes.path_cdr import PathDecodeError, decode_path
from em_exploration_ros.nodes.qos import (ESTIMATE_READER_QOS, GROUND_TRUTH_QOS, LATCHED_QOS,
                                          LIVELINESS_LEASE_S, SENSOR_QOS, STREAM_QOS,
                                          TEAM_QOS)
from em_exploration_ros.nodes.input_guard import (LOG_PERIOD_S, InputGuard, checked_team_update,
                                                  content_problem, deserialized, header_problem,
                                                  path_problem, publish_or_log, serialized_size,
                                                  size_limited)
from em_exploration_ros.nodes.ros_params import (declare_exploration_params,
                                                 declare_node_settings, refuse_unknown_overrides)
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.nodes.team_topics import LINK_COUNTS_TOPIC

EXIT_SILENCE, EXIT_INTERRUPTED = 3, 130
#: Wall period of the silence check [s].
_WATCH_PERIOD_S = 1.0
#: Relay mode: the link counts of this many evaluation steps before the newest are kept.
_LINK_COUNTS_KEPT = 100
#: Longest reason a WorldStatus may give (longer statuses are dropped unread).
_MAX_REASON_CHARS = 200


class StampedEstimates:
    """What each robot published over time (paths, landmark sets), keyed by their stamps,
    so that an evaluation reads every robot's estimate as of a given simulation time."""

    def __init__(self) -> None:
        self._items: dict[int, dict[int, Any]] = {}

    def add(self, robot: int, stamp_s: float, value: Any) -> None:
        self._items.setdefault(robot, {})[stamp_key(stamp_s)] = value

    def newest_key(self, robot: int) -> int | None:
        """Stamp key of the newest value of ``robot`` (None if nothing arrived)."""
        items = self._items.get(robot)
        return max(items) if items else None

    def as_of(self, stamp_s: float) -> dict[int, Any]:
        """Each robot's newest value stamped at or before ``stamp_s`` [s], in robot id order
        (so pooled sums add up the same way every run); older values, no longer needed by
        later evaluations, are dropped."""
        limit = stamp_key(stamp_s)
        chosen = {}
        for robot, items in sorted(self._items.items()):
            keys = [key for key in items if key <= limit]
            if keys:
                newest = max(keys)
                chosen[robot] = items[newest]
                for key in keys:
                    if key != newest:
                        del items[key]
        return chosen


class EvaluatorNode(LeanNode):
    """Team metrics, the run's stop rule and its summary (see module docstring)."""

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
        metrics_interval_s = settings.metrics_interval_s
        self.progress_interval_s = settings.progress_interval_s
        max_sim_time_s = settings.max_sim_time_s
        self.estimate_wait_s = settings.estimate_wait_s
        self.silence_timeout_s = settings.silence_timeout_s
        self.params = declare_exploration_params(self)
        self.wire = TeamWireFormat(self.params)
        refuse_unknown_overrides(self)
        self.num_robots = self.params.world.num_robots
        self.time_step_s = self.params.motion.time_step_s
        self.interval_steps = max(1, round(metrics_interval_s / self.time_step_s))
        self.monitor = RunMonitor(self.params, max_sim_time_s)
        self.evaluator: TeamEvaluator | None = None
        self.paths = StampedEstimates()
        self.landmark_estimates = StampedEstimates()
        self.blocked_s = StampedEstimates()
        self.given_up: list[list[GivenUpEntry]] = [[] for _ in range(self.num_robots)]
        self.targets: list[dict[int, TargetRecord]] = [{} for _ in range(self.num_robots)]
        self.rendezvous_events: list[RendezvousEvent] = []
        self.team_updates = TeamUpdateInbox(None, self.num_robots)
        #: Relay mode: the link relay's update counts by step (``/world/link_counts``).
        self.link_counts: dict[int, dict[str, int]] = {}
        self.exit_code: int | None = None
        self.done = Future()
        self.recorded_step = -1
        self._truth: dict[int, dict[int, np.ndarray]] = {}
        self._complete_steps: deque[int] = deque()
        self._pending: tuple[int, float] | None = None
        self._overdue: set[int] = set()
        self._last_command: list[MotionCommand | None] = [None] * self.num_robots
        #: Set once every robot that is not lost has finished (``_check_all_finished``).
        self._team_finished: TeamFinished | None = None
        self._stream_wait_deadline_s = math.inf
        self._evaluated: tuple[dict, dict] = ({}, {})
        self._next_progress_s = self.progress_interval_s
        self._first_step_wall_s: float | None = None
        self._last_data_wall_s = time.monotonic()
        self._world_watch = WorldWatch(self.silence_timeout_s)
        self._started_wall_s = time.monotonic()
        self.liveness = TeamLiveness(self.num_robots, settings.liveliness_grace_s)
        self._unseen = UnseenLiveliness(self.num_robots, LIVELINESS_LEASE_S)
        #: (step, reason) once the world said it stepped over.
        self._world_over: tuple[int, str] | None = None
        self._create_interfaces()
        self.get_logger().info(
            f"evaluating {self.num_robots} robots every {self.interval_steps} steps; stop at "
            f"explored ratio {self.params.run.until_explored:g} or step "
            f"{self.monitor.final_step}; "
            f"summary -> {self.summary_path}")

    def _create_interfaces(self) -> None:
        if not perfect_links(self.params.links):  # first: taken before a step's ground truth
            self.create_subscription(TeamLinkCounts, LINK_COUNTS_TOPIC, self._on_link_counts,
                                     GROUND_TRUTH_QOS)
        self.metrics_pub = self.create_publisher(ExplorationMetrics, "/evaluation/metrics",
                                                 STREAM_QOS)
        self.request_pub = self.create_publisher(TeamUpdateRequest, "/team/update_requests",
                                                 TEAM_QOS)
        self.create_subscription(LandmarkArray, "/world/landmarks", self._on_true_landmarks,
                                 LATCHED_QOS)
        status_bytes = serialized_size(WorldStatus(header=Header(frame_id=WORLD_FRAME),
                                                   reason="x" * _MAX_REASON_CHARS))
        self.create_subscription(WorldStatus, WORLD_STATUS_TOPIC, size_limited(
            self.inputs, WORLD_STATUS_TOPIC, WorldStatus, status_bytes, self._on_world_status),
            LATCHED_QOS, raw=True)
        # The largest valid estimates: a path with a pose per keyframe of the run, a
        # landmark set of the most landmarks an update may hold.
        path_bytes = len(serialized_path(0.0, np.zeros(self._keyframes()),
                                         np.zeros((self._keyframes(), 3))))
        landmarks_bytes = serialized_size(landmark_array_to_msg(0.0, MAP_FRAME, [
            LandmarkEstimate(0, np.zeros(2), np.eye(2))] * MAX_LANDMARKS_PER_UPDATE))
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
            self.create_subscription(TeamUpdate, f"/{ns}/team/updates",
                                     lambda m, r=robot: self._on_team_update(r, m), TEAM_QOS)
            self.create_subscription(MotionCommand, f"/{ns}/motion_command",
                                     lambda m, r=robot: self._on_command(r, m), SENSOR_QOS)
        watch_liveliness(self, list(range(self.num_robots)), self._on_liveliness)
        self.create_timer(_WATCH_PERIOD_S, self._watch,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- inputs ----------------------------------------------------------------------------

    def _latest_step(self) -> int:
        """The newest step this evaluator has ground truth of (-1 before the first)."""
        return max([self.recorded_step, *self._truth, *self._complete_steps])

    def _stamp_problem(self, stamp: Time, keyframes_only: bool = False) -> tuple[int, str | None]:
        """(step, reason to drop) of a message stamp: not the time of a step, (keyframe
        steps only: not a keyframe's step), or a step outside the run or implausibly far
        ahead of the newest ground truth."""
        stamp_s = time_to_seconds(stamp)
        step = round(stamp_s / self.time_step_s) if math.isfinite(stamp_s) else -1
        interval = self.params.slam.keyframe_interval_steps
        problem = (step_problem(step, None, self.monitor.final_step)
                   or stamp_step_problem(stamp.sec * 1_000_000_000 + stamp.nanosec, step,
                                         self.time_step_s)
                   or (f"step {step} is not a keyframe step"
                       if keyframes_only and step % interval else None)
                   or (f"step {step} is more than {EVALUATOR_STEP_LEAD} steps ahead of the "
                       f"ground truth" if step > self._latest_step() + EVALUATOR_STEP_LEAD
                       else None))
        return step, problem

    def _on_true_landmarks(self, message: LandmarkArray) -> None:
        if self.evaluator is not None:
            return
        expected = self.params.world.num_landmarks
        ids = [lm.landmark_id for lm in message.landmarks]
        if not self.inputs.check(
                "/world/landmarks", header_problem(message.header, WORLD_FRAME),
                content_problem(message),
                (f"{len(ids)} landmarks, the world has {expected}"
                 if len(ids) != expected else None),
                (f"landmark ids {sorted(set(ids))[:5]}... are not distinct"
                 if len(set(ids)) != len(ids) else None)):
            return
        truth = landmark_positions_from_msg(message)
        ids = np.array(sorted(truth), dtype=np.int64)
        positions = np.array([truth[i] for i in ids]).reshape(-1, 2)
        self.evaluator = TeamEvaluator(
            landmark_truth(self.params.world, ids, positions, message.radius), self.params)
        self._process()

    def _on_truth_data(self, robot: int, codec: OdometryCodec, data: bytes) -> None:
        """A robot's serialized ground truth: read in one struct when it is in the world's
        own form (``nodes.odometry_cdr``), otherwise as a message with every check."""
        truth = codec.decode(data)
        if truth is not None:
            self._take_truth(robot, Time(sec=truth.stamp[0], nanosec=truth.stamp[1]),
                             truth.pose)
            return
        message = deserialized(self.inputs, f"/world/ground_truth/{robot_namespace(robot)}",
                               Odometry, data)
        if message is None:
            return
        self._take_truth(robot, message.header.stamp, odometry_pose(message),
                         header_problem(message.header, WORLD_FRAME),
                         frame_problem(message.child_frame_id,
                                       f"{robot_namespace(robot)}/base_link", "child_frame_id"),
                         content_problem(message))

    def _take_truth(self, robot: int, stamp: Time, pose: np.ndarray,
                    *message_problems: str | None) -> None:
        """A robot's true pose at a step, unless ``message_problems`` (frames, numbers) or
        its stamp give a reason to drop it."""
        step, problem = self._stamp_problem(stamp)
        if not self.inputs.check(
                f"/world/ground_truth/{robot_namespace(robot)}", *message_problems,
                problem, step_problem(step, self.recorded_step + 1, self.monitor.final_step,
                                      EVALUATOR_STEP_LEAD),
                "duplicate" if step in self._complete_steps or robot in self._truth.get(
                    step, {}) else None):
            return
        self._last_data_wall_s = time.monotonic()
        poses = self._truth.setdefault(step, {})
        poses[robot] = pose
        if len(poses) == self.num_robots:
            self._complete_steps.append(step)
            if self._first_step_wall_s is None:
                self._first_step_wall_s = time.monotonic()
                self._unseen.first_step(self._first_step_wall_s)
            self._process()

    def _expect_liveliness(self) -> None:
        """A robot whose liveliness was not reported a lease after the first step counts as
        lost unless it shows within the grace, as if its liveliness had been lost then."""
        for robot in self._unseen.due(time.monotonic()):
            self.liveness.liveliness_lost(robot, *self._status_times())

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
        stamp = Time(sec=path.stamp[0], nanosec=path.stamp[1])
        _, problem = self._stamp_problem(stamp, keyframes_only=True)
        if not self.inputs.check(
                topic, problem, path_problem(path, MAP_FRAME),
                self._stale_problem(self.paths, robot, stamp),
                size_problem(len(path.poses), self._keyframes(), "poses")):
            return
        self._on_estimate(self.paths, robot, stamp, planar_path(path))

    def _keyframes(self) -> int:
        """Keyframes of the whole run (a robot's path has at most as many poses)."""
        return self.monitor.final_step // self.params.slam.keyframe_interval_steps + 1

    def _on_landmark_estimates(self, robot: int, message: LandmarkArray) -> None:
        _, problem = self._stamp_problem(message.header.stamp, keyframes_only=True)
        if not self.inputs.check(
                f"/{robot_namespace(robot)}/landmarks", problem,
                header_problem(message.header, MAP_FRAME),
                self._stale_problem(self.landmark_estimates, robot, message.header.stamp),
                size_problem(len(message.landmarks), MAX_LANDMARKS_PER_UPDATE, "landmarks"),
                first_problem(id_problem(lm.landmark_id, None, "landmark id")
                              for lm in message.landmarks),
                content_problem(message)):
            return
        self._on_estimate(self.landmark_estimates, robot, message.header.stamp,
                          landmark_positions_from_msg(message))

    @staticmethod
    def _stale_problem(history: StampedEstimates, robot: int, stamp: Time) -> str | None:
        """Reason if an estimate is older than the newest one of the robot (robots publish
        their estimates in time order)."""
        newest = history.newest_key(robot)
        if newest is not None and stamp_key(time_to_seconds(stamp)) < newest:
            return "older than the robot's last estimate"
        return None

    def _on_estimate(self, history: StampedEstimates, robot: int, stamp: Time,
                     value: Any) -> None:
        history.add(robot, time_to_seconds(stamp), value)
        if robot in self._overdue and not self._behind(robot, max(self.recorded_step, 0)):
            self._overdue.discard(robot)
        self._process()

    def _on_link_counts(self, message: TeamLinkCounts) -> None:
        """The relay's update counts of one step (the first copy of a step counts). Kept for
        the steps of the last ``_LINK_COUNTS_KEPT`` evaluations, so the memory is bounded."""
        step = int(message.step)
        counts = {"sent": int(message.sent), "on_time": int(message.on_time),
                  "late": int(message.late), "never": int(message.never)}
        oldest = self.recorded_step - _LINK_COUNTS_KEPT * self.interval_steps
        problem = (step_problem(step, max(oldest, 0), self.monitor.final_step,
                                EVALUATOR_STEP_LEAD)
                   or (f"counts {counts} do not add up"
                       if counts["on_time"] + counts["late"] + counts["never"] != counts["sent"]
                       else None))
        if not self.inputs.check(LINK_COUNTS_TOPIC, problem):
            return
        self.link_counts.setdefault(step, counts)
        for old in [s for s in self.link_counts if s < oldest]:
            del self.link_counts[old]

    def _on_world_status(self, message: WorldStatus) -> None:
        """The world stepped over (no further step will come): remembered, so that the run
        ends as soon as the ground truth up to that step is in (``_end_with_the_world``)."""
        step, problem = self._stamp_problem(message.header.stamp)
        if not self.inputs.check(
                WORLD_STATUS_TOPIC, header_problem(message.header, WORLD_FRAME), problem,
                f"stamp of step {step} in a status of step {message.step}"
                if step != message.step else None):
            return
        if not message.stepping_over or self._world_over == (step, message.reason):
            return
        self._world_over = (step, message.reason)  # the latest, should a forged one precede
        self.get_logger().info(f"the world stepped over at step {step} ({message.reason})")

    def _end_with_the_world(self) -> None:
        """End the run (exit code 3, as for silence) when the world stepped over at a step
        whose ground truth is recorded and evaluated as far as due, and no stop rule fired:
        ``liveliness_grace_s`` after the last ground truth when every robot is lost here
        (the evaluator would wait for silence), ``estimate_wait_s`` after it otherwise (the
        robots' last answers and estimates had that long to come). Only while the world is
        the sole publisher of its status: a forged "stepping over" must not end a live run."""
        if self._world_over is None or self.monitor.stopped or self.exit_code is not None:
            return
        step, reason = self._world_over
        if (self._latest_step() != step or self.recorded_step != step
                or self._pending is not None or self._complete_steps):
            return
        publishers = {info.node_name for info in
                      self.get_publishers_info_by_topic(WORLD_STATUS_TOPIC)}
        if publishers != {WORLD_NODE_NAME}:
            self.get_logger().warn(
                f"the world's status says it stepped over, but {WORLD_STATUS_TOPIC} has the "
                f"publishers {sorted(publishers)}: not trusted; ending by silence instead",
                throttle_duration_sec=LOG_PERIOD_S)
            return
        every_robot_lost = all(self.liveness.status(r) == LOST for r in range(self.num_robots))
        wait_s = self.liveness.grace_s if every_robot_lost else self.estimate_wait_s
        if time.monotonic() - self._last_data_wall_s < wait_s:
            return
        self.finish(f"the world stepped over at step {step} ({reason})", EXIT_SILENCE)

    def _on_team_update(self, robot: int, message: TeamUpdate) -> None:
        """Targets from the robots' update streams, validated and in sequence order exactly
        as a robot reads them (malformed or impostor records are rejected)."""
        try:
            self.team_updates.receive(checked_team_update(message, self.wire), robot)
        except InvalidTeamUpdate as error:
            self.inputs.drop(f"/{robot_namespace(robot)}/team/updates",
                             f"rejected a team update: {error}")
            return
        for update in self.team_updates.pop_ready():
            for record in update.targets:
                self.targets[update.robot_id][record.decision_index] = record
            self.rendezvous_events.extend(update.rendezvous)
        if self.monitor.stopped:
            self._process()

    def _status_times(self) -> tuple[float, float]:
        """(simulation time of the latest recorded step, wall seconds since the start) [s]."""
        return (self._stamp_s(max(self.recorded_step, 0)),
                time.monotonic() - self._started_wall_s)

    def _on_liveliness(self, robot: int, alive: bool, restarted: bool) -> None:
        if alive:
            self._unseen.seen(robot)
            self.get_logger().info(f"robot {robot}: liveliness asserted"
                                   + (" by a new process (restarted)" if restarted else ""))
            if self.liveness.liveliness_back(robot, restarted, *self._status_times()):
                self.get_logger().warn(f"robot {robot} lost: its process was restarted")
            return
        self.liveness.liveliness_lost(robot, *self._status_times())
        self.get_logger().warn(f"robot {robot}: liveliness lost (process dead, stopped or "
                               f"wedged, or its assertions lost on the network)")

    def _on_command(self, robot: int, message: MotionCommand) -> None:
        last = self._last_command[robot]
        step, problem = self._stamp_problem(message.header.stamp)
        stamp_s = self._stamp_s(int(message.step))
        try:
            given_up, given_up_problem = [given_up_from_msg(g, stamp_s)
                                          for g in message.given_up], None
        except ValueError as error:
            given_up, given_up_problem = [], str(error)
        if not self.inputs.check(
                f"/{robot_namespace(robot)}/motion_command",
                (f"robot_id {message.robot_id} on robot {robot}'s topic"
                 if message.robot_id != robot else None),
                header_problem(message.header, f"{robot_namespace(robot)}/base_link"), problem,
                f"stamp of step {step} in a command for step {message.step}"
                if step != message.step else None,
                content_problem(message), given_up_problem,
                f"blocked_s {message.blocked_s} < 0" if message.blocked_s < 0.0 else None,
                command_sequence_problem(message.team_sequence, 0 if last is None else int(
                    last.team_sequence), MAX_SEQUENCE_LEAD)):
            return
        if last is not None and message.step <= last.step:
            return  # an older answer arriving late
        self._last_command[robot] = message
        self.blocked_s.add(robot, stamp_s, float(message.blocked_s))
        self.given_up[robot].extend(given_up)
        if self.liveness.heard(robot, *self._status_times(), "answers the world again"):
            self.get_logger().info(f"robot {robot} rejoined: it answers the world again "
                                   f"(step {message.step})")
        if message.finished:
            self.liveness.finished(robot, self._stamp_s(int(message.step)),
                                   time.monotonic() - self._started_wall_s)
        self._check_all_finished()

    def _check_all_finished(self) -> None:
        """Every robot that is not lost has reported ``finished`` (at least one is not
        lost): the run ends at the latest step they answered, as soon as its ground truth is
        in; the robots lost then without having finished are kept for the stop reason."""
        if self._team_finished is not None:
            return
        self._team_finished = every_live_robot_finished(
            [int(c.step) if c is not None and c.finished else None for c in self._last_command],
            [self.liveness.status(r) == LOST for r in range(self.num_robots)])
        if self._team_finished is not None:
            self._process()

    def _watch(self) -> None:
        if self.exit_code is not None:
            return
        self._watch_world()
        self._expect_liveliness()
        self._end_with_the_world()
        if self.exit_code is not None:
            return
        for robot in self.liveness.confirm(time.monotonic() - self._started_wall_s):
            never = "" if self._unseen.was_seen(robot) else " (never seen alive)"
            self.get_logger().warn(f"robot {robot} lost: no liveliness for "
                                   f"{self.liveness.grace_s:g} s{never}")
            self._check_all_finished()
        self._request_missing_updates()
        self._process()
        silent_s = time.monotonic() - self._last_data_wall_s
        if self.exit_code is None and silent_s > self.silence_timeout_s:
            self.finish(f"no ground truth for {silent_s:.0f} s (world or robots stopped)",
                        EXIT_SILENCE)

    def _watch_world(self) -> None:
        """Log at once when the world (the ground-truth publisher) leaves the ROS graph or
        comes back; the run then ends by the silence rule (exit code 3)."""
        topic = f"/world/ground_truth/{robot_namespace(0)}"
        event = self._world_watch.update(self.count_publishers(topic) > 0, time.monotonic())
        if event == WorldEvent.LOST:
            self.get_logger().warn(
                f"the world left the ROS graph (no publisher of {topic}); the run ends with "
                f"the summary so far if it is not back within {self.silence_timeout_s:g} s")
        elif event == WorldEvent.BACK:
            self.get_logger().info("the world is back on the ROS graph")

    def _missing_updates(self) -> list[MissingRange]:
        """Gaps in the robots' update streams up to the latest sequence each robot reported
        in its motion commands."""
        latest = {robot: int(command.team_sequence)
                  for robot, command in enumerate(self._last_command) if command is not None}
        return self.team_updates.missing(latest)

    def _request_missing_updates(self) -> None:
        """Ask robots again for team updates this evaluator missed (as robots do)."""
        for gap in self._missing_updates():
            request = TeamUpdateRequest(requester_id=TeamUpdateRequest.OBSERVER,
                                        robot_id=gap.robot_id,
                                        first_sequence=gap.first_sequence,
                                        last_sequence=gap.last_sequence)
            request.header.stamp = self.get_clock().now().to_msg()
            publish_or_log(self.request_pub, request, self, "a request for updates")

    # -- evaluation ------------------------------------------------------------------------

    def _process(self) -> None:
        """Record complete steps of ground truth in order and run the evaluations due.

        An evaluation at step k reads each robot's estimates as of step k - 1 (the robots
        publish them while answering their keyframe steps, before the world steps on), and
        waits up to ``estimate_wait_s`` for those of the last keyframe before k to arrive,
        so that the result does not depend on message timing.
        """
        while self.evaluator is not None and self.exit_code is None:
            if self.monitor.stopped:
                self._finish_when_streams_complete()
                return
            if self._pending is None:
                if not self._complete_steps:
                    if self._finished_after_evaluation():
                        continue
                    if not self._finished_unevaluated():
                        return
                    self._pending = (self.recorded_step, time.monotonic())
                    continue
                step = self._complete_steps.popleft()
                self._record_step(step)
                if step >= self.monitor.final_step or self._finished_by(step) or (
                        step > 0 and step % self.interval_steps == 0):
                    self._pending = (step, time.monotonic())
                continue
            step, queued_wall_s = self._pending
            missing = self._robots_without_estimates(step)
            if missing and time.monotonic() - queued_wall_s < self.estimate_wait_s:
                return
            if missing:
                self._overdue.update(missing)
                self.get_logger().warn(
                    f"evaluating step {step} with older estimates of robots {missing}: theirs "
                    f"did not arrive within {self.estimate_wait_s:g} s (not waited for again "
                    f"until they publish)")
            self._pending = None
            metrics = self.evaluate(step)
            if self.monitor.observe(step, metrics, self._finished_by(step),
                                    self._lost_unfinished()):
                self._stopping()

    def _stopping(self) -> None:
        """A stop rule fired: give the robots' update streams ``estimate_wait_s`` to
        complete, and ask for what is missing."""
        self._stream_wait_deadline_s = time.monotonic() + self.estimate_wait_s
        self._request_missing_updates()

    def _finish_when_streams_complete(self) -> None:
        """After the stop rule fired: finish once every robot's update stream is complete up
        to what it reported (so the summary holds every decision made before the stop
        step), or after ``estimate_wait_s`` wall seconds, saying what is missing."""
        missing = self._missing_updates()
        silent = self._missing_commands()
        if (missing or silent) and time.monotonic() < self._stream_wait_deadline_s:
            return
        if missing:
            self.get_logger().warn(
                "summary written without team updates that never arrived: " + ", ".join(
                    f"robot {g.robot_id} #{g.first_sequence}-{g.last_sequence}"
                    for g in missing))
        if silent:
            self.get_logger().warn(
                "summary written without the motion commands of the step before the stop "
                "step (their blocked time and targets given up) of robots "
                + ", ".join(str(robot) for robot in silent))
        self.finish(self.monitor.stop_reason, self.monitor.exit_code)

    def _missing_commands(self) -> list[int]:
        """Robots waited for (``_waited_for``) whose motion command answering the step
        before the stop step has not arrived."""
        final = self.monitor.final_metrics
        if final is None:
            return []
        step = round(final.stamp_s / self.time_step_s)
        return [robot for robot, last in enumerate(self._last_command)
                if self._waited_for(robot) and (last is None or int(last.step) < step - 1)]

    def _finished_by(self, step: int) -> bool:
        return self._team_finished is not None and step >= self._team_finished.step

    def _lost_unfinished(self) -> tuple[int, ...]:
        """The robots lost without having finished when all the others had finished."""
        return () if self._team_finished is None else self._team_finished.lost

    def _finished_after_evaluation(self) -> bool:
        """Every robot finished at the last recorded step, which was evaluated before their
        answers said so: the stop rule runs again on that evaluation (True if it fired).
        Without this, a run whose robots all finished at an evaluation step waited for
        ground truth that never came (exit 3 after ``silence_timeout_s``)."""
        if not (self._finished_by(self.recorded_step) and self._recorded_step_evaluated()):
            return False
        if not self.monitor.observe_finished(self.recorded_step, self._lost_unfinished()):
            return False
        self._stopping()
        return True

    def _finished_unevaluated(self) -> bool:
        """Every robot finished at a step already recorded (its ground truth came before
        the robots' answers) that was not evaluated yet."""
        return self._finished_by(self.recorded_step) and not self._recorded_step_evaluated()

    def _recorded_step_evaluated(self) -> bool:
        """Whether the last evaluation is that of the last recorded step."""
        history = self.monitor.history
        return bool(history) and history[-1].stamp_s == self._stamp_s(self.recorded_step)

    def _record_step(self, step: int) -> None:
        stamp_s = self._stamp_s(step)
        for robot, pose in sorted(self._truth.pop(step).items()):
            self.evaluator.record_truth(robot, stamp_s, pose)
        self.recorded_step = step

    def _robots_without_estimates(self, step: int) -> list[int]:
        """Robots waited for (``_waited_for``) whose estimates of the last keyframe before
        ``step`` have not arrived."""
        return [robot for robot in range(self.num_robots)
                if self._waited_for(robot) and self._behind(robot, step)]

    def _behind(self, robot: int, step: int) -> bool:
        """Whether the robot's estimates of the last keyframe before ``step`` are missing."""
        interval = self.params.slam.keyframe_interval_steps
        needed = stamp_key(self._stamp_s(max(step - 1, 0) // interval * interval))
        return any(history.newest_key(robot) is None or history.newest_key(robot) < needed
                   for history in (self.paths, self.landmark_estimates))

    def _waited_for(self, robot: int) -> bool:
        """Whether an evaluation waits for the robot's estimates: unless it is lost (its
        liveliness lapsed) or overdue (an evaluation already went on without its estimates
        after ``estimate_wait_s``, until it has caught up with the latest recorded step: a
        robot that keeps lagging, as under ``--realtime 1000``, once made every evaluation
        wait ``estimate_wait_s`` again, 30 s each). A live robot publishes the
        estimates of a keyframe step right after its answer to that step, which the world
        needs before it publishes the next step's ground truth, so the wait ends; when the
        messages of the different topics reach this node (a flooded or loaded node takes
        them in bursts) does not decide which estimates an evaluation reads."""
        return self.liveness.status(robot) != LOST and robot not in self._overdue

    def _stamp_s(self, step: int) -> float:
        return sim_time_s(step, self.time_step_s)

    def evaluate(self, step: int, publish: bool = True) -> TeamMetrics:
        """Team metrics at ``step`` (its ground truth recorded), published; the caller hands
        them to the run monitor."""
        stamp_s = self._stamp_s(step)
        as_of_s = self._stamp_s(max(step - 1, 0))
        self._evaluated = (self.paths.as_of(as_of_s), self.landmark_estimates.as_of(as_of_s))
        self.blocked_s.as_of(as_of_s)  # drops the values no later summary needs
        metrics = self.evaluator.evaluate(stamp_s, *self._evaluated)
        decisions = sum(len(self.monitor.decisions_counted(chosen, until=metrics))
                        for chosen in self._decisions())
        if publish:
            message = ExplorationMetrics(
                explored_ratio=metrics.explored_ratio, distance_m=metrics.distance_m,
                loc_rmse_m=metrics.loc_rmse_m, landmark_rmse_m=metrics.landmark_rmse_m,
                decisions=decisions,
                robot_distance_m=[float(d) for d in self.evaluator.robot_distances_m])
            message.header.stamp = seconds_to_time(stamp_s)
            message.header.frame_id = WORLD_FRAME
            self.metrics_pub.publish(message)
        if stamp_s >= self._next_progress_s:
            self._next_progress_s += self.progress_interval_s * math.floor(
                (stamp_s - self._next_progress_s) / self.progress_interval_s + 1.0)
            self.get_logger().info(_progress_line(metrics, decisions))
        return metrics

    # -- the end ---------------------------------------------------------------------------

    def finish(self, reason: str, exit_code: int, publish: bool = True) -> None:
        """Summary JSON and map PNG; then ``done`` completes.

        After a stop rule fired the summary holds the values of that step. Otherwise (Ctrl-C,
        silence) the steps recorded so far are evaluated once more, so the summary holds the
        latest complete step."""
        if self.exit_code is not None:
            return
        self.exit_code = exit_code
        self.monitor.end(reason)
        if self.evaluator is not None and not self.monitor.stopped:
            while self._complete_steps:
                self._record_step(self._complete_steps.popleft())
            last = self.monitor.final_metrics
            if self.recorded_step >= 0 and (
                    last is None or last.stamp_s != self._stamp_s(self.recorded_step)):
                self.monitor.record(self.evaluate(self.recorded_step, publish))
        summary = self.summary()
        summary.write(self.summary_path)
        log = self.get_logger()
        log.info(f"done ({summary.stop_reason}): explored {summary.explored_ratio:.3f}, "
                 f"distance {summary.distance_m:.1f} m, loc RMSE {summary.loc_rmse_m:.3f} m, "
                 f"landmark RMSE {summary.landmark_rmse_m:.3f} m, {summary.decisions} "
                 f"decisions, sim {summary.sim_time_s:.1f} s, wall {summary.wall_s:.1f} s")
        log.info(f"summary: {self.summary_path}")
        if self.evaluator is not None:
            render_team_map(self.map_layers(summary.stop_reason), self.map_png_path)
            log.info(f"map: {self.map_png_path}")
        if not self.done.done():
            self.done.set_result(exit_code)

    def _decisions(self) -> list[list[DecisionEntry]]:
        """Each robot's decisions received so far, in order."""
        return [[DecisionEntry(t.stamp_s, (float(t.position[0]), float(t.position[1])), t.kind,
                               t.planning_time_s, t.planner_failed)
                 for _, t in sorted(records.items())]
                for records in self.targets]

    def summary(self) -> RunSummary:
        """The run's summary (the run monitor's, em-sim's schema) with each robot's status,
        status changes and downtime."""
        wall_s = (0.0 if self._first_step_wall_s is None
                  else time.monotonic() - self._first_step_wall_s)
        summary = self.monitor.summary(self._decisions(), wall_s, progress=self._progress(),
                                       rendezvous_events=self.rendezvous_events)
        final = self.monitor.final_metrics
        if final is not None and self.link_counts:
            step = round(final.stamp_s / self.time_step_s)
            summary.team_updates = self.link_counts.get(step)
            if summary.team_updates is None:
                self.get_logger().warn(f"no link counts of step {step} arrived: the summary "
                                       f"has no team_updates")
        until_s = self._status_times()
        for entry in summary.robots:
            entry.status = self.liveness.status(entry.id)
            entry.status_changes = self.liveness.changes(entry.id)
            entry.downtime_s, entry.downtime_wall_s = self.liveness.downtime_s(entry.id, *until_s)
        return summary

    def _progress(self) -> list[RobotProgressRecord] | None:
        """Each robot's progress bookkeeping as of the step before the final evaluation
        (its blocked time NaN if no command of it arrived by then); None before any."""
        final = self.monitor.final_metrics
        if final is None:
            return None
        blocked = self.blocked_s.as_of(final.stamp_s - self.time_step_s)
        for robot, last in enumerate(self._last_command):
            if last is not None and last.given_up_count > len(self.given_up[robot]):
                self.get_logger().warn(
                    f"robot {robot} reported {last.given_up_count} targets given up, "
                    f"{len(self.given_up[robot])} arrived")
        return [RobotProgressRecord(tuple(self.given_up[robot]), blocked.get(robot, math.nan))
                for robot in range(self.num_robots)]

    def map_layers(self, title: str) -> TeamMapLayers:
        """The final map's layers: the truth and the estimates of the last evaluation."""
        paths, landmarks = self._evaluated
        final = self.monitor.final_metrics
        end_s = math.inf if final is None else final.stamp_s
        return evaluation_layers(
            self.evaluator, {r: poses for r, (_, poses) in paths.items()},
            {r: np.array(list(e.values())).reshape(-1, 2) for r, e in landmarks.items()},
            {r: [d.target_entry() for d in self.monitor.decisions_counted(chosen)]
             for r, chosen in enumerate(self._decisions())},
            rendezvous_outcomes(self.rendezvous_events, end_s),
            f"{self.params.planner.name}, {self.num_robots} robots, seed "
            f"{self.params.run.seed}: {title}")


def _progress_line(metrics: TeamMetrics, decisions: int) -> str:
    def metres(value: float) -> str:
        return "n/a" if math.isnan(value) else f"{value:.3f} m"
    return (f"t={metrics.stamp_s:7.1f} s  explored {metrics.explored_ratio:5.3f}  distance "
            f"{metrics.distance_m:7.1f} m  loc RMSE {metres(metrics.loc_rmse_m)}  landmark RMSE "
            f"{metres(metrics.landmark_rmse_m)}  decisions {decisions}")


def main(args: list[str] | None = None) -> int:
    """Entry point of em-evaluator; returns the exit code (see module docstring)."""
    return run_node(EvaluatorNode, "em_evaluator", args, wrap_up=_keep_what_was_measured)


def _keep_what_was_measured(node: EvaluatorNode) -> int:
    """After Ctrl-C (rclpy's handler ends the spin) or SIGTERM the summary so far is still
    written; returns the node's exit code."""
    node.finish("interrupted", EXIT_INTERRUPTED, publish=False)
    return node.exit_code


if __name__ == "__main__":
    sys.exit(main())
