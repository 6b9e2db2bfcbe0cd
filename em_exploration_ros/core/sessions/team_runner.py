"""An N-robot exploration in one process: the engine of em-sim and of the benchmark.

The runner plays the roles of the ROS system without ROS: ``WorldSession``
(``world_session.py``, the protocol em-world drives, with its ``WorldSimulation`` and link
relay) is the world node, one ``RobotSession`` per robot (``robot_session.py``, the
protocol the ROS robot node drives, with its ``RobotAgent``) is each robot process in
relay mode, and team records and requests travel through the link model
(``core/links/link_model.py``, the relay) into each robot's session, counted as the relay
counts its deliveries. Message timing follows the lockstep protocol of the ROS system: an
update a robot publishes while processing step k is applied by a teammate before it
processes the step at which the link delivers it (k+1 over perfect links: the world's
barrier), and commands and odometry go through the same wire conversions. A seeded em-sim
run therefore chooses the same targets as the ROS system in lockstep mode.

Gap repair is driven by steps (``core/links/link_sender.py``, shared with the ROS robot in
relay mode): a robot whose inbox has gaps sends a request for one of them (through the
link, to the stream's owner) at most every ``links.repair_interval_s``; the owner
re-sends the records, as broadcasts, through the link.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from em_exploration_ros.core.agent.robot_agent import StepInput
from em_exploration_ros.core.node_settings import RobotNodeSettings, WorldNodeSettings
from em_exploration_ros.core.records.team_data import MissingRange, RendezvousEvent, TeamUpdate
from em_exploration_ros.core.sessions.robot_effects import SendCommand, SendFrame
from em_exploration_ros.core.sessions.robot_session import (OdometryInput, RobotSession,
                                                            ScanInput)
from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator, TeamMetrics
from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers, evaluation_layers
from em_exploration_ros.core.evaluation.rendezvous_stats import rendezvous_outcomes
from em_exploration_ros.core.evaluation.run_monitor import (METRICS_INTERVAL_STEPS,
                                                            DecisionEntry,
                                                            RobotProgressRecord, RunMonitor)
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, MeetingEntry, RunSummary
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.links.link_model import Delivery, FrameKind
from em_exploration_ros.core.sessions.world_effects import PublishSensors
from em_exploration_ros.core.sessions.world_session import WorldSession
from em_exploration_ros.core.world.simulation import SensorFrame
from em_exploration_ros.core.records.wire_model import (pose_through_wire,
                                                        seconds_to_nanoseconds,
                                                        twist_to_increment_covariance)


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
        # The world as em-world runs it, always with the links (perfect ones deliver at k+1).
        self.world = WorldSession(params, WorldNodeSettings(), 0.0, relayed=True)
        self.simulation = self.world.sim
        world = self.simulation.world
        n = params.world.num_robots
        settings = RobotNodeSettings()
        self.sessions = [RobotSession(i, params, settings, relay_mode=True) for i in range(n)]
        for session in self.sessions:
            session.anchor(world.start_poses[0], 0.0, 0)
        self.agents = [session.agent for session in self.sessions]
        self._delivered = [[0, 0] for _ in range(n)]  # (records, requests) to each robot
        self.evaluator = TeamEvaluator(world, params)
        self.monitor = RunMonitor(params)
        self.rendezvous_events: list[RendezvousEvent] = []

    def run(self, progress: Callable[[Progress], None] | None = None) -> RunSummary:
        """Explore until the stop rule; report progress every metrics evaluation."""
        started = time.perf_counter()
        monitor = self.monitor
        while not monitor.stopped and self.simulation.step < monitor.final_step:
            self.step_once()
            step = self.simulation.step
            if step % METRICS_INTERVAL_STEPS == 0 or step >= monitor.final_step:
                metrics = self.evaluate()
                if progress is not None:
                    progress(Progress(step, metrics, self.num_decisions))
                monitor.observe(step, metrics, all(agent.finished for agent in self.agents))
        return self.summary(time.perf_counter() - started)

    def step_once(self) -> None:
        """One lockstep cycle: deliver what the links bring, sense, decide, send, move."""
        sim = self.simulation
        step = sim.step
        sensors = []
        for effect in self.world.step_messages():
            kind = type(effect)
            if kind is Delivery:
                self._deliver(effect, step)
            elif kind is PublishSensors:
                sensors.append(effect)
        commands = []
        for session in self.sessions:
            robot = session.robot_id
            frame = sensors[robot].frame
            self.evaluator.record_truth(robot, frame.stamp_s, sim.true_pose(robot))
            session.odometry(step, OdometryInput(pose_through_wire(frame.odom_pose),
                                                 frame.twist_covariance), 0.0, step)
            stamp = divmod(seconds_to_nanoseconds(frame.stamp_s), 1_000_000_000)
            effects = session.scan(ScanInput(step, stamp, frame.landmarks, frame.teammates,
                                             (), tuple(self._delivered[robot])), 0.0, step)
            commands.append(self._send(robot, step, effects))
        self.world.advance(commands)

    def _deliver(self, delivery: Delivery, step: int) -> None:
        """Hand a frame the links bring before ``step`` to its receiver's session (a record,
        or a request for records of its stream), counted as the relay counts them."""
        frame, receiver = delivery.frame, delivery.receiver
        session, delivered = self.sessions[receiver], self._delivered[receiver]
        if frame.kind == FrameKind.REQUEST:
            gap: MissingRange = frame.payload
            delivered[1] += 1
            session.delivered_request(frame.sender, gap.robot_id, gap.first_sequence,
                                      gap.last_sequence, delivered[1], 0.0, step)
            return
        update: TeamUpdate = frame.payload
        delivered[0] += 1
        session.delivered_update(update.robot_id, update, delivered[0], 0.0, step)

    def _send(self, robot: int, step: int, effects: list) -> tuple[float, float]:
        """Perform what robot ``robot``'s session returned for ``step``: its frames (a gap
        request, re-sends asked of it, its new update) offered to its channel; returns its
        command's twist (linear [m/s], angular [rad/s]). The rest is the ROS node's."""
        twist = None
        for effect in effects:
            kind = type(effect)
            if kind is SendFrame:
                frame = effect.frame
                if frame.kind == FrameKind.UPDATE:
                    self.rendezvous_events.extend(frame.payload.rendezvous)
                self.world.offer(frame)
            elif kind is SendCommand:
                twist = effect.reply.linear_x, effect.reply.angular_z
        if twist is None:
            raise RuntimeError(f"robot {robot} did not answer step {step}")
        return twist

    @property
    def num_decisions(self) -> int:
        """Decisions made by the whole team so far."""
        return sum(len(agent.decisions) for agent in self.agents)

    def evaluate(self) -> TeamMetrics:
        """Team metrics now (the truth of this step recorded first)."""
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
        return self.evaluator.evaluate(self.simulation.stamp_s, trajectories, landmarks)

    def map_layers(self) -> TeamMapLayers:
        """The picture of the run so far: truth, each robot's own estimate of its path and
        of the landmarks, the targets counted in the summary and the rendezvous."""
        final = self.monitor.final_metrics
        end_s = math.inf if final is None else final.stamp_s
        counted = {agent.robot_id: self.monitor.decisions_counted(entries)
                   for agent, entries in zip(self.agents, self._decision_entries())}
        targets = {robot: [d.target_entry() for d in chosen] for robot, chosen in counted.items()}
        params = self.params
        return evaluation_layers(
            self.evaluator,
            {agent.robot_id: agent.slam.trajectory(agent.robot_id)[1] for agent in self.agents},
            {agent.robot_id: np.array(list(agent.slam.landmark_estimates().values())
                                      ).reshape(-1, 2) for agent in self.agents},
            targets, rendezvous_outcomes(self.rendezvous_events, end_s),
            f"{params.planner.name}, {params.world.num_robots} robots, seed {params.run.seed}: "
            f"{self.monitor.stop_reason or 'running'}")

    def _decision_entries(self) -> list[list[DecisionEntry]]:
        """Each robot's decisions as the run monitor counts them."""
        return [[DecisionEntry(d.stamp_s, (float(d.target.position[0]),
                                           float(d.target.position[1])),
                               d.target.kind, d.planning_time_s, d.planner_failed)
                 for d in agent.decisions]
                for agent in self.agents]

    def summary(self, wall_s: float) -> RunSummary:
        """The run's summary in the shared JSON schema (the run monitor's)."""
        decisions = self._decision_entries()
        progress = [RobotProgressRecord(
            tuple(GivenUpEntry(float(g.position[0]), float(g.position[1]), g.stamp_s,
                               g.reason.value) for g in agent.given_up), agent.blocked_s,
            len(agent.slam.recoveries))
            for agent in self.agents]
        meetings = sorted((MeetingEntry(agent.robot_id, e.partner_id, e.rendezvous_id,
                                        e.requested_at_s, e.stamp_s, e.trace_before_m2,
                                        e.trace_after_m2)
                           for agent in self.agents for e in agent.meeting_effects),
                          key=lambda m: (m.stamp_s, m.requester_id))
        summary = self.monitor.summary(decisions, wall_s, progress=progress,
                                       rendezvous_events=self.rendezvous_events,
                                       meetings=meetings)
        summary.team_updates = dataclasses.asdict(self.world.update_counts())
        return summary
