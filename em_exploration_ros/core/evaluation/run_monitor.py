"""The run monitor: one stop rule and one run summary for em-sim, the benchmark and em-evaluator.

Whoever watches a run (``core.sessions.team_runner.TeamRunner`` in process, the
``em-evaluator`` node over ROS) evaluates the team metrics at some steps and hands each
evaluation to ``RunMonitor.observe``, which keeps the history and applies the stop rule:

- the team explored ratio reached ``run.until_explored``;
- the team's true distance reached ``run.max_distance_m``;
- every robot reported that it finished: in em-evaluator, every robot that is not lost
  (``every_live_robot_finished``; em-sim loses no robot). When robots were lost without
  having finished, the stop reason starts with ``ROBOTS_LOST_PREFIX`` and names them, and the
  programs exit with ``EXIT_ROBOTS_LOST``: the run ended below ``run.until_explored`` (that
  rule comes first) with part of the team gone, which must not pass for success;
- the run's final step (``final_step``: ``run.max_steps`` or an earlier simulation-time
  limit) was evaluated;
- the run stalled: for ``run.stall_timeout_s`` of simulation time the team neither
  travelled (true team distance) nor explored new area (team explored ratio)
  (``StallWatch``); the stop reason starts with ``STALLED_PREFIX`` and the programs exit
  with ``EXIT_STALLED`` instead of idling to the step limit.

Once a rule fired the monitor is closed: later evaluations are ignored, and the summary
(``RunMonitor.summary``) reports the values of the step at which the rule fired (metrics,
per-robot distances, and the decisions made before that step), whatever the world did
afterwards. A run that ends without a rule (Ctrl-C, a silent world) is summarized at its
last evaluation.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from em_exploration_ros.core.evaluation.evaluator import TeamMetrics, stamp_key
from em_exploration_ros.core.evaluation.rendezvous_stats import count_rendezvous
from em_exploration_ros.core.evaluation.summary import (GivenUpEntry, HistorySample, MeetingEntry,
                                                        RobotSummary, RunSummary, TargetEntry)
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import FrontierType, RendezvousEvent

#: Team metrics are evaluated every this many steps (and at the end) in em-sim; the link
#: relay delivers before those steps so that they see what the links carried.
METRICS_INTERVAL_STEPS = 10

#: Exit status of em-sim, em-evaluator and run_team.sh for a stalled run.
EXIT_STALLED = 4
#: Stop reasons of stalled runs start with this.
STALLED_PREFIX = "stalled: "
#: Exit status of em-evaluator and run_team.sh for a run that ended below its explored goal
#: because every live robot finished while other robots were lost (never in em-sim).
EXIT_ROBOTS_LOST = 5
#: Stop reasons of runs whose live robots all finished while others were lost start with this.
ROBOTS_LOST_PREFIX = "every live robot finished; "
#: The team distance must grow by more than this to count as travel [m] (far below the
#: 0.2 m of one step, far above round-off).
_MIN_TRAVEL_M = 0.01


def final_step(params: ExplorationParams, max_sim_time_s: float = 0.0) -> int:
    """Index of the last step of a run: ``run.max_steps``, or earlier when
    ``max_sim_time_s`` > 0 [s] ends it first (the last step with time <= the limit)."""
    last = params.run.max_steps
    if max_sim_time_s > 0.0:
        last = min(last, int(math.floor(max_sim_time_s / params.motion.time_step_s + 1e-9)))
    return last


def frontier_type_name(kind: FrontierType) -> str:
    """The summary's name of a frontier type: exploration / revisiting / rendezvous."""
    return FrontierType(kind).name.lower()


@dataclass(frozen=True)
class DecisionEntry:
    """One decision of a robot as the monitor sees it.

    ``stamp_s`` [s] is the simulation time at which it was made, ``position`` the target
    (x, y) [m] in the map frame, ``kind`` its frontier type, ``planning_time_s`` the
    wall time [s] the robot spent deciding and ``planner_failed`` whether the planner
    failed and the nearest frontier rule chose.
    """

    stamp_s: float
    position: tuple[float, float]
    kind: FrontierType
    planning_time_s: float
    planner_failed: bool = False

    def target_entry(self) -> TargetEntry:
        """The summary's entry of this decision's target."""
        return TargetEntry(float(self.position[0]), float(self.position[1]),
                           frontier_type_name(self.kind))


@dataclass(frozen=True)
class RobotProgressRecord:
    """What a robot knows of its own progress (em-sim reads it from the agents): the
    targets it gave up, the time [s] its odometry showed it blocked and, when known, how
    many of its SLAM updates were re-solved in batch (``TeamSlam.recoveries``)."""

    given_up: tuple[GivenUpEntry, ...]
    blocked_s: float
    slam_recoveries: int | None = None


@dataclass(frozen=True)
class TeamFinished:
    """Every robot that is not lost reported ``finished``: the latest ``step`` at which they
    answered, and the robots that were ``lost`` without having finished (by id)."""

    step: int
    lost: tuple[int, ...]


def every_live_robot_finished(finished_steps: Sequence[int | None],
                              lost: Sequence[bool]) -> TeamFinished | None:
    """Whether the "every robot finished" rule applies to a team some of whose robots may be
    lost: every robot that is not lost reported ``finished`` (at least one is not lost).

    Args: per robot (by id) the step of its latest answer if that answer reported
    ``finished``, else None; per robot whether the watcher counts it lost. A lost robot that
    had finished before it was lost did its part and is not listed as lost. Returns None
    while the rule does not apply.
    """
    robots = list(zip(finished_steps, lost, strict=True))
    live = [step for step, gone in robots if not gone]
    if not live or None in live:
        return None
    return TeamFinished(max(live), tuple(robot for robot, (step, gone) in enumerate(robots)
                                         if gone and step is None))


class StallWatch:
    """The stall rule: no team travel and no newly explored area for ``timeout_s``."""

    def __init__(self, timeout_s: float) -> None:
        """Args: time without progress that ends a run [s sim time]; 0 disables the rule."""
        self.timeout_s = float(timeout_s)
        self._since_s: float | None = None
        self._distance_m = 0.0
        self._explored_ratio = 0.0

    def update(self, metrics: TeamMetrics) -> str:
        """The stop reason ("stalled: ...") when the team made no progress for the timeout
        up to these metrics, else ""."""
        if (self._since_s is None or metrics.distance_m > self._distance_m + _MIN_TRAVEL_M
                or metrics.explored_ratio > self._explored_ratio):
            self._since_s = metrics.stamp_s
            self._distance_m, self._explored_ratio = metrics.distance_m, metrics.explored_ratio
            return ""
        idle_s = metrics.stamp_s - self._since_s
        if self.timeout_s <= 0.0 or idle_s < self.timeout_s:
            return ""
        return (f"{STALLED_PREFIX}no distance and no newly explored area for {idle_s:.0f} s "
                f"(distance {self._distance_m:.1f} m, explored {self._explored_ratio:.3f})")


class RunMonitor:
    """Stop rule, history and summary of one run (see module docstring)."""

    def __init__(self, params: ExplorationParams, max_sim_time_s: float = 0.0) -> None:
        """Args: the run's parameters; an optional simulation-time limit [s] (0: none)."""
        self.params = params
        self.final_step = final_step(params, max_sim_time_s)
        self.history: list[TeamMetrics] = []
        self.stop_reason = ""
        self._stop_metrics: TeamMetrics | None = None
        self._stall = StallWatch(params.run.stall_timeout_s)

    @property
    def stopped(self) -> bool:
        """Whether a stop rule fired."""
        return self._stop_metrics is not None

    @property
    def stalled(self) -> bool:
        """Whether the run ended by the stall rule."""
        return self.stop_reason.startswith(STALLED_PREFIX)

    @property
    def exit_code(self) -> int:
        """Exit status of a run a stop rule ended: ``EXIT_STALLED`` when it stalled,
        ``EXIT_ROBOTS_LOST`` when every live robot finished while others were lost, else 0.
        (A run ended without a rule, interrupted or silent, has its watcher's own code.)"""
        if self.stalled:
            return EXIT_STALLED
        if self.stop_reason.startswith(ROBOTS_LOST_PREFIX):
            return EXIT_ROBOTS_LOST
        return 0

    @property
    def final_metrics(self) -> TeamMetrics | None:
        """Metrics at the step where the stop rule fired, else the last evaluation."""
        if self._stop_metrics is not None:
            return self._stop_metrics
        return self.history[-1] if self.history else None

    def observe(self, step: int, metrics: TeamMetrics, all_finished: bool = False,
                lost: Sequence[int] = ()) -> str:
        """Record the metrics evaluated at ``step``; returns the stop reason ("" to go on).

        ``all_finished`` tells whether every robot had reported ``finished`` by that step,
        but for the robots ``lost`` (by id; ``every_live_robot_finished``), which the stop
        reason then names. After a rule fired, further evaluations are ignored and the
        reason is returned again.
        """
        if self.stopped:
            return self.stop_reason
        self.history.append(metrics)
        reason = self._stop_rule(step, metrics, all_finished, lost)
        if reason:
            self.stop_reason = reason
            self._stop_metrics = metrics
        return reason

    def observe_finished(self, step: int, lost: Sequence[int] = ()) -> str:
        """Every robot (but those ``lost``, as in ``observe``) had reported ``finished`` by
        ``step``, the step of the last evaluation, but that was learned only after the
        evaluation was observed (the robots' answers can arrive after the step's ground
        truth): the stop rule is applied to it again as ``observe`` would have, and its
        reason returned ("" if none fired)."""
        if self.stopped or not self.history:
            return self.stop_reason
        reason = self._stop_rule(step, self.history[-1], True, lost)
        if reason:
            self.stop_reason = reason
            self._stop_metrics = self.history[-1]
        return reason

    def record(self, metrics: TeamMetrics) -> None:
        """Keep an evaluation made after the run ended without a stop rule (the last steps
        recorded before Ctrl-C or silence); no rule is applied. Ignored after a rule fired."""
        if not self.stopped:
            self.history.append(metrics)

    def end(self, reason: str) -> None:
        """End the run without a stop rule (interrupted, world silent); keeps a fired rule."""
        if not self.stop_reason:
            self.stop_reason = reason

    def _stop_rule(self, step: int, metrics: TeamMetrics, all_finished: bool,
                   lost: Sequence[int]) -> str:
        run = self.params.run
        if metrics.explored_ratio >= run.until_explored:
            return f"explored ratio {metrics.explored_ratio:.3f} >= {run.until_explored}"
        if metrics.distance_m >= run.max_distance_m:
            return f"distance {metrics.distance_m:.0f} m >= {run.max_distance_m:.0f} m"
        if all_finished:
            return (f"{ROBOTS_LOST_PREFIX}robots {sorted(lost)} lost" if lost
                    else "every robot finished")
        if step >= self.final_step:
            return f"final step {self.final_step} (t = {metrics.stamp_s:g} s) reached"
        return self._stall.update(metrics)

    def decisions_counted(self, decisions: Sequence[DecisionEntry],
                          until: TeamMetrics | None = None) -> list[DecisionEntry]:
        """The decisions made before the evaluation ``until`` (default: the final one); all
        of them when nothing was evaluated. Decisions are stamped at the step they were made;
        an evaluation at step k counts those of steps < k."""
        until = until or self.final_metrics
        if until is None:
            return list(decisions)
        limit = stamp_key(until.stamp_s)
        return [d for d in decisions if stamp_key(d.stamp_s) < limit]

    def summary(self, decisions: Sequence[Sequence[DecisionEntry]], wall_s: float,
                progress: Sequence[RobotProgressRecord] | None = None,
                rendezvous_events: Sequence[RendezvousEvent] = (),
                meetings: Sequence[MeetingEntry] = ()) -> RunSummary:
        """The run's summary from each robot's decisions (in order, indexed by robot id),
        the wall time [s], the rendezvous events the robots sent and the meetings' effects
        on the requesters' uncertainty (when known); values at the final metrics (NaN where
        nothing was measured). Events and meetings count when stamped before the final
        evaluation, as decisions do. ``progress`` (indexed by robot id), when the watcher
        knows it, fills each robot's ``given_up`` (those stamped before the final evaluation,
        as decisions), ``blocked_s`` and ``slam_recoveries`` (else they stay null)."""
        world = self.params.world
        summary = RunSummary(seed=self.params.run.seed, planner=self.params.planner.name,
                             num_robots=world.num_robots,
                             map_size_m=(world.width_m, world.height_m),
                             cell_size_m=self.params.map.cell_size_m,
                             num_landmarks=world.num_landmarks, stop_reason=self.stop_reason,
                             wall_s=wall_s)
        final = self.final_metrics
        counted = [self.decisions_counted(robot_decisions) for robot_decisions in decisions]
        distances = (final.robot_distances_m if final is not None
                     else (0.0,) * len(counted))
        summary.robots = [RobotSummary(
            id=robot, distance_m=float(distances[robot]), decisions=len(chosen),
            targets=[d.target_entry() for d in chosen],
            decision_times_s=[d.planning_time_s for d in chosen])
            for robot, chosen in enumerate(counted)]
        end_s = math.inf if final is None else final.stamp_s
        for robot, record in zip(summary.robots, progress or ()):
            robot.given_up = [g for g in record.given_up if g.stamp_s < end_s]
            robot.blocked_s = record.blocked_s
            robot.slam_recoveries = record.slam_recoveries
        times = [d.planning_time_s for chosen in counted for d in chosen]
        summary.decisions = len(times)
        for chosen in counted:
            for decision in chosen:
                summary.decisions_by_type[frontier_type_name(decision.kind)] += 1
                summary.planner_failures += decision.planner_failed
        summary.rendezvous = count_rendezvous(rendezvous_events, end_s)
        summary.meetings = [m for m in meetings if m.stamp_s < end_s]
        if times:
            summary.decision_time_median_s = float(np.median(times))
            summary.decision_time_max_s = float(np.max(times))
        if final is not None:
            summary.explored_ratio, summary.distance_m = final.explored_ratio, final.distance_m
            summary.loc_rmse_m, summary.landmark_rmse_m = final.loc_rmse_m, final.landmark_rmse_m
            summary.sim_time_s = final.stamp_s
            summary.history = [HistorySample(m.stamp_s, m.distance_m, m.explored_ratio,
                                             m.loc_rmse_m, m.landmark_rmse_m,
                                             list(m.robot_pose_sigma_m))
                               for m in self.history if m.stamp_s <= final.stamp_s]
        return summary
