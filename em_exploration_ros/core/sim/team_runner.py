"""An N-robot exploration in one process: the engine of em-sim and of the benchmark.

The runner plays the roles of the ROS system without ROS: ``WorldSimulation`` is the
world node, one ``RobotAgent`` per robot is each robot process, and team updates travel
through one ``TeamUpdateInbox`` per robot. Message timing follows the lockstep protocol
of the ROS system: an update a robot publishes while processing step k is applied by
every teammate before it processes step k+1 (the world's barrier), and commands and
odometry go through the same wire conversions. A seeded em-sim run therefore chooses
the same targets as the ROS system in lockstep mode.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator, TeamMetrics
from em_exploration_ros.core.planning.frontiers import FrontierType
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.sim.simulation import SensorFrame, WorldSimulation
from em_exploration_ros.core.evaluation.summary import (HistorySample, RobotSummary, RunSummary,
                                             TargetEntry)
from em_exploration_ros.core.agent.team_data import TeamUpdateInbox
from em_exploration_ros.core.sim.wire_model import (command_to_twist, pose_through_wire,
                                                twist_to_increment_covariance)

#: Team metrics are evaluated every this many steps (and at the end).
METRICS_INTERVAL_STEPS = 10

FRONTIER_TYPE_NAMES = {FrontierType.EXPLORATION: "exploration",
                       FrontierType.REVISITING: "revisiting",
                       FrontierType.RENDEZVOUS: "rendezvous"}


def step_input(frame: SensorFrame, time_step_s: float) -> StepInput:
    """The robot-side view of a world sensor frame (same conversion as the ROS robot node)."""
    return StepInput(frame.step, frame.stamp_s, pose_through_wire(frame.odom_pose),
                     twist_to_increment_covariance(frame.twist_covariance, time_step_s),
                     frame.landmarks, frame.teammates)


@dataclass(frozen=True)
class Progress:
    """Reported to the progress callback after each metrics evaluation."""

    step: int
    metrics: TeamMetrics
    decisions: int


class TeamRunner:
    """Runs one seeded exploration; ``run()`` returns its ``RunSummary``."""

    def __init__(self, params: ExplorationParams) -> None:
        self.params = params
        self.simulation = WorldSimulation(params)
        world = self.simulation.world
        n = params.world.num_robots
        self.agents = [RobotAgent(i, params, world.start_poses[0]) for i in range(n)]
        self.evaluator = TeamEvaluator(world, params)
        self._inboxes = [TeamUpdateInbox(i, n) for i in range(n)]
        self._barrier = {i: 0 for i in range(n)}
        self.history: list[TeamMetrics] = []

    def run(self, progress: Callable[[Progress], None] | None = None) -> RunSummary:
        """Explore until the stop rule; report progress every metrics evaluation."""
        started = time.perf_counter()
        run = self.params.run
        stop_reason = f"max_steps {run.max_steps} reached"
        for _ in range(run.max_steps):
            self.step_once()
            if self.simulation.step % METRICS_INTERVAL_STEPS == 0:
                metrics = self.evaluate()
                if progress is not None:
                    progress(Progress(self.simulation.step, metrics, self.num_decisions))
                reason = self._stop_reason(metrics)
                if reason:
                    stop_reason = reason
                    break
        if not self.history or self.history[-1].stamp_s != self.simulation.stamp_s:
            self.evaluate()
        return self.summary(time.perf_counter() - started, stop_reason)

    def step_once(self) -> None:
        """One lockstep cycle: sense, deliver team data, decide, move."""
        sim = self.simulation
        time_step = self.params.motion.time_step_s
        commands = []
        published = []
        for agent, inbox in zip(self.agents, self._inboxes):
            frame = sim.sense(agent.robot_id)
            self.evaluator.record_truth(agent.robot_id, frame.stamp_s,
                                        sim.true_pose(agent.robot_id))
            limits = {r: s for r, s in self._barrier.items() if r != agent.robot_id}
            agent.apply_team_updates(inbox.pop_ready(limits))
            command = agent.step(step_input(frame, time_step))
            update = agent.take_outgoing()
            if update is not None:
                published.append(update)
            commands.append(command_to_twist(command.turn_rad, command.forward_m, time_step))
        for update in published:
            for inbox in self._inboxes:
                if inbox is not self._inboxes[update.robot_id]:
                    inbox.receive(update)
        self._barrier = {agent.robot_id: agent.outbox.last_sequence for agent in self.agents}
        for robot_id, (linear_x, angular_z) in enumerate(commands):
            sim.apply_command(robot_id, linear_x, angular_z)
        sim.advance()

    @property
    def num_decisions(self) -> int:
        """Decisions made by the whole team so far."""
        return sum(len(agent.decisions) for agent in self.agents)

    def evaluate(self) -> TeamMetrics:
        """Team metrics now, appended to the history."""
        interval = self.params.slam.keyframe_interval_steps
        time_step = self.params.motion.time_step_s
        for agent in self.agents:  # the truth of this step (distance up to now)
            self.evaluator.record_truth(agent.robot_id, self.simulation.stamp_s,
                                        self.simulation.true_pose(agent.robot_id))
        trajectories, landmarks = {}, {}
        for agent in self.agents:
            indices, poses = agent.slam.trajectory(agent.robot_id)
            trajectories[agent.robot_id] = (indices * interval * time_step, poses)
            landmarks[agent.robot_id] = agent.slam.landmark_estimates()
        metrics = self.evaluator.evaluate(self.simulation.stamp_s, trajectories, landmarks)
        self.history.append(metrics)
        return metrics

    def _stop_reason(self, metrics: TeamMetrics) -> str:
        run = self.params.run
        if metrics.explored_ratio >= run.until_explored:
            return f"explored ratio {metrics.explored_ratio:.3f} >= {run.until_explored}"
        if metrics.distance_m >= run.max_distance_m:
            return f"distance {metrics.distance_m:.0f} m >= {run.max_distance_m:.0f} m"
        if all(agent.finished for agent in self.agents):
            return "every robot finished"
        return ""

    def summary(self, wall_s: float, stop_reason: str) -> RunSummary:
        """The run's summary in the shared JSON schema."""
        final = self.history[-1]
        distances = self.evaluator.robot_distances_m
        times = [d.planning_time_s for agent in self.agents for d in agent.decisions]
        world = self.params.world
        return RunSummary(
            seed=self.params.run.seed, planner=self.params.planner.name,
            num_robots=world.num_robots, map_size_m=(world.width_m, world.height_m),
            num_landmarks=world.num_landmarks, explored_ratio=final.explored_ratio,
            distance_m=final.distance_m, loc_rmse_m=final.loc_rmse_m,
            landmark_rmse_m=final.landmark_rmse_m, decisions=len(times), wall_s=wall_s,
            sim_time_s=self.simulation.stamp_s,
            decision_time_median_s=float(np.median(times)) if times else math.nan,
            decision_time_max_s=float(np.max(times)) if times else math.nan,
            stop_reason=stop_reason,
            robots=[RobotSummary(
                id=agent.robot_id, distance_m=float(distances[agent.robot_id]),
                decisions=len(agent.decisions),
                targets=[TargetEntry(float(d.target.position[0]), float(d.target.position[1]),
                                     FRONTIER_TYPE_NAMES[d.target.kind])
                         for d in agent.decisions],
                decision_times_s=[d.planning_time_s for d in agent.decisions])
                for agent in self.agents],
            history=[HistorySample(m.stamp_s, m.distance_m, m.explored_ratio, m.loc_rmse_m,
                                   m.landmark_rmse_m) for m in self.history])
