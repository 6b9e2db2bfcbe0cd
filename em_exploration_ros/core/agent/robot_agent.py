"""One robot's brain: team SLAM, virtual map, planner and motion control.

A ``RobotAgent`` knows only what its own sensors report (``StepInput``) and what its
teammates share (``TeamUpdate``). It is driven identically by em-sim (in-process) and by
the ``em-robot`` ROS node, which makes seeded runs of both choose the same targets.

Per simulation step: teammates' updates released by the lockstep barrier are applied
first (``apply_team_updates``), then ``step`` integrates odometry, cuts a keyframe every
``keyframe_interval_steps`` (and updates SLAM), keeps rendezvous bookkeeping, decides a
new target when the current one is reached, and returns the motion for the next step.
What is new for the teammates is collected with ``take_outgoing``.

A target the robot cannot reach is given up (``core.planning.progress``): when its own
odometry shows it blocked, when its estimated distance to the target stops shrinking, or
at the target's deadline. The robot then excludes candidates near that target for a
while (its own blacklist; teammates are not told, see ``_give_up``) and, if blocked,
first turns on the spot away from the blocked direction.

Rendezvous: a robot that chooses a RENDEZVOUS target sends REQUEST with a wait limit that
scales with its travel to the meeting point; the partner goes to the meeting point and
waits until both arrived or the limit passed. The requester sends RELEASE when it gives the
meeting up (new target, its wait limit passed, finished, partner lost); a finished robot
answers a request with RELEASE and tells the team it finished (``TeamUpdate.finished``);
finished teammates are no rendezvous candidates. A teammate silent for
``teammate_silent_after_s`` is *out of contact* (lost, or out of range of an imperfect
link): a partner stops waiting for such a requester (RELEASE), but the teammate stays a
rendezvous candidate at its last known target, and a requester keeps going to such a
partner until its wait limit, because meeting is what restores the link. Until then the
robot plans with what it has: the teammate's last keyframes and targets. For each meeting it
requested, the robot records the trace of its own latest pose covariance just before and after
the SLAM update that added the first inter-robot factor with the partner (``meeting_effects``).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from em_exploration_ros.core.planning.frontiers import (Frontier, candidate_targets,
                                                        exploration_frontiers, frontier_cells)
from em_exploration_ros.core.records.team_data import FrontierType
from em_exploration_ros.core.geometry import compose
from em_exploration_ros.core.planning.motion import ApfController
from em_exploration_ros.core.planning.rendezvous import Meeting, RendezvousBook, meeting_timeout_s
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.planner_api import Decision, Planner, PlanningContext
from em_exploration_ros.core.planning.planners import make_planner
from em_exploration_ros.core.planning.progress import (GivenUpTarget, GiveUpReason,
                                                       ProgressMonitor, RecoveryTurn,
                                                       TargetBlacklist, blocked_step)
from em_exploration_ros.core.world.sensors import odometry_covariance_per_step
from em_exploration_ros.core.records.readings import (LandmarkReading, OdometryReading,
                                                      TeammateReading)
from em_exploration_ros.core.slam.own_landmarks import OwnLandmarks
from em_exploration_ros.core.slam.team_slam import KeyframeBuilder, TeamSlam
from em_exploration_ros.core.records.readings import KeyframeMeasurements
from em_exploration_ros.core.records.team_data import (RendezvousEvent, RendezvousState,
                                                     TargetRecord, TeamUpdate, TeamUpdateOutbox)
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.records.wire_model import DeadReckoningDifferencer

_LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepInput:
    """What a robot's own sensors report at one simulation step.

    ``odom_pose`` is the dead-reckoning pose in the robot's odom frame (x [m], y [m],
    theta [rad]); ``odom_increment_covariance`` the 3x3 covariance of the last per-step
    increment. Landmark and teammate readings are in the robot's body frame.
    """

    step: int
    stamp_s: float
    odom_pose: np.ndarray
    odom_increment_covariance: np.ndarray
    landmarks: tuple[LandmarkReading, ...] = ()
    teammates: tuple[TeammateReading, ...] = ()


@dataclass(frozen=True)
class MotionCommand:
    """Motion for the next step: turn [rad] then move ``forward_m`` [m] along the heading."""

    turn_rad: float
    forward_m: float
    finished: bool


@dataclass(frozen=True)
class DecisionRecord:
    """One planning decision of this robot at simulation time ``stamp_s`` [s].

    ``planning_time_s``: wall time of the whole decision [s]: the map rebuild from the SLAM
    estimate, the candidates and the planner (``Decision.choose_time_s`` is the planner's
    part).
    """

    decision_index: int
    stamp_s: float
    target: Frontier
    planning_time_s: float
    num_candidates: int
    explored_ratio: float
    planner_failed: bool = False


@dataclass(frozen=True)
class MeetingEffect:
    """What a rendezvous requested by this robot did to its own uncertainty.

    ``trace_before_m2`` / ``trace_after_m2``: trace of the marginal covariance of this
    robot's latest keyframe pose (x, y, theta; m^2 and rad^2 summed) just before and just
    after the SLAM update that added the first inter-robot factor with ``partner_id``
    between the request and this robot's next decision, at simulation time ``stamp_s`` [s].
    """

    rendezvous_id: int
    partner_id: int
    requested_at_s: float
    stamp_s: float
    trace_before_m2: float
    trace_after_m2: float


@dataclass
class _Pending:
    """What this robot has produced since its last update to the team."""

    keyframes: list[KeyframeMeasurements] = field(default_factory=list)
    targets: list[TargetRecord] = field(default_factory=list)
    rendezvous: list[RendezvousEvent] = field(default_factory=list)
    finished: bool = False


class RobotAgent:
    """The decision-making of one robot, independent of ROS (see module docstring)."""

    def __init__(self, robot_id: int, params: ExplorationParams, anchor_pose: np.ndarray, *,
                 slam: TeamSlam | None = None, planner: Planner | None = None,
                 controller: ApfController | None = None,
                 progress_monitor: ProgressMonitor | None = None,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        """Each collaborator left out is built from ``params`` (what every run uses).

        Args:
            robot_id: this robot's id (0-based).
            params: all parameters.
            anchor_pose: robot 0's launch pose in the map frame (x [m], y [m], theta [rad]),
                which anchors the default ``slam``.
            slam: the team's factor graph as this robot holds it (keyframes of every robot,
                estimates, marginals); default ``TeamSlam`` anchored at ``anchor_pose``.
            planner: chooses the next target among the candidates; default
                ``make_planner(params)`` (``planner.name``). Should it fail numerically, the
                nearest frontier is taken for that decision.
            controller: drives toward a goal around the estimated landmarks and tells when
                a position is reached; default ``ApfController`` (``motion.*``).
            progress_monitor: judges each step of the approach to the current target
                (blocked, no progress); default ``ProgressMonitor(params.progress)``.
            clock: wall clock [s] timing each decision (``DecisionRecord.planning_time_s``);
                default ``time.perf_counter``.
        """
        self.robot_id = robot_id
        self.params = params
        self.num_robots = params.world.num_robots
        self.slam = slam if slam is not None else TeamSlam(
            robot_id, self.num_robots, params.slam, np.asarray(anchor_pose),
            landmark_ids=params.sensors.landmark_ids)
        self.grid = OccupancyGrid(params.world.width_m, params.world.height_m, params.map,
                                  params.sensors.sonar_max_range_m)
        self.planner = planner if planner is not None else make_planner(params)
        self._fallback_planner = make_planner(params, "NEAREST")
        self.controller = controller if controller is not None else ApfController(
            params.motion, params.world.landmark_radius_m, params.world.robot_radius_m)
        self._clock = clock
        self.rendezvous = RendezvousBook()
        self.outbox = TeamUpdateOutbox(robot_id)
        self.wire = TeamWireFormat(params)
        self.decisions: list[DecisionRecord] = []
        self.target: Frontier | None = None
        self.finished = False
        self.explored_ratio = 0.0
        self.last_candidates: list[Frontier] = []
        #: The planner's latest decision with every candidate's utility terms (diagnostics).
        self.last_decision: Decision | None = None
        self.team_targets: dict[int, list[TargetRecord]] = {r: [] for r in range(self.num_robots)}
        self._keyframes = KeyframeBuilder(robot_id, params.slam,
                                          keep_unidentified=not params.sensors.landmark_ids)
        #: Without landmark identities, this robot's own data association (else None).
        self.own_landmarks = (None if params.sensors.landmark_ids
                              else OwnLandmarks(self.slam, params.sensors))
        self._dead_reckoning = DeadReckoningDifferencer()
        self._since_keyframe = np.zeros(3)
        self._pending = _Pending()
        self._target_deadline_s = np.inf
        self._stamp_s = 0.0
        self._arrivals_sent: set[tuple[int, int]] = set()
        self.finished_teammates: set[int] = set()
        self._last_heard_s: dict[int, float] = {}
        self.meeting_effects: list[MeetingEffect] = []
        self._watched_meeting: Meeting | None = None
        self._gap_covariance: np.ndarray | None = None
        #: Consecutive steps without an estimate of its own pose (``current_pose`` None):
        #: a robot's stream is tied to the map by robot 0's start pose, or for another robot
        #: by a teammate's reading of it, which the graph may not (or no longer) hold.
        self.steps_unanchored = 0
        self.given_up: list[GivenUpTarget] = []
        self.blocked_s = 0.0
        self.blacklist = TargetBlacklist(params.progress)
        self._progress = (progress_monitor if progress_monitor is not None
                          else ProgressMonitor(params.progress))
        self._recovery: RecoveryTurn | None = None
        self._commanded_forward_m = 0.0

    # -- inputs --------------------------------------------------------------------------

    def apply_team_updates(self, updates: list[TeamUpdate]) -> None:
        """Apply teammates' updates (already validated and in sequence order)."""
        for update in updates:
            self._last_heard_s[update.robot_id] = max(update.stamp_s,
                                                      self._last_heard_s.get(update.robot_id,
                                                                             -np.inf))
            if update.finished and update.robot_id not in self.finished_teammates:
                self.finished_teammates.add(update.robot_id)
                self._end_meetings_with(update.robot_id, "finished")
            for keyframe in update.keyframes:
                self.slam.add_keyframe(keyframe)
            for target in update.targets:
                self.team_targets[target.robot_id].append(target)
            for event in update.rendezvous:
                self._apply_rendezvous_event(event)
        if updates:
            self._update_slam()

    def resume(self, history: list[TeamUpdate], through_sequence: int = 0,
               first_step: int = 0, team_records: Sequence[TeamUpdate] = ()) -> None:
        """Take back this robot's own earlier stream after its process restarted.

        ``history``: its records from sequence 1 on, as its teammates hold them;
        ``through_sequence``: the last sequence number its earlier process used (the
        world's barrier entry), if more than the history holds; ``first_step``: the first
        step this process processes. The own keyframes go back into the graph, the targets
        into the decision list, rendezvous events into the bookkeeping, and numbering
        continues after ``through_sequence`` (``TeamUpdateOutbox.restore``).
        ``team_records``: the teammates' records the earlier process applied, in the order it
        applied them (its team journal). Both are replayed in the order and groups of the
        earlier process (``_replay_order``): one SLAM update per step that had a keyframe or
        teammates' records, so that iSAM2 takes the same updates from the same linearization
        points and the rebuilt estimate is the uninterrupted one. The next
        odometry reading is linked to the last keyframe: the dead-reckoning pose there is
        the composition of the keyframe deltas (the stream started at the odometry origin,
        step 0, as every lockstep robot's does), so the reading measures all the motion
        since, which nobody recorded, and gets the covariance of that many steps at full
        speed: ``keyframe_interval_steps`` when the history is complete (the vehicle moved
        for less than one interval before it stopped), every step from the last keyframe
        to ``first_step`` when records are missing.

        When no record came back (its earlier process sent some, or died before the world
        counted any), the stream is continued from its first keyframe (step 0, at the
        odometry origin): record 1 is rebuilt with that keyframe without its readings (a
        teammate that holds the real one keeps it; the teammates' readings of it anchor it),
        and the next reading bridges every step since. (A new first keyframe would instead
        restart the stream mid-run: robot 0's is anchored at the mission's start pose, so a
        teammate's graph and its own were pulled to where the vehicle was at step 0 and
        diverged; another robot's is anchored only by a teammate's reading at the same
        keyframe, which may never come, and the robot stood still for the rest of the run.)
        """
        rebuilt = not history and (through_sequence > 0 or first_step > 0)
        if rebuilt:
            history = [self._stream_start()]
        self.outbox.restore(history, through_sequence)
        odom_pose, last_keyframe = np.zeros(3), None
        for own, records in self._replay_order(history, team_records):
            if not own:
                self.apply_team_updates(records)
                continue
            update = records[0]
            for keyframe in update.keyframes:
                self.slam.add_keyframe(keyframe)
                if not keyframe.is_first:
                    odom_pose = compose(odom_pose, keyframe.odom_delta)
                last_keyframe = keyframe
            if update.keyframes:
                self._update_slam()
            for target in update.targets:
                self.team_targets[self.robot_id].append(target)
                partner = None if target.partner_id == self.robot_id else target.partner_id
                self.decisions.append(DecisionRecord(
                    target.decision_index, target.stamp_s,
                    Frontier(target.position.copy(), target.kind, partner),
                    target.planning_time_s, 0, float("nan"), target.planner_failed))
            for event in update.rendezvous:
                self._apply_rendezvous_event(event)
        self.finished = any(update.finished for update in history)
        if last_keyframe is None:
            return
        self._restore_target()
        self._keyframes.resume(last_keyframe.index)
        self._dead_reckoning.resume(odom_pose)
        interval = self.params.slam.keyframe_interval_steps
        complete = len(history) >= through_sequence and not rebuilt
        moving_steps = interval if complete else max(
            first_step - last_keyframe.index * interval, interval)
        self._gap_covariance = self._moving_step_covariance() * moving_steps

    def _restore_target(self) -> None:
        """Drive on to the last target the earlier process chose (its last decision: a target
        reached or given up is followed by a new decision at the same step), with its
        deadline as set then from the estimated pose at the decision's keyframe; the
        progress window starts anew."""
        if self.finished or not self.decisions:
            return
        decision = self.decisions[-1]
        self.target = decision.target
        self._progress.restart()
        motion = self.params.motion
        indices, poses = self.slam.trajectory(self.robot_id)
        step = round(decision.stamp_s / motion.time_step_s)
        at_decision = indices <= step // self.params.slam.keyframe_interval_steps
        if not at_decision.any():
            return
        distance = float(np.linalg.norm(decision.target.position
                                        - poses[at_decision][-1][:2]))
        self._target_deadline_s = (decision.stamp_s + motion.target_timeout_factor * distance
                                   / motion.speed_mps + motion.target_timeout_margin_s)

    def _replay_order(self, history: Sequence[TeamUpdate], team_records: Sequence[TeamUpdate]
                      ) -> list[tuple[bool, list[TeamUpdate]]]:
        """The own records (True, [record]) and groups of teammates' records (False, records)
        in the order the earlier process handled them: at each step, the teammates' records
        it applied (one group), then its own record of the step. A teammate's record made at
        step s was applied at step s + 1 (the lockstep links' delivery; later if it came
        later in the journal's order)."""
        time_step = self.params.motion.time_step_s
        events: list[tuple[int, int, int, bool, list[TeamUpdate]]] = [
            (round(update.stamp_s / time_step), 1, order, True, [update])
            for order, update in enumerate(history)]
        groups: dict[int, list[TeamUpdate]] = {}
        applied_at = 0
        for update in team_records:
            applied_at = max(round(update.stamp_s / time_step) + 1, applied_at)
            groups.setdefault(applied_at, []).append(update)
        events += [(step, 0, 0, False, records) for step, records in groups.items()]
        events.sort(key=lambda event: event[:3])
        return [(own, records) for _, _, _, own, records in events]

    def skip_steps(self) -> None:
        """The steps between the last one processed and the next are skipped: the world went
        on without this robot (it stopped waiting for its answers), and their sensor data is
        lost or stale. The world holds an unanswered robot's vehicle still, so the next
        odometry reading (the dead reckoning is a running pose) measures at most one step of
        motion, the last command's, while its own increment covariance is that of a still
        vehicle (zero): that one moving step's covariance is added to it."""
        step_covariance = self._moving_step_covariance()
        self._gap_covariance = (step_covariance if self._gap_covariance is None
                                else self._gap_covariance + step_covariance)

    def _moving_step_covariance(self) -> np.ndarray:
        """Odometry covariance of one step at full speed, turning ([m^2], [rad^2])."""
        motion = self.params.motion
        return odometry_covariance_per_step(motion.speed_mps * motion.time_step_s, True,
                                            self.params.sensors)

    def _stream_start(self) -> TeamUpdate:
        """Record 1 of this robot's stream as far as it can be rebuilt (``resume``): its first
        keyframe (step 0, at the odometry origin) without its readings."""
        return TeamUpdate(self.robot_id, 1, 0.0, keyframes=(KeyframeMeasurements(
            robot_id=self.robot_id, index=0, stamp_s=0.0, is_first=True, previous_index=-1,
            odom_delta=np.zeros(3), odom_covariance=np.zeros((3, 3)), landmarks=(),
            teammates=()),))

    def step(self, sensed: StepInput) -> MotionCommand:
        """Process one step of own sensor data; returns the motion for the next step."""
        self._stamp_s = sensed.stamp_s
        increment = self._dead_reckoning.increment(sensed.odom_pose)
        odometry_forward_m = 0.0 if increment is None else float(np.hypot(*increment[:2]))
        if increment is not None and blocked_step(self._commanded_forward_m, odometry_forward_m):
            self.blocked_s += self.params.motion.time_step_s
        covariance = np.asarray(sensed.odom_increment_covariance, dtype=float)
        if increment is not None and self._gap_covariance is not None:
            covariance, self._gap_covariance = covariance + self._gap_covariance, None
        odometry = None if increment is None else OdometryReading(increment, covariance)
        if odometry is not None:
            self._since_keyframe = compose(self._since_keyframe, odometry.delta)
        keyframe = self._keyframes.add_step(sensed.step, sensed.stamp_s, odometry,
                                            sensed.landmarks, sensed.teammates)
        if keyframe is not None:
            if self.own_landmarks is not None:
                keyframe = self.own_landmarks.associate(keyframe)
            keyframe = self.wire.keyframe(keyframe)  # what the teammates will receive
            self._since_keyframe = np.zeros(3)
            self.slam.add_keyframe(keyframe)
            self._update_slam()
            self._pending.keyframes.append(keyframe)
        pose = self.current_pose()
        self.steps_unanchored = self.steps_unanchored + 1 if pose is None else 0
        if pose is None or self.finished:
            return self._command(0.0, 0.0)
        self._handle_rendezvous(pose)
        meeting_point = self.rendezvous.is_waiting(self.robot_id)
        if meeting_point is not None:
            self._progress.restart()  # the approach to the target starts anew afterwards
            if self.controller.reached(pose, meeting_point):
                return self._command(0.0, 0.0)
            goal = meeting_point
        else:
            goal = self._goal(pose, odometry_forward_m)
        motion = self.params.motion
        if self._recovery is not None:
            return self._command(motion.max_turn_per_step_rad, 0.0)
        if goal is None:
            return self._command(0.0, 0.0)
        landmarks = np.array(list(self.slam.landmark_estimates().values())).reshape(-1, 2)
        turn = self.controller.command(pose, goal, landmarks)
        return self._command(float(turn), motion.speed_mps * motion.time_step_s)

    def _command(self, turn_rad: float, forward_m: float) -> MotionCommand:
        """The motion for the next step, remembered to judge the next odometry reading."""
        self._commanded_forward_m = forward_m
        return MotionCommand(turn_rad, forward_m, self.finished)

    # -- outputs -------------------------------------------------------------------------

    def take_outgoing(self) -> TeamUpdate | None:
        """The update to send to the teammates now, or None when nothing is new."""
        pending, self._pending = self._pending, _Pending()
        if not (pending.keyframes or pending.targets or pending.rendezvous or pending.finished):
            return None
        return self.outbox.publish(self._stamp_s, tuple(pending.keyframes),
                                   tuple(pending.targets), tuple(pending.rendezvous),
                                   self.finished)

    def current_pose(self) -> np.ndarray | None:
        """Estimated current pose in the map frame, None until this robot is anchored."""
        latest = self.slam.latest_index(self.robot_id)
        if latest is None:
            return None
        return compose(self.slam.pose(self.robot_id, latest), self._since_keyframe)

    def teammate_states(self) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
        """``{teammate: (latest estimated position (2,), current target (2,) or None)}``."""
        states = {}
        for robot in range(self.num_robots):
            latest = self.slam.latest_index(robot)
            if robot == self.robot_id or latest is None:
                continue
            history = self.team_targets[robot]
            target = history[-1].position if history else None
            states[robot] = (self.slam.pose(robot, latest)[:2], target)
        return states

    def is_lost(self, teammate: int) -> bool:
        """True when the teammate's latest update is older than
        ``frontiers.teammate_silent_after_s`` (never heard: not lost, it has no pose)."""
        heard = self._last_heard_s.get(teammate)
        return (heard is not None
                and self._stamp_s - heard > self.params.frontiers.teammate_silent_after_s)

    def rendezvous_partners(self) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
        """``teammate_states`` of the teammates that can still meet: every teammate that has
        not finished. A teammate out of contact (``is_lost``) stays one, at its last known
        target: going there is how the link comes back (range-limited links)."""
        return {robot: state for robot, state in self.teammate_states().items()
                if robot not in self.finished_teammates}

    # -- decisions -----------------------------------------------------------------------

    def _goal(self, pose: np.ndarray, odometry_forward_m: float) -> np.ndarray | None:
        """The position to drive to; judges progress and decides a new target when needed.

        None while a recovery turn is under way or when there is nothing left to do.
        ``odometry_forward_m``: translation [m] the odometry measured over the last step.
        """
        if self._recovery is not None:
            if not self._recovery.done(pose[2]):
                return None
            self._recovery = None
        reached = self.target is not None and self.controller.reached(pose, self.target.position)
        if self.target is not None and not reached:
            distance = float(np.linalg.norm(self.target.position - pose[:2]))
            verdict = self._progress.update(self._stamp_s, distance, self._commanded_forward_m,
                                            odometry_forward_m)
            if self._stamp_s > self._target_deadline_s:
                verdict = GiveUpReason.DEADLINE
            if verdict is not None:
                self._give_up(verdict)
                if self._progress.blocked_now:
                    self._recovery = RecoveryTurn(pose[2])
                    return None
        if self.target is None or reached:
            self._decide(pose)
        return None if self.target is None else self.target.position

    def _give_up(self, reason: GiveUpReason) -> None:
        """Drop the current target and exclude candidates near it for a while.

        The blacklist stays with this robot: whether a target can be reached depends on
        this robot's own localization error and where it drives from, so a teammate may
        well reach it. Teammates still see the target in this robot's target history
        (task allocation keeps them away from it as from any other target of this robot).
        """
        given_up = GivenUpTarget(self.target.position.copy(), self._stamp_s, reason)
        progress = self.params.progress
        _LOG.info("robot %d: gave up target %s (%s); no target within %.1f m of it for %.0f s",
                  self.robot_id, given_up.position.tolist(), reason.value,
                  progress.blacklist_radius_m, progress.blacklist_duration_s)
        self.given_up.append(given_up)
        self.blacklist.add(given_up)
        self.target = None
        self._target_deadline_s = np.inf

    def _decide(self, pose: np.ndarray) -> None:
        """Rebuild the map from the SLAM estimate and choose the next target."""
        started = self._clock()
        trajectories = [self.slam.trajectory(robot)[1] for robot in range(self.num_robots)]
        landmark_positions = self.slam.landmark_estimates()
        landmarks = np.array(list(landmark_positions.values())).reshape(-1, 2)
        self.grid.rebuild(np.concatenate(trajectories), landmarks)
        self.explored_ratio = self.grid.explored_ratio()
        if self.explored_ratio >= self.params.run.until_explored:
            self._finish("explored ratio %.3f reached" % self.explored_ratio)
            return
        cells = frontier_cells(self.grid, self.params.frontiers)
        candidates = candidate_targets(cells, self.robot_id, pose[:2], self.explored_ratio,
                                       landmarks, self.rendezvous_partners(),
                                       self.params.frontiers)
        if not candidates:
            self.last_candidates = []
            self._finish("no frontier left")
            return
        candidates = self.blacklist.allowed(candidates, self._stamp_s)
        self.last_candidates = candidates
        if not candidates:
            self._fall_back(cells, pose, started)
            return
        context = PlanningContext(
            robot_id=self.robot_id, slam=self.slam, grid=self.grid, candidates=candidates,
            robot_pose=pose, teammates=self.teammate_states(),
            target_history={robot: [t.position for t in records]
                            for robot, records in self.team_targets.items()},
            explored_ratio=self.explored_ratio)
        planner_failed = False
        try:
            decision = self.planner.choose(context)
        except (RuntimeError, np.linalg.LinAlgError) as error:  # numerical failure in GTSAM
            _LOG.error("robot %d: planner %s failed (%s); nearest frontier this time",
                       self.robot_id, self.planner.name, str(error).splitlines()[0][:120])
            decision = self._fallback_planner.choose(context)
            planner_failed = True
        self.last_decision = decision
        planning_time_s = self._clock() - started
        self._set_target(decision.target, pose, planning_time_s, len(candidates), planner_failed)

    def _fall_back(self, cells: np.ndarray, pose: np.ndarray, started: float) -> None:
        """Every candidate lies near a given-up target: the nearest frontier cell that does
        not, or finish when there is none."""
        open_cells = cells[~self.blacklist.excludes(cells, self._stamp_s)]
        if len(open_cells) == 0:
            self._finish("no reachable frontier")
            return
        target = exploration_frontiers(open_cells, pose[:2], self.explored_ratio,
                                       self.params.frontiers)[0]  # the nearest comes first
        _LOG.info("robot %d: every candidate is near a given-up target; nearest other "
                  "frontier %s", self.robot_id, target.position.tolist())
        self._set_target(target, pose, self._clock() - started, 1, planner_failed=False)

    def _set_target(self, target: Frontier, pose: np.ndarray, planning_time_s: float,
                    num_candidates: int, planner_failed: bool) -> None:
        self._give_up_own_meeting("new target chosen")
        index = len(self.decisions)
        self.target = target
        self._progress.restart()
        self.decisions.append(DecisionRecord(index, self._stamp_s, target, planning_time_s,
                                             num_candidates, self.explored_ratio,
                                             planner_failed))
        distance = float(np.linalg.norm(target.position - pose[:2]))
        motion = self.params.motion
        self._target_deadline_s = (self._stamp_s + motion.target_timeout_factor * distance
                                   / motion.speed_mps + motion.target_timeout_margin_s)
        partner = target.partner_id if target.kind == FrontierType.RENDEZVOUS else None
        record = self.wire.target(TargetRecord(self.robot_id, index, self._stamp_s,
                                               target.position.copy(), target.kind, partner,
                                               planning_time_s, planner_failed))
        self.team_targets[self.robot_id].append(record)
        self._pending.targets.append(record)
        if partner is not None:
            frontiers = self.params.frontiers
            timeout_s = meeting_timeout_s(distance, motion.speed_mps,
                                          frontiers.rendezvous_timeout_factor,
                                          frontiers.rendezvous_timeout_margin_s)
            meeting = self.rendezvous.request(self.robot_id, partner, target.position,
                                              self._stamp_s, timeout_s, index)
            self._send_rendezvous(RendezvousState.REQUEST, meeting)
            self._watched_meeting = meeting

    def _finish(self, reason: str) -> None:
        if not self.finished:
            _LOG.info("robot %d finished: %s", self.robot_id, reason)
            self._pending.finished = True
        self.finished = True
        self.target = None
        for meeting in self.rendezvous.release(self.robot_id):
            self._send_rendezvous(RendezvousState.RELEASE, meeting)

    # -- rendezvous ----------------------------------------------------------------------

    def _handle_rendezvous(self, pose: np.ndarray) -> None:
        """Report own arrivals at meeting points; end meetings past their deadline (the
        requester sends RELEASE) and stop waiting for a requester out of contact (a
        requester keeps going to a silent partner until its wait limit: meeting restores
        the link)."""
        for meeting in self.rendezvous.expire(self._stamp_s):
            if meeting.requester_id == self.robot_id:
                _LOG.info("robot %d: rendezvous %d with robot %d timed out", self.robot_id,
                          meeting.rendezvous_id, meeting.partner_id)
                self._send_rendezvous(RendezvousState.RELEASE, meeting)
                self._drop_meeting_target(meeting)
        for meeting in self.rendezvous.open_meetings():
            if meeting.partner_id == self.robot_id and self.is_lost(meeting.requester_id):
                _LOG.info("robot %d: rendezvous %d of robot %d ended, robot %d out of contact",
                          self.robot_id, meeting.rendezvous_id, meeting.requester_id,
                          meeting.requester_id)
                self.rendezvous.release_meeting(meeting.requester_id, meeting.rendezvous_id)
                self._send_rendezvous(RendezvousState.RELEASE, meeting)
        for meeting in self.rendezvous.open_meetings():
            involved = self.robot_id in (meeting.requester_id, meeting.partner_id)
            announced = (meeting.requester_id, meeting.rendezvous_id) in self._arrivals_sent
            if involved and not announced and self.controller.reached(pose, meeting.meeting_point):
                self._arrivals_sent.add((meeting.requester_id, meeting.rendezvous_id))
                self._send_rendezvous(RendezvousState.ARRIVED, meeting)
                self.rendezvous.arrived(self.robot_id, self._stamp_s, meeting.requester_id)

    def _end_meetings_with(self, teammate: int, why: str) -> None:
        """End this robot's meetings with a finished or lost teammate: RELEASE each, and
        give up a rendezvous target with it (a new target is chosen at the next step)."""
        for meeting in self.rendezvous.release(teammate):
            if self.robot_id not in (meeting.requester_id, meeting.partner_id):
                continue
            _LOG.info("robot %d: rendezvous %d of robot %d ended, robot %d %s", self.robot_id,
                      meeting.rendezvous_id, meeting.requester_id, teammate, why)
            self._send_rendezvous(RendezvousState.RELEASE, meeting)
            self._drop_meeting_target(meeting)

    def _give_up_own_meeting(self, why: str) -> None:
        """RELEASE the open meeting this robot requested, if any (plans changed)."""
        meeting = self.rendezvous.meeting_of(self.robot_id)
        self._watched_meeting = None
        if meeting is None:
            return
        _LOG.info("robot %d: gives up rendezvous %d with robot %d (%s)", self.robot_id,
                  meeting.rendezvous_id, meeting.partner_id, why)
        self.rendezvous.release_meeting(self.robot_id, meeting.rendezvous_id)
        self._send_rendezvous(RendezvousState.RELEASE, meeting)

    def _drop_meeting_target(self, meeting: Meeting) -> None:
        """Forget the current target when it is this ended meeting's point (requester)."""
        if (meeting.requester_id == self.robot_id and self.target is not None
                and self.target.kind == FrontierType.RENDEZVOUS
                and self.target.partner_id == meeting.partner_id):
            self.target = None
            self._watched_meeting = None

    def _apply_rendezvous_event(self, event: RendezvousEvent) -> None:
        if event.state == RendezvousState.REQUEST:
            meeting = self.rendezvous.request(event.requester_id, event.partner_id,
                                              event.meeting_point, event.stamp_s,
                                              event.timeout_s, event.rendezvous_id)
            if self.finished and event.partner_id == self.robot_id:
                self.rendezvous.release_meeting(event.requester_id, event.rendezvous_id)
                self._send_rendezvous(RendezvousState.RELEASE, meeting)
        elif event.state == RendezvousState.ARRIVED:
            self.rendezvous.arrived(event.sender_id, event.stamp_s, event.requester_id)
        else:
            for meeting in self.rendezvous.release_meeting(event.requester_id,
                                                           event.rendezvous_id):
                self._drop_meeting_target(meeting)

    def _send_rendezvous(self, state: RendezvousState, meeting: Meeting) -> None:
        self._pending.rendezvous.append(RendezvousEvent(
            meeting.rendezvous_id, meeting.requester_id, meeting.partner_id, self.robot_id,
            state, self._stamp_s, np.asarray(meeting.meeting_point, dtype=float).copy(),
            meeting.deadline_s - meeting.requested_at_s))

    # -- SLAM ----------------------------------------------------------------------------

    def _update_slam(self) -> None:
        """Update SLAM; while a meeting this robot requested is watched, record the first
        inter-robot factor with the partner (``MeetingEffect``)."""
        meeting = self._watched_meeting
        if meeting is None:
            self.slam.update()
            self._match_teammates_landmarks()
            return
        factors_before = self.slam.inter_robot_factors(self.robot_id, meeting.partner_id)
        trace_before = self._latest_pose_trace()
        self.slam.update()
        if self.slam.inter_robot_factors(self.robot_id, meeting.partner_id) > factors_before:
            self.meeting_effects.append(MeetingEffect(
                meeting.rendezvous_id, meeting.partner_id, meeting.requested_at_s,
                self._stamp_s, trace_before, self._latest_pose_trace()))
            self._watched_meeting = None
        self._match_teammates_landmarks()

    def _match_teammates_landmarks(self) -> None:
        """Without landmark identities: tie the teammates' landmarks that are this robot's
        own in the graph (``OwnLandmarks.match_teammates``)."""
        if self.own_landmarks is not None:
            self.own_landmarks.match_teammates()

    def _latest_pose_trace(self) -> float:
        """Trace of the marginal covariance of this robot's latest keyframe pose."""
        latest = self.slam.latest_index(self.robot_id)
        if latest is None:
            return float("nan")
        return float(np.trace(self.slam.pose_covariance(self.robot_id, latest)))
