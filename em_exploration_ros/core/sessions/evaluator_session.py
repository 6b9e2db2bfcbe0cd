"""The outside observer of a run, one input at a time: em-evaluator's protocol, em-sim's summary.

``EvaluatorSession`` owns the ``TeamEvaluator`` (metrics from ground truth), the
``RunMonitor`` (stop rules), each robot's stamped estimates and the progress it reports, and
decides everything the observer does; it never reads a clock (wall times [s], monotonic,
are arguments), never logs and never publishes: each input returns the effects to perform
(``PublishMetrics``, ``RequestUpdates``, ``Finished``; ``Dropped`` and ``LogLine`` of
``effects.py``). Two drivers feed it: the ROS node ``nodes/evaluator_node.py`` (every
message, converted to core values) and em-sim's ``TeamRunner`` (the same inputs from the
agents, in the lockstep order), so both write THE summary (``RunSummary``) and the map
layers the same way.

The observer sees the ground truth (``/world/ground_truth/robot_i``, ``/world/landmarks``)
and what each robot publishes (``/robot_i/estimated_path``, ``/robot_i/landmarks``,
``/robot_i/estimated_pose`` for its latest keyframe's marginal covariance,
``/robot_i/team/updates`` for the chosen targets and rendezvous, ``/robot_i/motion_command``
for the finished flags and the robots' own progress bookkeeping). It never publishes
anything a robot uses for its estimates or decisions; it only asks robots to re-send team
updates it missed, as robots do.

The keyframe covariances (``keyframe_covariance``, kept as ``KeyframeCovariances`` says: each
keyframe's as the robot published it when that keyframe was its newest) give each robot's
position uncertainty at every evaluation (the history's ``robot_pose_sigma_m``: its newest
covariance as of the step before) and the team virtual map's uncertainty in the final map
(from each robot's evaluated path and the covariances of its keyframes). Once a robot
published one, an evaluation waits for the covariance of the last keyframe of its path too.

A simulation step is complete when the true poses of every robot at that step arrived; steps
are recorded in order. Every ``metrics_interval_s`` of simulation time (default 2 s = em-sim's
10 steps) the team metrics are evaluated from each robot's estimates as of the step before
(waiting up to ``estimate_wait_s`` for those of the last keyframe), so a seeded lockstep run
gives the same metrics every time, whatever the message timing. They are published
(``PublishMetrics``: ``/evaluation/metrics``) and kept; a progress line is logged every
``progress_interval_s``. Each evaluation goes to the run monitor
(``core.evaluation.run_monitor.RunMonitor``). Once a stop rule fired, the observer waits (up
to ``estimate_wait_s``) until every robot's update stream is complete up to the sequence the
robot reported, so that the summary lists every decision made before the stop step, and until
every robot's motion command of the step before is in; the summary holds the values of that
step. The run ends (``Finished``: the driver writes the summary JSON and the final map) when:

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
  stopped), or sooner when the world said in its status that it stepped over and no stop
  rule fired here (``liveliness_grace_s`` later if every robot is lost, else
  ``estimate_wait_s``): exit code 3 (``EXIT_SILENCE``);
  Ctrl-C: the summary so far, exit code 130 (``EXIT_INTERRUPTED``);
- the team neither travelled nor explored new area for ``run.stall_timeout_s`` of
  simulation time: stop reason "stalled: ...", exit code 4 (``EXIT_STALLED``).

While the run goes on, em-evaluator keeps the summary so far on disk (``KeepSoFar``, at
evaluations, at most every ``SO_FAR_INTERVAL_S`` wall seconds), its stop reason starting with
``EVALUATOR_LOST_PREFIX``: an evaluator killed before the run ended (SIGKILL, a crash) leaves
the run up to its last evaluations, not nothing (run_team.sh exits 7 then).

Each robot's motion command carries its own progress bookkeeping (``CommandReport``): the
time its odometry showed it blocked so far, the targets it gave up and the meetings it
requested that added an inter-robot factor (``MeetingEntry``) at that step, and how many of
its SLAM updates were re-solved in batch so far. The summary's ``given_up`` and ``meetings``
list those stamped before the stop step; ``blocked_s`` and ``slam_recoveries`` are the values
of the command answering the step before it, as em-sim's agents hold them at that step (null
for a robot whose command of that step never arrived; for a restarted robot, its new
process's).

When the sonar is not the paper's ideal one, the observer also keeps the world's truth of
every robot's keyframe scans (``sonar_truth``), the landmark readings of the robots' streams
and the landmarks each robot tied to its own (``correspondences``) in an
``AssociationRecord``; the summary's ``association`` counts them as of each robot's answer
to the step before the final evaluation, and the run waits (up to ``estimate_wait_s``) for
the truth of the scans up to that step.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from em_exploration_ros.core.agent.clock_watch import ClockWatch
from em_exploration_ros.core.agent.input_checks import (EVALUATOR_STEP_LEAD,
                                                        command_sequence_problem, id_problem,
                                                        first_problem, run_problem,
                                                        size_problem, stamp_step_problem,
                                                        step_problem)
from em_exploration_ros.core.agent.liveness import LOST, TeamLiveness, UnseenLiveliness
from em_exploration_ros.core.agent.world_watch import WorldEvent, WorldWatch
from em_exploration_ros.core.evaluation.association_record import AssociationRecord
from em_exploration_ros.core.evaluation.association_stats import association_line
from em_exploration_ros.core.evaluation.evaluator import (TeamEvaluator, TeamMetrics,
                                                          landmark_truth, stamp_key)
from em_exploration_ros.core.evaluation.keyframe_covariances import KeyframeCovariances
from em_exploration_ros.core.evaluation.stamped_estimates import StampedEstimates
from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers, evaluation_layers
from em_exploration_ros.core.evaluation.rendezvous_stats import rendezvous_outcomes
from em_exploration_ros.core.evaluation.run_monitor import (DecisionEntry,
                                                            RobotProgressRecord, RunMonitor,
                                                            TeamFinished,
                                                            every_live_robot_finished)
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, MeetingEntry, RunSummary
from em_exploration_ros.core.node_settings import EvaluatorNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import (MAX_LANDMARKS_PER_UPDATE,
                                                     MAX_SEQUENCE_LEAD, InvalidTeamUpdate,
                                                     MissingRange, RendezvousEvent,
                                                     TargetRecord, TeamUpdate,
                                                     TeamUpdateInbox)
from em_exploration_ros.core.records.readings import LandmarkReading
from em_exploration_ros.core.records.wire_model import nanoseconds_to_seconds, sim_time_s
from em_exploration_ros.core.sessions.effects import Dropped, info, warn
from em_exploration_ros.core.sessions.evaluator_effects import (CommandReport, Effect, Finished,
                                                                KeepSoFar, PublishMetrics,
                                                                RequestUpdates)
from em_exploration_ros.core.slam.team_slam import landmark_owner
from em_exploration_ros.core.world.sensors import CLUTTER
from em_exploration_ros.core.world.world import World

#: Exit status of a run that ended by silence or when the world stepped over.
EXIT_SILENCE = 3
#: Exit status of an interrupted run (Ctrl-C, SIGTERM).
EXIT_INTERRUPTED = 130
#: Relay mode: the link counts of this many evaluation steps before the newest are kept.
_LINK_COUNTS_KEPT = 100
#: Throttle key of the warning about an untrusted world status.
_UNTRUSTED_STATUS_KEY = "untrusted world status"
#: Stop reason's start of the summary so far (``KeepSoFar``): what is left on disk when the
#: evaluator dies before the run ended.
EVALUATOR_LOST_PREFIX = "evaluator lost: "
#: Wall seconds [s] at least between two summaries so far (written at evaluations: each one
#: holds the whole history, so a long run must not write one per evaluation).
SO_FAR_INTERVAL_S = 2.0


class EvaluatorSession:
    """Team metrics, the run's stop rules, its summary and map (see module docstring)."""

    def __init__(self, params: ExplorationParams, settings: EvaluatorNodeSettings,
                 started_wall_s: float, liveliness_lease_s: float,
                 world_node_name: str = "", keep_so_far: bool = False) -> None:
        """Args: the run's parameters; the observer's settings; the wall time [s] it
        started at; the lease [s] of the robots' liveliness; the name of the node that alone
        may publish the world's status; whether to keep the summary so far on disk
        (``KeepSoFar`` at evaluations, at most every ``SO_FAR_INTERVAL_S`` wall seconds)."""
        self.params = params
        self.settings = settings
        self.num_robots = params.world.num_robots
        self.time_step_s = params.motion.time_step_s
        self.interval_steps = max(1, round(settings.metrics_interval_s / self.time_step_s))
        self.monitor = RunMonitor(params, settings.max_sim_time_s)
        self.evaluator: TeamEvaluator | None = None
        self.exit_code: int | None = None
        self.recorded_step = -1
        self.liveness = TeamLiveness(self.num_robots, settings.liveliness_grace_s)
        self._world_node_name = world_node_name
        self._paths = StampedEstimates()
        self._landmarks = StampedEstimates()
        self._blocked_s = StampedEstimates()
        self._slam_recoveries = StampedEstimates()
        self._keyframe_covariances = KeyframeCovariances()
        self._given_up: list[list[GivenUpEntry]] = [[] for _ in range(self.num_robots)]
        self._meetings: list[MeetingEntry] = []
        self._targets: list[dict[int, TargetRecord]] = [{} for _ in range(self.num_robots)]
        self._rendezvous: list[RendezvousEvent] = []
        self._team_updates = TeamUpdateInbox(None, self.num_robots)
        #: The evidence of the robots' data association (None with the ideal sonar).
        self.association = None if params.sensors.ideal_sonar else AssociationRecord(
            self.num_robots, params.slam.keyframe_interval_steps, params.sensors.landmark_ids)
        #: Relay mode: the link relay's update counts by step.
        self._link_counts: dict[int, dict[str, int]] = {}
        self._truth: dict[int, dict[int, np.ndarray]] = {}
        self._complete_steps: deque[int] = deque()
        self._pending: tuple[int, float] | None = None
        self._overdue: set[int] = set()
        self._last_command: list[CommandReport | None] = [None] * self.num_robots
        #: Set once every robot that is not lost has finished (``_check_all_finished``).
        self._team_finished: TeamFinished | None = None
        self._stream_wait_deadline_s = math.inf
        self._evaluated: tuple[dict, dict] = ({}, {})
        self._next_progress_s = settings.progress_interval_s
        self._first_step_wall_s: float | None = None
        self._started_wall_s = started_wall_s
        self._last_data_wall_s = started_wall_s
        self._world_watch = WorldWatch(settings.silence_timeout_s)
        self._clock = ClockWatch(started_s=started_wall_s)  # the ground truth's steps
        self._unseen = UnseenLiveliness(self.num_robots, liveliness_lease_s)
        #: (step, reason) once the world said it stepped over.
        self._world_over: tuple[int, str] | None = None
        #: Wall time [s] of the next summary so far (never without ``keep_so_far``).
        self._next_so_far_wall_s = -math.inf if keep_so_far else math.inf

    @property
    def max_keyframes(self) -> int:
        """Keyframes of the whole run (a robot's path has at most as many poses)."""
        return self.monitor.final_step // self.params.slam.keyframe_interval_steps + 1

    def evaluates_at(self, step: int) -> bool:
        """Whether ``step`` is an evaluation step (every ``metrics_interval_s``, and the final
        step); the step at which every robot finished is evaluated too."""
        return step >= self.monitor.final_step or (step > 0 and step % self.interval_steps == 0)

    def describe(self) -> str:
        """What this observer does, for the log."""
        return (f"evaluating {self.num_robots} robots every {self.interval_steps} steps; "
                f"stop at explored ratio {self.params.run.until_explored:g} or step "
                f"{self.monitor.final_step}")

    # -- inputs: the truth -------------------------------------------------------------------

    def run_problem(self, run_id: int) -> str | None:
        """Reason to drop a message of another run (its ``run_id`` not the evaluator's)."""
        return run_problem(run_id, self.settings.run_id)

    def next_expected(self, robot: int) -> int:
        """The next sequence number of robot ``robot``'s update stream this observer takes
        (a record below it is one it holds: ``screened_team_updates`` ignores it unread)."""
        return self._team_updates.next_expected(robot)

    def step_of(self, stamp_ns: int, keyframes_only: bool = False) -> tuple[int, str | None]:
        """(step, reason to drop) of a message stamp [ns sim time]: not the time of a step,
        (``keyframes_only``: not a keyframe's step), or a step outside the run or implausibly
        far ahead of the newest ground truth."""
        stamp_s = nanoseconds_to_seconds(stamp_ns)
        step = round(stamp_s / self.time_step_s) if math.isfinite(stamp_s) else -1
        interval = self.params.slam.keyframe_interval_steps
        problem = (step_problem(step, None, self.monitor.final_step)
                   or stamp_step_problem(stamp_ns, step, self.time_step_s)
                   or (f"step {step} is not a keyframe step"
                       if keyframes_only and step % interval else None)
                   or (f"step {step} is more than {EVALUATOR_STEP_LEAD} steps ahead of the "
                       f"ground truth" if step > self._latest_step() + EVALUATOR_STEP_LEAD
                       else None))
        return step, problem

    def true_landmarks(self, ids: Sequence[int], positions: np.ndarray, radius_m: float,
                       wall_s: float) -> list[Effect]:
        """The world's landmarks (ids, positions (M, 2) [m, world frame], radius [m]); the
        first valid set starts the evaluation, later ones are ignored."""
        if self.evaluator is not None:
            return []
        expected = self.params.world.num_landmarks
        problem = ((f"{len(ids)} landmarks, the world has {expected}"
                    if len(ids) != expected else None)
                   or (f"landmark ids {sorted(set(ids))[:5]}... are not distinct"
                       if len(set(ids)) != len(ids) else None))
        if problem:
            return [Dropped(problem)]
        order = np.argsort(np.asarray(ids, dtype=np.int64), kind="stable")
        ordered_ids = np.asarray(ids, dtype=np.int64)[order]
        ordered = np.asarray(positions, dtype=float).reshape(-1, 2)[order]
        return self.true_world(landmark_truth(self.params.world, ordered_ids, ordered,
                                              radius_m), wall_s)

    def true_world(self, world: World, wall_s: float) -> list[Effect]:
        """The world itself (em-sim): the evaluation starts."""
        self.evaluator = TeamEvaluator(world, self.params)
        return self._process(wall_s)

    def true_pose(self, robot: int, step: int, pose: np.ndarray, wall_s: float
                  ) -> list[Effect]:
        """Robot ``robot``'s true pose (x, y, theta) [m, rad, world frame] at ``step``
        (``step_of`` its stamp first); the step is recorded once every robot's is in."""
        problem = (step_problem(step, self.recorded_step + 1, self.monitor.final_step,
                                EVALUATOR_STEP_LEAD)
                   or ("duplicate" if step in self._complete_steps
                       or robot in self._truth.get(step, {}) else None))
        if problem:
            return [Dropped(problem)]
        self._last_data_wall_s = wall_s
        stood_s = self._clock.seen(step, wall_s)
        moved = [] if stood_s is None else [info(
            f"the world's steps come again: step {step} after {stood_s:.1f} s without a new "
            f"one")]
        poses = self._truth.setdefault(step, {})
        poses[robot] = pose
        if len(poses) < self.num_robots:
            return moved
        self._complete_steps.append(step)
        if self._first_step_wall_s is None:
            self._first_step_wall_s = wall_s
            self._unseen.first_step(wall_s)
        return moved + self._process(wall_s)

    def world_status(self, step: int, stamp_step: int, stepping_over: bool, reason: str
                     ) -> list[Effect]:
        """The world's status of ``step`` (its stamp's step ``stamp_step``, ``step_of``):
        when it stepped over, the run ends as soon as the ground truth up to that step is in
        (``tick``)."""
        if stamp_step != step:
            return [Dropped(f"stamp of step {stamp_step} in a status of step {step}")]
        if not stepping_over or self._world_over == (step, reason):
            return []
        self._world_over = (step, reason)  # the latest, should a forged one precede
        return [info(f"the world stepped over at step {step} ({reason})")]

    def link_counts(self, step: int, counts: dict[str, int]) -> list[Effect]:
        """The link relay's update counts of ``step`` (``sent``, ``on_time``, ``late``,
        ``never``; the first copy of a step counts), kept for the steps of the last
        ``_LINK_COUNTS_KEPT`` evaluations, so the memory is bounded."""
        oldest = self.recorded_step - _LINK_COUNTS_KEPT * self.interval_steps
        problem = (step_problem(step, max(oldest, 0), self.monitor.final_step,
                                EVALUATOR_STEP_LEAD)
                   or (f"counts {counts} do not add up"
                       if counts["on_time"] + counts["late"] + counts["never"] != counts["sent"]
                       else None))
        if problem:
            return [Dropped(problem)]
        self._link_counts.setdefault(step, counts)
        for old in [s for s in self._link_counts if s < oldest]:
            del self._link_counts[old]
        return []

    # -- inputs: what the robots publish -----------------------------------------------------

    def path_estimate(self, robot: int, stamp_ns: int, stamps_s: np.ndarray,
                      poses: np.ndarray, wall_s: float) -> list[Effect]:
        """Robot ``robot``'s estimate of its keyframe trajectory (stamps (K,) [s], poses
        (K, 3), map frame), published at ``stamp_ns`` [ns sim time]."""
        _, problem = self.step_of(stamp_ns, keyframes_only=True)
        problem = (problem or self._stale_problem(self._paths, robot, stamp_ns)
                   or size_problem(len(poses), self.max_keyframes, "poses"))
        if problem:
            return [Dropped(problem)]
        return self._on_estimate(self._paths, robot, stamp_ns, (stamps_s, poses), wall_s)

    def landmark_estimate(self, robot: int, stamp_ns: int, positions: dict[int, np.ndarray],
                          wall_s: float) -> list[Effect]:
        """Robot ``robot``'s landmark estimates ``{id: (x, y)}`` [m, map frame], published at
        ``stamp_ns`` [ns sim time] (at most ``MAX_LANDMARKS_PER_UPDATE``, the driver
        checks)."""
        _, problem = self.step_of(stamp_ns, keyframes_only=True)
        problem = (problem or self._stale_problem(self._landmarks, robot, stamp_ns)
                   or first_problem(id_problem(landmark, None, "landmark id")
                                    for landmark in positions))
        if problem:
            return [Dropped(problem)]
        return self._on_estimate(self._landmarks, robot, stamp_ns, positions, wall_s)

    def keyframe_covariance(self, robot: int, stamp_ns: int, covariance: np.ndarray,
                            wall_s: float) -> list[Effect]:
        """Robot ``robot``'s marginal covariance (3, 3) (x, y [m], theta [rad], map frame) of
        its latest keyframe, stamped with that keyframe's time [ns sim time]."""
        _, problem = self.step_of(stamp_ns, keyframes_only=True)
        newest = self._keyframe_covariances.newest_key(robot)
        stamp_s = nanoseconds_to_seconds(stamp_ns)
        problem = (problem or ("older than the robot's last keyframe covariance"
                               if newest is not None and stamp_key(stamp_s) < newest else None)
                   or _covariance_problem(covariance))
        if problem:
            return [Dropped(problem)]
        self._keyframe_covariances.add(robot, stamp_s, covariance)
        if robot in self._overdue and not self._behind(robot, max(self.recorded_step, 0)):
            self._overdue.discard(robot)
        return self._process(wall_s)

    def team_update(self, robot: int, update: TeamUpdate, wall_s: float) -> list[Effect]:
        """A record of robot ``robot``'s update stream (wire-checked by the driver): its
        targets and rendezvous events are taken in sequence order exactly as a robot reads
        them (malformed or impostor records are refused)."""
        try:
            self._team_updates.receive(update, robot)
        except InvalidTeamUpdate as error:
            return [Dropped(f"rejected a team update: {error}")]
        for ready in self._team_updates.pop_ready():
            for record in ready.targets:
                self._targets[ready.robot_id][record.decision_index] = record
            self._rendezvous.extend(ready.rendezvous)
            if self.association is not None:
                self.association.team_update(ready)
        return self._process(wall_s) if self.monitor.stopped else []

    def sonar_truth(self, robot: int, stamp_ns: int, step: int,
                    readings: tuple[LandmarkReading, ...], sources: tuple[int, ...],
                    wall_s: float) -> list[Effect]:
        """The world's truth of robot ``robot``'s scan at keyframe ``step`` (stamped
        ``stamp_ns`` [ns sim time]): its landmark readings (body frame) and where each came
        from (a landmark id, or ``sensors.CLUTTER``); only when the sonar is not ideal."""
        stamp_step, problem = self.step_of(stamp_ns, keyframes_only=True)
        problem = (("the sonar is ideal: no truth of its scans is kept"
                    if self.association is None else None)
                   or problem or (f"stamp of step {stamp_step} in the truth of step {step}"
                                  if stamp_step != step else None)
                   or (f"{len(sources)} sources of {len(readings)} readings"
                       if len(sources) != len(readings) else None)
                   or size_problem(len(readings), MAX_LANDMARKS_PER_UPDATE, "readings")
                   or first_problem(None if source == CLUTTER
                                    else id_problem(source, None, "landmark id")
                                    for source in sources))
        if problem:
            return [Dropped(problem)]
        self.association.sonar_truth(robot, step, readings, sources)
        return self._process(wall_s) if self.monitor.stopped else []

    def correspondences(self, robot: int, stamp_ns: int, step: int,
                        pairs: Sequence[tuple[int, int]], wall_s: float) -> list[Effect]:
        """The teammates' landmarks robot ``robot`` tied to its own while answering ``step``
        (stamped ``stamp_ns`` [ns sim time]): pairs of team-graph ids (own, teammate's)."""
        stamp_step, problem = self.step_of(stamp_ns)
        problem = (("landmarks carry identities: no robot ties them"
                    if self.association is None or self.params.sensors.landmark_ids
                    else None)
                   or problem or (f"stamp of step {stamp_step} in correspondences of step "
                                  f"{step}" if stamp_step != step else None)
                   or size_problem(len(pairs), MAX_LANDMARKS_PER_UPDATE, "correspondences")
                   or first_problem(
                       f"landmarks {own} and {theirs} are not robot {robot}'s and a "
                       f"teammate's" for own, theirs in pairs
                       if landmark_owner(own) != robot or landmark_owner(theirs) in (None, robot)
                       or not landmark_owner(theirs) < self.num_robots))
        if problem:
            return [Dropped(problem)]
        self.association.correspondences(robot, step, pairs)
        return []

    def command(self, robot: int, report: CommandReport, wall_s: float) -> list[Effect]:
        """Robot ``robot``'s answer to a step (on its topic): its finished flag, its
        stream's length and its progress bookkeeping."""
        last = self._last_command[robot]
        step, problem = self.step_of(report.stamp_ns)
        problem = ((f"robot_id {report.robot_id} on robot {robot}'s topic"
                    if report.robot_id != robot else None)
                   or problem or (f"stamp of step {step} in a command for step {report.step}"
                               if step != report.step else None)
                   or (f"blocked_s {report.blocked_s} < 0" if report.blocked_s < 0.0 else None)
                   or first_problem(self._meeting_problem(robot, meeting, report.stamp_ns)
                                    for meeting in report.meetings)
                   or command_sequence_problem(report.team_sequence, 0 if last is None
                                               else last.team_sequence, MAX_SEQUENCE_LEAD))
        if problem:
            return [Dropped(problem)]
        if last is not None and report.step <= last.step:
            return []  # an older answer arriving late
        self._last_command[robot] = report
        stamp_s = self._stamp_s(report.step)
        self._blocked_s.add(robot, stamp_s, report.blocked_s)
        self._slam_recoveries.add(robot, stamp_s, report.slam_recoveries)
        self._given_up[robot].extend(report.given_up)
        self._meetings.extend(report.meetings)
        effects: list[Effect] = []
        if self.liveness.heard(robot, *self._status_times(wall_s), "answers the world again"):
            effects.append(info(f"robot {robot} rejoined: it answers the world again "
                                f"(step {report.step})"))
        if report.finished:
            self.liveness.finished(robot, stamp_s, wall_s - self._started_wall_s)
        effects += self._check_all_finished(wall_s)
        if self.monitor.stopped and self.exit_code is None:
            effects += self._process(wall_s)
        return effects

    def _meeting_problem(self, robot: int, meeting: MeetingEntry, stamp_ns: int
                         ) -> str | None:
        """Reason if a meeting robot ``robot`` reported in its command stamped ``stamp_ns``
        [ns] is implausible: another requester, a partner outside the team or itself, a
        factor added after the command or requested after it was added, a negative trace."""
        stamp_s = nanoseconds_to_seconds(stamp_ns)
        return ((f"a meeting requested by robot {meeting.requester_id}"
                 if meeting.requester_id != robot else None)
                or id_problem(meeting.partner_id, self.num_robots, "meeting partner id")
                or ("a meeting with itself" if meeting.partner_id == robot else None)
                or id_problem(meeting.rendezvous_id, None, "rendezvous id")
                or (f"a meeting at {meeting.stamp_s:g} s, after its command's {stamp_s:g} s"
                    if stamp_key(meeting.stamp_s) > stamp_key(stamp_s) else None)
                or (f"a meeting requested at {meeting.requested_at_s:g} s, after it happened"
                    if meeting.requested_at_s > meeting.stamp_s else None)
                or ("a meeting with a negative covariance trace"
                    if min(meeting.trace_before_m2, meeting.trace_after_m2) < 0.0 else None))

    def liveliness(self, robot: int, alive: bool, restarted: bool, wall_s: float
                   ) -> list[Effect]:
        """The middleware reported robot ``robot``'s liveliness gained (``restarted``: by a
        new process) or lost."""
        if alive:
            self._unseen.seen(robot)
            effects: list[Effect] = [info(
                f"robot {robot}: liveliness asserted"
                + (" by a new process (restarted)" if restarted else ""))]
            if self.liveness.liveliness_back(robot, restarted, *self._status_times(wall_s)):
                effects.append(warn(f"robot {robot} lost: its process was restarted"))
            return effects
        self.liveness.liveliness_lost(robot, *self._status_times(wall_s))
        return [warn(f"robot {robot}: liveliness lost (process dead, stopped or wedged, or "
                     f"its assertions lost on the network)")]

    def tick(self, wall_s: float, world_on_graph: bool,
             status_publishers: frozenset[str]) -> list[Effect]:
        """The periodic look (about once a wall second): whether the world (the ground truth's
        publisher) is on the graph, who publishes the world's status; robots never seen alive
        or lost for good, the world's end, missing updates, silence."""
        if self.exit_code is not None:
            return []
        effects = self._watch_world(wall_s, world_on_graph)
        for robot in self._unseen.due(wall_s):
            self.liveness.liveliness_lost(robot, *self._status_times(wall_s))
        effects += self._end_with_the_world(wall_s, status_publishers)
        if self.exit_code is not None:
            return effects
        for robot in self.liveness.confirm(wall_s - self._started_wall_s):
            never = "" if self._unseen.was_seen(robot) else " (never seen alive)"
            effects.append(warn(f"robot {robot} lost: no liveliness for "
                                f"{self.liveness.grace_s:g} s{never}"))
            effects += self._check_all_finished(wall_s)
        effects += self._watch_the_clock(wall_s, world_on_graph)
        effects += self._request_missing_updates()
        effects += self._process(wall_s)
        silent_s = wall_s - self._last_data_wall_s
        if self.exit_code is None and silent_s > self.settings.silence_timeout_s:
            effects += self.finish(f"no ground truth for {silent_s:.0f} s (world or robots "
                                   f"stopped)", EXIT_SILENCE, wall_s)
        return effects

    # -- the watch ---------------------------------------------------------------------------

    def _watch_world(self, wall_s: float, world_on_graph: bool) -> list[Effect]:
        """Say at once when the world leaves the ROS graph or comes back; the run then ends
        by the silence rule (exit code 3)."""
        event = self._world_watch.update(world_on_graph, wall_s)
        if event == WorldEvent.LOST:
            return [warn(f"the world left the ROS graph (no publisher of its ground truth); "
                         f"the run ends with the summary so far if it is not back within "
                         f"{self.settings.silence_timeout_s:g} s")]
        if event == WorldEvent.BACK:
            return [info("the world is back on the ROS graph")]
        return []

    def _watch_the_clock(self, wall_s: float, world_on_graph: bool) -> list[Effect]:
        """Warn when no new step of ground truth came for ``CLOCK_STOPPED_S`` wall seconds
        (then every ``CLOCK_STOPPED_REPEAT_S``) while the run is not over: a world stopped
        (SIGSTOP) or waiting for a robot's answer stays on the graph and says nothing.
        Before the first ground truth, say so ``FIRST_STEP_AFTER_S`` after the start (then
        as often): a restarted evaluator that gets nothing from the world waited in silence
        until the silence rule ended the run."""
        if (self._world_over is not None or self.monitor.stopped
                or self._team_finished is not None):
            return []
        waited_s = self._clock.no_first_step(wall_s)
        if waited_s is not None:
            where = ("the world is on the ROS graph; at a run's start it holds its first step "
                     "until the team is connected" if world_on_graph
                     else "the world is not on the ROS graph")
            return [info(f"no ground truth from the world yet, {waited_s:.0f} s after this "
                         f"evaluator started ({where}); the run ends by silence after "
                         f"{self.settings.silence_timeout_s:g} s without any")]
        stood_s = self._clock.stopped(wall_s)
        if stood_s is None:
            return []
        return [warn(f"no new step from the world for {stood_s:.1f} s (last ground truth of "
                     f"step {self._clock.step}); the run ends by silence after "
                     f"{self.settings.silence_timeout_s:g} s without one")]

    def _end_with_the_world(self, wall_s: float, status_publishers: frozenset[str]
                            ) -> list[Effect]:
        """End the run (exit code 3, as for silence) when the world stepped over at a step
        whose ground truth is recorded and evaluated as far as due, and no stop rule fired:
        ``liveliness_grace_s`` after the last ground truth when every robot is lost here
        (the observer would wait for silence), ``estimate_wait_s`` after it otherwise (the
        robots' last answers and estimates had that long to come). Only while the world is
        the sole publisher of its status: a forged "stepping over" must not end a live run."""
        if self._world_over is None or self.monitor.stopped or self.exit_code is not None:
            return []
        step, reason = self._world_over
        if (self._latest_step() != step or self.recorded_step != step
                or self._pending is not None or self._complete_steps):
            return []
        if status_publishers != {self._world_node_name}:
            return [warn(f"the world's status says it stepped over, but it has the "
                         f"publishers {sorted(status_publishers)}: not trusted; ending by "
                         f"silence instead", _UNTRUSTED_STATUS_KEY)]
        every_robot_lost = all(self.liveness.status(r) == LOST for r in range(self.num_robots))
        wait_s = self.liveness.grace_s if every_robot_lost else self.settings.estimate_wait_s
        if wall_s - self._last_data_wall_s < wait_s:
            return []
        return self.finish(f"the world stepped over at step {step} ({reason})", EXIT_SILENCE,
                           wall_s)

    def _check_all_finished(self, wall_s: float) -> list[Effect]:
        """Every robot that is not lost has reported ``finished`` (at least one is not
        lost): the run ends at the latest step they answered, as soon as its ground truth is
        in; the robots lost then without having finished are kept for the stop reason."""
        if self._team_finished is not None:
            return []
        self._team_finished = every_live_robot_finished(
            [c.step if c is not None and c.finished else None for c in self._last_command],
            [self.liveness.status(r) == LOST for r in range(self.num_robots)])
        return [] if self._team_finished is None else self._process(wall_s)

    def _missing_updates(self) -> list[MissingRange]:
        """Gaps in the robots' update streams up to the latest sequence each robot reported
        in its motion commands."""
        latest = {robot: command.team_sequence
                  for robot, command in enumerate(self._last_command) if command is not None}
        return self._team_updates.missing(latest)

    def _request_missing_updates(self) -> list[Effect]:
        gaps = tuple(self._missing_updates())
        return [RequestUpdates(gaps)] if gaps else []

    # -- evaluation --------------------------------------------------------------------------

    def _process(self, wall_s: float) -> list[Effect]:
        """Record complete steps of ground truth in order and run the evaluations due.

        An evaluation at step k reads each robot's estimates as of step k - 1 (the robots
        publish them while answering their keyframe steps, before the world steps on), and
        waits up to ``estimate_wait_s`` for those of the last keyframe before k to arrive,
        so that the result does not depend on message timing.
        """
        effects: list[Effect] = []
        while self.evaluator is not None and self.exit_code is None:
            if self.monitor.stopped:
                return effects + self._finish_when_streams_complete(wall_s)
            if self._pending is None:
                if not self._complete_steps:
                    done, more = self._finished_after_evaluation(wall_s)
                    effects += more
                    if done:
                        continue
                    if not self._finished_unevaluated():
                        return effects
                    self._pending = (self.recorded_step, wall_s)
                    continue
                step = self._complete_steps.popleft()
                self._record_step(step)
                if self.evaluates_at(step) or self._finished_by(step):
                    self._pending = (step, wall_s)
                continue
            step, queued_wall_s = self._pending
            missing = self._robots_without_estimates(step)
            if missing and wall_s - queued_wall_s < self.settings.estimate_wait_s:
                return effects
            if missing:
                self._overdue.update(missing)
                effects.append(warn(
                    f"evaluating step {step} with older estimates of robots {missing}: theirs "
                    f"did not arrive within {self.settings.estimate_wait_s:g} s (not waited "
                    f"for again until they publish)"))
            self._pending = None
            metrics, more = self._evaluate(step)
            stopped = self.monitor.observe(step, metrics, self._finished_by(step),
                                           self._lost_unfinished())
            if not stopped and wall_s >= self._next_so_far_wall_s:
                self._next_so_far_wall_s = wall_s + SO_FAR_INTERVAL_S
                # Before the progress line: what the log showed is on disk.
                effects.append(KeepSoFar(self._summary_so_far(wall_s)))
            effects += more
            if stopped:
                effects += self._stopping(wall_s)
        return effects

    def _stopping(self, wall_s: float) -> list[Effect]:
        """A stop rule fired: give the robots' update streams ``estimate_wait_s`` to
        complete, and ask for what is missing."""
        self._stream_wait_deadline_s = wall_s + self.settings.estimate_wait_s
        return self._request_missing_updates()

    def _finish_when_streams_complete(self, wall_s: float) -> list[Effect]:
        """After the stop rule fired: finish once every robot's update stream is complete up
        to what it reported (so the summary holds every decision made before the stop
        step), or after ``estimate_wait_s`` wall seconds, saying what is missing."""
        missing = self._missing_updates()
        silent = self._missing_commands()
        unseen = self._missing_scans()
        if (missing or silent or unseen) and wall_s < self._stream_wait_deadline_s:
            return []
        effects: list[Effect] = []
        if unseen:
            effects.append(warn(f"association counted without the truth of {len(unseen)} "
                                f"keyframe scans that never arrived (robot, step): "
                                f"{unseen[:5]}"))
        if missing:
            effects.append(warn("summary written without team updates that never arrived: "
                                + ", ".join(f"robot {g.robot_id} #{g.first_sequence}-"
                                            f"{g.last_sequence}" for g in missing)))
        if silent:
            effects.append(warn(
                "summary written without the motion commands of the step before the stop "
                "step (their blocked time and targets given up) of robots "
                + ", ".join(str(robot) for robot in silent)))
        return effects + self.finish(self.monitor.stop_reason, self.monitor.exit_code, wall_s)

    def _missing_scans(self) -> list[tuple[int, int]]:
        """(robot, step) of the keyframe scans up to the step before the stop step whose
        truth has not arrived (none with the ideal sonar)."""
        final = self.monitor.final_metrics
        if self.association is None or final is None:
            return []
        return self.association.missing_scans(round(final.stamp_s / self.time_step_s) - 1)

    def _missing_commands(self) -> list[int]:
        """Robots waited for (``_waited_for``) whose motion command answering the step
        before the stop step has not arrived."""
        final = self.monitor.final_metrics
        if final is None:
            return []
        step = round(final.stamp_s / self.time_step_s)
        return [robot for robot, last in enumerate(self._last_command)
                if self._waited_for(robot) and (last is None or last.step < step - 1)]

    def _finished_by(self, step: int) -> bool:
        return self._team_finished is not None and step >= self._team_finished.step

    def _lost_unfinished(self) -> tuple[int, ...]:
        """The robots lost without having finished when all the others had finished."""
        return () if self._team_finished is None else self._team_finished.lost

    def _finished_after_evaluation(self, wall_s: float) -> tuple[bool, list[Effect]]:
        """Every robot finished at the last recorded step, which was evaluated before their
        answers said so: the stop rule runs again on that evaluation (True if it fired).
        Without this, a run whose robots all finished at an evaluation step waited for
        ground truth that never came (exit 3 after ``silence_timeout_s``)."""
        if not (self._finished_by(self.recorded_step) and self._recorded_step_evaluated()):
            return False, []
        if not self.monitor.observe_finished(self.recorded_step, self._lost_unfinished()):
            return False, []
        return True, self._stopping(wall_s)

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
        return self._covariance_behind(robot) or any(
            history.newest_key(robot) is None or history.newest_key(robot) < needed
            for history in (self._paths, self._landmarks))

    def _covariance_behind(self, robot: int) -> bool:
        """Whether the covariance of the last keyframe of the robot's newest path is missing,
        once the robot published one (a robot or recording without them is not waited
        for; a robot without an estimate of its own pose publishes none)."""
        newest = self._keyframe_covariances.newest_key(robot)
        path = self._paths.newest(robot)
        return (newest is not None and path is not None and len(path[0]) > 0
                and stamp_key(float(path[0][-1])) > newest)

    def _waited_for(self, robot: int) -> bool:
        """Whether an evaluation waits for the robot's estimates: unless it is lost (its
        liveliness lapsed) or overdue (an evaluation already went on without its estimates
        after ``estimate_wait_s``, until it has caught up with the latest recorded step: a
        robot that keeps lagging, as under ``--realtime 1000``, once made every evaluation
        wait ``estimate_wait_s`` again, 30 s each). A live robot publishes the
        estimates of a keyframe step right after its answer to that step, which the world
        needs before it publishes the next step's ground truth, so the wait ends; when the
        messages of the different topics reach the observer (a flooded or loaded node takes
        them in bursts) does not decide which estimates an evaluation reads."""
        return self.liveness.status(robot) != LOST and robot not in self._overdue

    def _on_estimate(self, history: StampedEstimates, robot: int, stamp_ns: int, value: Any,
                     wall_s: float) -> list[Effect]:
        history.add(robot, nanoseconds_to_seconds(stamp_ns), value)
        if robot in self._overdue and not self._behind(robot, max(self.recorded_step, 0)):
            self._overdue.discard(robot)
        return self._process(wall_s)

    @staticmethod
    def _stale_problem(history: StampedEstimates, robot: int, stamp_ns: int) -> str | None:
        """Reason if an estimate is older than the newest one of the robot (robots publish
        their estimates in time order)."""
        newest = history.newest_key(robot)
        if newest is not None and stamp_key(nanoseconds_to_seconds(stamp_ns)) < newest:
            return "older than the robot's last estimate"
        return None

    def _latest_step(self) -> int:
        """The newest step this observer has ground truth of (-1 before the first)."""
        return max([self.recorded_step, *self._truth, *self._complete_steps])

    def _stamp_s(self, step: int) -> float:
        return sim_time_s(step, self.time_step_s)

    def _status_times(self, wall_s: float) -> tuple[float, float]:
        """(simulation time of the latest recorded step, wall seconds since the start) [s]."""
        return self._stamp_s(max(self.recorded_step, 0)), wall_s - self._started_wall_s

    def _evaluate(self, step: int, publish: bool = True) -> tuple[TeamMetrics, list[Effect]]:
        """Team metrics at ``step`` (its ground truth recorded), to publish; the caller
        hands them to the run monitor."""
        stamp_s = self._stamp_s(step)
        as_of_s = self._stamp_s(max(step - 1, 0))
        self._evaluated = (self._paths.as_of(as_of_s), self._landmarks.as_of(as_of_s))
        self._blocked_s.as_of(as_of_s)  # drops the values no later summary needs
        self._slam_recoveries.as_of(as_of_s)
        metrics = self.evaluator.evaluate(stamp_s, *self._evaluated,
                                          self._keyframe_covariances.latest_as_of(as_of_s))
        decisions = sum(len(self.monitor.decisions_counted(chosen, until=metrics))
                        for chosen in self._decisions())
        effects: list[Effect] = []
        if publish:
            effects.append(PublishMetrics(metrics, decisions))
        interval_s = self.settings.progress_interval_s
        if stamp_s >= self._next_progress_s:
            self._next_progress_s += interval_s * math.floor(
                (stamp_s - self._next_progress_s) / interval_s + 1.0)
            effects.append(info(_progress_line(metrics, decisions)))
        return metrics, effects

    # -- the end -----------------------------------------------------------------------------

    def finish(self, reason: str, exit_code: int, wall_s: float, publish: bool = True
               ) -> list[Effect]:
        """End the run: the summary (``Finished``) and the line that says how it went.

        After a stop rule fired the summary holds the values of that step. Otherwise (Ctrl-C,
        silence) the steps recorded so far are evaluated once more, so the summary holds the
        latest complete step (published unless ``publish`` is False)."""
        if self.exit_code is not None:
            return []
        self.exit_code = exit_code
        self.monitor.end(reason)
        effects: list[Effect] = []
        if self.evaluator is not None and not self.monitor.stopped:
            while self._complete_steps:
                self._record_step(self._complete_steps.popleft())
            last = self.monitor.final_metrics
            if self.recorded_step >= 0 and (
                    last is None or last.stamp_s != self._stamp_s(self.recorded_step)):
                metrics, more = self._evaluate(self.recorded_step, publish)
                effects += more
                self.monitor.record(metrics)
        summary, notes = self._summary(wall_s)
        effects += notes
        effects.append(info(
            f"done ({summary.stop_reason}): explored {summary.explored_ratio:.3f}, distance "
            f"{summary.distance_m:.1f} m, loc RMSE {summary.loc_rmse_m:.3f} m, landmark RMSE "
            f"{summary.landmark_rmse_m:.3f} m, {summary.decisions} decisions, sim "
            f"{summary.sim_time_s:.1f} s, wall {summary.wall_s:.1f} s"))
        if summary.association is not None:
            effects.append(info(association_line(summary.association)))
        return effects + [Finished(summary, exit_code)]

    def _decisions(self) -> list[list[DecisionEntry]]:
        """Each robot's decisions received so far, in order."""
        return [[DecisionEntry(t.stamp_s, (float(t.position[0]), float(t.position[1])), t.kind,
                               t.planning_time_s, t.planner_failed)
                 for _, t in sorted(records.items())]
                for records in self._targets]

    def summary(self, wall_s: float) -> RunSummary:
        """The run's summary so far (``Finished`` carries the final one)."""
        return self._summary(wall_s)[0]

    def _summary(self, wall_s: float) -> tuple[RunSummary, list[Effect]]:
        """The run's summary (the run monitor's, em-sim's schema) with each robot's progress,
        status, status changes and downtime, and what it lacks, to log. ``wall_s`` [s]: now
        (the summary's wall time counts from the first step)."""
        notes: list[Effect] = []
        run_wall_s = 0.0 if self._first_step_wall_s is None else wall_s - self._first_step_wall_s
        final = self.monitor.final_metrics
        end_s = math.inf if final is None else final.stamp_s
        meetings = sorted((m for m in self._meetings if m.stamp_s < end_s),
                          key=lambda m: (m.stamp_s, m.requester_id))
        progress, more = self._progress()
        notes += more
        summary = self.monitor.summary(self._decisions(), run_wall_s, progress=progress,
                                       rendezvous_events=self._rendezvous, meetings=meetings)
        if final is not None and self._link_counts:
            step = round(final.stamp_s / self.time_step_s)
            summary.team_updates = self._link_counts.get(step)
            if summary.team_updates is None:
                notes.append(warn(f"no link counts of step {step} arrived: the summary has no "
                                  f"team_updates"))
        if final is not None and self.association is not None:
            interval_s = self.params.slam.keyframe_interval_steps * self.time_step_s
            summary.association = self.association.counts(
                round(final.stamp_s / self.time_step_s) - 1,
                {robot: np.rint(stamps_s / interval_s).astype(int)
                 for robot, (stamps_s, _) in self._evaluated[0].items()})
        until_s = self._status_times(wall_s)
        for entry in summary.robots:
            entry.status = self.liveness.status(entry.id)
            entry.status_changes = self.liveness.changes(entry.id)
            entry.status_changes_omitted = self.liveness.omitted_changes(entry.id)
            entry.downtime_s, entry.downtime_wall_s = self.liveness.downtime_s(entry.id,
                                                                               *until_s)
        return summary, notes

    def _summary_so_far(self, wall_s: float) -> RunSummary:
        """The summary as of the latest evaluation, its stop reason saying that the run went
        on (``KeepSoFar``); what it lacks is not logged (the final summary says it)."""
        summary = self._summary(wall_s)[0]
        summary.stop_reason = (f"{EVALUATOR_LOST_PREFIX}the run so far, to t = "
                               f"{summary.sim_time_s:g} s (the evaluator ended before the run)")
        return summary

    def _progress(self) -> tuple[list[RobotProgressRecord] | None, list[Effect]]:
        """Each robot's progress bookkeeping as of the step before the final evaluation
        (its blocked time NaN and SLAM recoveries None if no command of it arrived by then);
        None before any evaluation."""
        final = self.monitor.final_metrics
        if final is None:
            return None, []
        as_of_s = final.stamp_s - self.time_step_s
        blocked, recoveries = self._blocked_s.as_of(as_of_s), self._slam_recoveries.as_of(as_of_s)
        notes: list[Effect] = [
            warn(f"robot {robot} reported {last.given_up_count} targets given up, "
                 f"{len(self._given_up[robot])} arrived")
            for robot, last in enumerate(self._last_command)
            if last is not None and last.given_up_count > len(self._given_up[robot])]
        return [RobotProgressRecord(tuple(self._given_up[robot]), blocked.get(robot, math.nan),
                                    recoveries.get(robot))
                for robot in range(self.num_robots)], notes

    def map_layers(self, title: str) -> TeamMapLayers:
        """The final map's layers: the truth and the estimates of the last evaluation, the
        targets counted in the summary, the targets given up before the end and the
        rendezvous; ``title`` ends the picture's title (planner, team size and seed come
        first)."""
        paths, landmarks = self._evaluated
        final = self.monitor.final_metrics
        end_s = math.inf if final is None else final.stamp_s
        return evaluation_layers(
            self.evaluator, {r: poses for r, (_, poses) in paths.items()},
            {r: np.array(list(e.values())).reshape(-1, 2) for r, e in landmarks.items()},
            {r: [d.target_entry() for d in self.monitor.decisions_counted(chosen)]
             for r, chosen in enumerate(self._decisions())},
            rendezvous_outcomes(self._rendezvous, end_s),
            f"{self.params.planner.name}, {self.num_robots} robots, seed "
            f"{self.params.run.seed}: {title}",
            given_up={r: [g for g in entries if g.stamp_s < end_s]
                      for r, entries in enumerate(self._given_up)},
            pose_covariances=self._path_covariances(paths))

    def _path_covariances(self, paths: dict[int, Any]) -> dict[int, np.ndarray] | None:
        """The published covariances (K, 3, 3) of the keyframes of each evaluated path
        (``{robot: (stamps, poses)}``), NaN where none arrived; None if no robot published
        any."""
        if not self._keyframe_covariances.published:
            return None
        return {r: self._keyframe_covariances.along(r, stamps)
                for r, (stamps, _) in paths.items()}


def _covariance_problem(covariance: np.ndarray) -> str | None:
    """Reason if ``covariance`` is not a finite symmetric 3x3 with a nonnegative diagonal."""
    matrix = np.asarray(covariance, dtype=float)
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
        return f"a covariance of shape {matrix.shape} or with non-finite entries"
    if (np.diag(matrix) < 0.0).any() or not np.allclose(matrix, matrix.T, rtol=1e-6,
                                                        atol=1e-12):
        return "a covariance that is not symmetric with a nonnegative diagonal"
    return None


def _progress_line(metrics: TeamMetrics, decisions: int) -> str:
    def metres(value: float) -> str:
        return "n/a" if math.isnan(value) else f"{value:.3f} m"
    return (f"t={metrics.stamp_s:7.1f} s  explored {metrics.explored_ratio:5.3f}  distance "
            f"{metrics.distance_m:7.1f} m  loc RMSE {metres(metrics.loc_rmse_m)}  landmark RMSE "
            f"{metres(metrics.landmark_rmse_m)}  decisions {decisions}")

