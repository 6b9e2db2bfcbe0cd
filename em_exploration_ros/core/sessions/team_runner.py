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

The outside observer is em-evaluator's own protocol, ``EvaluatorSession``
(``evaluator_session.py``), shown every step's ground truth and, at its evaluation steps,
each robot's estimates, answer and stream as em-evaluator sees them (``TeamRunner.observe``),
and, when the sonar is not ideal, the truth of the keyframe scans and the landmarks each robot
tied to its own as they are made: it evaluates, applies the stop rules and writes the summary
(with the robots' association counts) and the map layers for both.

Gap repair is driven by steps (``core/links/link_sender.py``, shared with the ROS robot in
relay mode): a robot whose inbox has gaps sends a request for one of them (through the
link, to the stream's owner) at most every ``links.repair_interval_s``; the owner
re-sends the records, as broadcasts, through the link.

Restarts (``restarts``, em-sim's ``--restart ROBOT:STEP``): robot r's session is replaced,
before step k's deliveries, by a new one that rejoins as a restarted em-robot process with a
``state_dir`` does: its first scan is step k, it reads back the journals its earlier session
kept (held here in memory) and resumes (``RobotSession.journals_read``, ``_resume``). The
runner keeps journals only when restarts are asked for.
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Callable

import numpy as np

from em_exploration_ros.core.agent.robot_agent import RobotAgent
from em_exploration_ros.core.node_settings import (EvaluatorNodeSettings, RobotNodeSettings,
                                                   WorldNodeSettings)
from em_exploration_ros.core.records.team_data import MissingRange, TeamUpdate
from em_exploration_ros.core.sessions.robot_effects import (AppendJournal, Journal,
                                                            KeyframeEstimate,
                                                            PublishCorrespondences,
                                                            PublishEstimates, ReadJournals,
                                                            SendCommand, SendFrame,
                                                            StartJournal)
from em_exploration_ros.core.sessions.robot_session import (JournalRecords, OdometryInput,
                                                            RobotSession, ScanInput)
from em_exploration_ros.core.sessions.world_effects import PublishSensors, PublishSonarTruth
from em_exploration_ros.core.sessions.world_session import WorldSession
from em_exploration_ros.core.sessions.evaluator_effects import (CommandReport, Effect,
                                                                PublishMetrics)
from em_exploration_ros.core.sessions.evaluator_session import EvaluatorSession
from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator, TeamMetrics
from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.run_monitor import METRICS_INTERVAL_STEPS, RunMonitor
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, MeetingEntry, RunSummary
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.links.link_model import Delivery, FrameKind
from em_exploration_ros.core.world.simulation import SensorFrame, WorldSimulation
from em_exploration_ros.core.records.wire_model import (pose_through_wire,
                                                        seconds_to_nanoseconds, sim_time_s)


def sensor_inputs(frame: SensorFrame, delivered: tuple[int, int]
                  ) -> tuple[OdometryInput, ScanInput]:
    """A world sensor frame as a robot's session takes it: the dead reckoning through the
    wire's numbers and the scan with its stamp (sec, nanosec) and ``delivered``, the links'
    deliveries to the robot so far (records, requests); em-robot builds the same from the
    world's messages (``nodes.conversions.scan_input_from_msg``)."""
    stamp = divmod(seconds_to_nanoseconds(frame.stamp_s), 1_000_000_000)
    return (OdometryInput(pose_through_wire(frame.odom_pose), frame.twist_covariance),
            ScanInput(frame.step, stamp, frame.landmarks, frame.teammates, (), delivered))


@dataclass(frozen=True)
class Progress:
    """Reported to the progress callback after each metrics evaluation."""

    step: int
    metrics: TeamMetrics
    decisions: int


class TeamRunner:
    """Runs one seeded exploration; ``run()`` returns its ``RunSummary``. ``restarts``:
    (robot, step) pairs, each a restart of that robot's process before that step (module
    docstring). ``simulation``: the world to run (default: the one ``params`` describe; a
    test gives one whose physics it changes); ``make_agent``: makes each robot's brain
    (``RobotSession``'s, for a benchmark or test that gives its own collaborators)."""

    def __init__(self, params: ExplorationParams,
                 restarts: Iterable[tuple[int, int]] = (), *,
                 simulation: WorldSimulation | None = None,
                 make_agent: Callable[[int, ExplorationParams, np.ndarray],
                                      RobotAgent] = RobotAgent) -> None:
        self.params = params
        self._restarts: dict[int, list[int]] = {}
        for robot, step in restarts:
            if not 0 <= robot < params.world.num_robots or step < 1:
                raise ValueError(f"restart {robot}:{step}: no such robot, or not after step 0")
            self._restarts.setdefault(step, []).append(robot)
        journaled = bool(self._restarts)
        # The world as em-world runs it, always with the links (perfect ones deliver at k+1).
        self.world = WorldSession(params, WorldNodeSettings(), 0.0, relayed=True,
                                  simulation=simulation)
        self._make_agent = make_agent
        self.simulation = self.world.sim
        world = self.simulation.world
        n = params.world.num_robots
        settings = RobotNodeSettings()
        self.sessions = [RobotSession(i, params, settings, relay_mode=True, journaled=journaled,
                                      make_agent=make_agent)
                         for i in range(n)]
        #: Each robot's journals (own stream, teammates' records applied), with restarts only.
        self.journals = {Journal.OWN: [[] for _ in range(n)], Journal.TEAM: [[] for _ in range(n)]}
        for session in self.sessions:
            session.anchor(world.start_poses[0], 0.0, 0)
        self.agents = [session.agent for session in self.sessions]
        self._delivered = [[0, 0] for _ in range(n)]  # (records, requests) to each robot
        # The outside observer, as em-evaluator: truth, estimates, commands, team records.
        self.observer = EvaluatorSession(params, EvaluatorNodeSettings(
            metrics_interval_s=METRICS_INTERVAL_STEPS * params.motion.time_step_s),
            time.perf_counter(), 0.0)
        self.observer.true_world(world, time.perf_counter())
        self._reported = [(0, 0)] * n  # (targets given up, meetings) reported of each robot
        #: The latest keyframes the robots published since the observer last looked.
        self._published: list[tuple[int, KeyframeEstimate]] = []

    @property
    def evaluator(self) -> TeamEvaluator:
        """The observer's metrics from ground truth (never seen by an agent)."""
        return self.observer.evaluator

    @property
    def monitor(self) -> RunMonitor:
        """The observer's stop rules and history."""
        return self.observer.monitor

    def run(self, progress: Callable[[Progress], None] | None = None) -> RunSummary:
        """Explore until the stop rule; report progress every metrics evaluation."""
        monitor = self.monitor
        self.observe(time.perf_counter())
        while not monitor.stopped and self.simulation.step < monitor.final_step:
            self.step_once()
            for effect in self.observe(time.perf_counter()):
                if isinstance(effect, PublishMetrics) and progress is not None:
                    progress(Progress(self.simulation.step, effect.metrics,
                                      self.num_decisions))
        return self.summary(time.perf_counter())

    def step_once(self) -> None:
        """One lockstep cycle: deliver what the links bring, sense, decide, send, move."""
        step = self.simulation.step
        if self._restarts:
            for robot in self._restarts.get(step, ()):
                self._restart(robot)
        sensors = []
        for effect in self.world.step_messages():
            kind = type(effect)
            if kind is Delivery:
                self._deliver(effect, step)
            elif kind is PublishSensors:
                sensors.append(effect)
            elif kind is PublishSonarTruth:
                self.observer.sonar_truth(effect.robot, seconds_to_nanoseconds(effect.stamp_s),
                                          effect.step, effect.readings, effect.sources,
                                          time.perf_counter())
        commands = []
        for session in self.sessions:
            robot = session.robot_id
            frame = sensors[robot].frame
            odometry, scan = sensor_inputs(frame, tuple(self._delivered[robot]))
            session.odometry(step, odometry, 0.0, step)
            effects = session.scan(scan, 0.0, step)
            commands.append(self._send(robot, step, effects))
        self.world.advance(commands)

    def _restart(self, robot: int) -> None:
        """Robot ``robot``'s process restarts: a new session, anchored as every robot's is,
        that rejoins at its first scan from the journals its earlier session kept. It holds
        its whole stream at once from its journal, so it does not wait for teammates' copies
        (``rejoin_settle_s`` 0: em-sim's clock does not run)."""
        old = self.sessions[robot]
        session = RobotSession(robot, self.params,
                               dataclasses.replace(old.settings, rejoin_settle_s=0.0),
                               relay_mode=True, journaled=True, make_agent=self._make_agent)
        session.anchor(self.simulation.world.start_poses[0], 0.0, self.simulation.step)
        self.sessions[robot] = session
        self.agents[robot] = session.agent

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
        effects = list(effects)
        for effect in effects:  # grows with what a restarted session does with its journals
            kind = type(effect)
            if kind is SendFrame:
                frame = effect.frame
                if frame.kind == FrameKind.UPDATE:
                    self.observer.team_update(robot, frame.payload, time.perf_counter())
                self.world.offer(frame)
            elif kind is SendCommand:
                twist = effect.reply.linear_x, effect.reply.angular_z
            elif kind is PublishCorrespondences:
                self.observer.correspondences(
                    robot, effect.stamp[0] * 1_000_000_000 + effect.stamp[1], effect.step,
                    effect.pairs, time.perf_counter())
            elif kind is PublishEstimates and effect.latest is not None:
                self._published.append((robot, effect.latest))
            elif kind is AppendJournal:
                self.journals[effect.journal][robot].append(effect.record)
            elif kind is StartJournal:
                self.journals[effect.journal][robot] = list(effect.records)
            elif kind is ReadJournals:
                own, team = (JournalRecords(f"{journal.value} journal", f"<em-sim robot {robot}>",
                                            None, list(self.journals[journal][robot]))
                             for journal in (Journal.OWN, Journal.TEAM))
                effects += self.sessions[robot].journals_read(own, team, 0.0, step)
        if twist is None:
            raise RuntimeError(f"robot {robot} did not answer step {step}")
        return twist

    @property
    def num_decisions(self) -> int:
        """Decisions made by the whole team so far."""
        return sum(len(agent.decisions) for agent in self.agents)

    def observe(self, wall_s: float) -> list[Effect]:
        """Show the observer the step the world is at (wall time ``wall_s`` [s]) as
        em-evaluator sees it: the latest keyframe covariance each robot published while
        answering step k - 1 (at a keyframe step); before an evaluation step k, each robot's
        estimates as of step k - 1 (stamped at the latest keyframe step, as a robot publishes
        them); the true poses of step k; then each robot's answer to step k - 1 (its progress
        bookkeeping). Returns the observer's effects (``PublishMetrics`` at an evaluation)."""
        observer, step = self.observer, self.simulation.step
        evaluating = observer.evaluates_at(step)
        effects: list[Effect] = []
        for robot, latest in self._published:
            effects += observer.keyframe_covariance(
                robot, seconds_to_nanoseconds(latest.stamp_s), latest.covariance, wall_s)
        self._published.clear()
        if evaluating:
            interval = self.params.slam.keyframe_interval_steps
            time_step = self.params.motion.time_step_s
            stamp_ns = seconds_to_nanoseconds(
                sim_time_s((step - 1) // interval * interval, time_step))
            for agent in self.agents:
                indices, poses = agent.slam.trajectory(agent.robot_id)
                effects += observer.path_estimate(agent.robot_id, stamp_ns,
                                                  indices * interval * time_step, poses, wall_s)
                effects += observer.landmark_estimate(
                    agent.robot_id, stamp_ns, agent.slam.landmark_estimates(), wall_s)
        for robot in range(self.params.world.num_robots):
            effects += observer.true_pose(robot, step, self.simulation.true_pose(robot), wall_s)
        if evaluating:
            for agent in self.agents:
                effects += observer.command(agent.robot_id, self._command_report(agent, step - 1),
                                            wall_s)
        return effects

    def _command_report(self, agent: RobotAgent, step: int) -> CommandReport:
        """What ``agent``'s answer to ``step`` tells the observer, with the targets it gave
        up and the meetings it measured since its previous report."""
        given_up, meetings = self._reported[agent.robot_id]
        self._reported[agent.robot_id] = len(agent.given_up), len(agent.meeting_effects)
        stamp_ns = seconds_to_nanoseconds(sim_time_s(step, self.params.motion.time_step_s))
        return CommandReport(
            agent.robot_id, step, stamp_ns, agent.finished, agent.outbox.last_sequence,
            agent.blocked_s, len(agent.given_up),
            tuple(GivenUpEntry(float(g.position[0]), float(g.position[1]), g.stamp_s,
                               g.reason.value) for g in agent.given_up[given_up:]),
            tuple(MeetingEntry(agent.robot_id, e.partner_id, e.rendezvous_id,
                               e.requested_at_s, e.stamp_s, e.trace_before_m2,
                               e.trace_after_m2) for e in agent.meeting_effects[meetings:]),
            len(agent.slam.recoveries))

    def map_layers(self) -> TeamMapLayers:
        """The picture of the run: truth, each robot's estimate of its path and of the
        landmarks at the last evaluation, the targets counted in the summary and the
        rendezvous (``EvaluatorSession.map_layers``)."""
        return self.observer.map_layers(self.monitor.stop_reason or "running")

    def summary(self, wall_s: float) -> RunSummary:
        """The run's summary in the shared JSON schema (``EvaluatorSession``'s, as
        em-evaluator's, with ``association`` when the sonar is not ideal), at wall time
        ``wall_s`` [s], with what the links delivered."""
        summary = self.observer.summary(wall_s)
        summary.team_updates = dataclasses.asdict(self.world.update_counts())
        return summary
