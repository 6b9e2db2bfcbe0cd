"""The world's side of the team protocol: when to start, the lockstep barrier, the links.

``WorldSession`` owns the ``WorldSimulation`` (the system's clock and its only source of
ground truth), the ``LockstepBarrier`` and, in relay mode, the link model's relay bookkeeping
(``core/links/link_relay.py``). It takes inputs (a robot's command with the wall time, a
liveliness change, a team message heard by the relay, a poll tick with who is connected, a
real-time tick) and returns the effects to perform (``world_effects``, ``effects.LogLine``);
it reads no clock and knows no ROS. em-world (``nodes/world_node.py``) and em-sim
(``team_runner.TeamRunner``, through ``step_messages``, ``offer`` and ``advance``) drive it.

Lockstep mode (default): once every robot is connected (and the evaluator and the recorder
listen, if required), for ``startup_settle_s`` (or ``startup_timeout_s`` passed), step k
publishes /clock, every robot's sensors (with the barrier ``team_sequences``) and the ground
truth; it then waits until every live robot has answered step k with a MotionCommand
(``core.sessions.lockstep.LockstepBarrier``). A robot whose answer is missing gets the step's
sensor messages again every ``step_resend_s`` (the same messages, so a missed start or a lost
packet changes nothing), after the step's /clock again; a robot still silent after
``robot_timeout_s`` wall seconds (``liveliness_grace_s`` once its liveliness lease expired,
or a lease into the run if it was never reported) is *lost*: the world logs ``robot <i>
lost: <why>`` and stops waiting for it (zero motion). A lost robot that answers again
(recovered, or restarted with the same id) rejoins at the pose where its vehicle stopped.
When every robot that has not finished is lost, the world waits ``lost_team_wait_s`` for one
to come back before the run ends. The commands are applied in robot id order and the world
advances: the same order as em-sim, so em-sim and the ROS system draw the same noise.

Relay mode (``links.*`` not perfect; always in em-sim): the world is also the link relay
between the robots: it hears their team data, closes step k only once it heard every team
message the answers count (or ``robot_timeout_s`` passed: logged, not waited for again),
transmits step k's frames with the true positions of step k, and delivers what arrives
before publishing step k+1 (whose sensors carry the delivery counts), after the update
counts of every ``METRICS_INTERVAL_STEPS``-th step and of the final step.

Real-time mode: a wall timer advances the world every ``time_step_s / realtime_factor``
seconds with each robot's latest command (none yet: stand still); no barrier.

Stepping ends at the run's final step (``final_step``) or when every robot finished or
stopped; the driver keeps serving what it published.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable

from em_exploration_ros.core.agent.input_checks import (command_problem,
                                                        command_sequence_problem,
                                                        request_problem, run_problem)
from em_exploration_ros.core.agent.liveness import UnseenLiveliness
from em_exploration_ros.core.evaluation.run_monitor import METRICS_INTERVAL_STEPS, final_step
from em_exploration_ros.core.links.link_model import (Frame, UpdateDeliveryCounts,
                                                      perfect_links)
from em_exploration_ros.core.links.link_relay import LinkRelay, SentCounts
from em_exploration_ros.core.node_settings import LOCKSTEP, WorldNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import MAX_SEQUENCE_LEAD
from em_exploration_ros.core.sessions.effects import LogLine, Level, info, warn
from em_exploration_ros.core.sessions.lockstep import STAND_STILL, LockstepBarrier, StepAnswer
from em_exploration_ros.core.sessions.world_effects import (Dropped, PublishClock,
                                                            PublishLinkCounts, PublishSensors,
                                                            PublishSonarTruth, PublishStatus,
                                                            PublishTruth, StartTicking)
from em_exploration_ros.core.world.simulation import WorldSimulation

#: A progress line every this many steps.
LOG_EVERY_STEPS = 500
#: Wall seconds [s] between two lines about the robots the world steps without.
ABSENT_LINE_PERIOD_S = 5.0


@dataclass(frozen=True)
class TeamConnections:
    """What the driver sees of the graph before the first step, by robot id: ``started``,
    the robot's process runs (it listens to its sensors and, in relay mode, to its
    deliveries, and publishes its commands); ``connected``, it runs and its team updates
    have their listeners (teammates or relay, plus the evaluator if required);
    ``observers``, the evaluator and the recorder listen (those required)."""

    started: tuple[bool, ...]
    connected: tuple[bool, ...]
    observers: bool


def _sent_counts(answers: dict[int, StepAnswer]) -> dict[int, SentCounts]:
    """What each robot's answer (robot -> StepAnswer) says it has published."""
    return {robot: SentCounts(a.team_messages, a.team_requests) for robot, a in answers.items()}


class WorldSession:
    """The world's protocol (see module docstring). Wall times ``now_s`` are monotonic
    seconds; ``relayed``: team data through the link relay (default: when the links are
    not perfect); ``lease_s``: the robots' liveliness lease [s] (inf: none)."""

    def __init__(self, params: ExplorationParams, settings: WorldNodeSettings, now_s: float,
                 lease_s: float = math.inf, relayed: bool | None = None,
                 simulation: WorldSimulation | None = None) -> None:
        self.params = params
        self.settings = settings
        self.num_robots = params.world.num_robots
        self.lockstep = settings.clock_mode == LOCKSTEP
        self.final_step = final_step(params, settings.max_sim_time_s)
        self.sim = WorldSimulation(params) if simulation is None else simulation
        self.barrier = LockstepBarrier(self.num_robots, settings.robot_timeout_s,
                                       settings.step_resend_s, settings.liveliness_grace_s)
        if relayed is None:
            relayed = not perfect_links(params.links)
        self.relay = LinkRelay(params) if relayed else None
        self.running = False
        self.stepping_over = False
        self._lease_s = lease_s
        self._unseen = UnseenLiveliness(self.num_robots, lease_s)
        self._latest = [STAND_STILL] * self.num_robots
        self._step_sensors: list[PublishSensors] = []
        self._started_wall_s = now_s
        self._ready_since_s: float | None = None
        self._frames_wait_since_s: float | None = None
        self._team_lost_since_s: float | None = None
        self._absent: tuple[int, ...] = ()  # robots the last step was taken without
        self._absent_steps = 0
        self._absent_line_s = 0.0

    def greeting(self) -> LogLine:
        """The line of a world ready to start."""
        params = self.params
        return info(
            f"world ready: {self.num_robots} robots, {self.sim.world.num_landmarks} landmarks, "
            f"{params.world.width_m:g} m x {params.world.height_m:g} m, seed "
            f"{params.run.seed}, {self.settings.clock_mode}"
            + ("" if self.relay is None else f", team data relayed through the link model "
               f"({params.links})")
            + "; waiting for the robots to connect")

    @property
    def polling(self) -> bool:
        """Whether the driver's poll tick is still needed (start-up, lockstep stepping)."""
        return not self.running or (self.lockstep and not self.stepping_over)

    # -- start-up ---------------------------------------------------------------------------

    def poll(self, now_s: float, team: TeamConnections | None = None) -> list[Any]:
        """The poll tick: before the first step, start once ``team`` (required then) is
        connected and settled or the start-up timeout passed; in lockstep, re-send the open
        step to the silent robots, give up those past their deadline, and step on."""
        if not self.running:
            return self._try_start(now_s, team)
        if not self.polling:
            return []
        effects = self._suspect_the_unseen(now_s)
        due = self.barrier.due_for_resend(now_s)
        if due:
            # /clock is best effort: a robot stopped while the world went on without it
            # missed every tick, and resumes only at a step the world's clock reached.
            effects.append(PublishClock(self.sim.stamp_s))
        effects.extend(self._step_sensors[robot] for robot in due)
        for robot in self.barrier.expire(now_s):
            effects.append(self._lost(robot, f"no answer to step {self.barrier.step} in time"
                                      + (" (liveliness lost)" if robot in self.barrier.suspects
                                         else "")))
        effects.extend(self._check_step_complete(now_s))
        return effects

    def _try_start(self, now_s: float, team: TeamConnections) -> list[Any]:
        settings = self.settings
        ready = all(team.connected) and team.observers
        if not ready:
            self._ready_since_s = None
        elif self._ready_since_s is None:
            self._ready_since_s = now_s
        waited = now_s - self._started_wall_s
        settled = ready and now_s - self._ready_since_s >= settings.startup_settle_s
        if not settled and waited < settings.startup_timeout_s:
            return []
        # Only a robot that does not run is missing; one whose team updates lack a listener
        # only because a teammate is missing goes on.
        missing = [r for r in range(self.num_robots) if not team.started[r]]
        effects: list[Any] = [  # run_team.sh --respawn restarts each (a wedged start)
            self._lost(robot, f"not connected after {settings.startup_timeout_s:g} s "
                              f"(treated as stopped)") for robot in missing]
        self.barrier.stop(missing)
        if not team.observers:
            effects.append(warn("the evaluator or the recorder does not listen yet; "
                                "starting anyway"))
        self.running = True
        self._unseen.first_step(now_s)
        mode = settings.clock_mode
        effects.append(info(f"all set after {waited:.1f} s: stepping ({mode})"))
        effects.append(self._status(False, f"stepping ({mode})"))
        effects.extend(self._publish_step(now_s))
        if self.lockstep:
            effects.extend(self._check_step_complete(now_s))
        else:
            effects.append(StartTicking(self.params.motion.time_step_s
                                        / settings.realtime_factor))
        return effects

    # -- the robots' answers and liveliness -------------------------------------------------

    def run_problem(self, run_id: int) -> str | None:
        """Reason to drop a message of another run (its ``run_id`` not the world's)."""
        return run_problem(run_id, self.settings.run_id)

    def command_problem(self, robot: int, robot_id: int, linear_x: float, angular_z: float,
                        team_sequence: int) -> str | None:
        """Reason to drop a motion command received on robot ``robot``'s topic (besides its
        form, which the driver checks): another robot's id, a twist (m/s, rad/s) beyond the
        robot's kinematics, or a barrier entry (team_sequence) behind the robot's last one
        or implausibly ahead."""
        motion = self.params.motion
        last_sequence = (self.barrier.team_sequences[robot] if self.lockstep
                         else self._latest[robot].team_sequence)
        return ((f"robot_id {robot_id} on robot {robot}'s topic" if robot_id != robot else None)
                or command_problem(linear_x, angular_z, motion.speed_mps,
                                   motion.max_turn_per_step_rad, motion.time_step_s)
                or command_sequence_problem(team_sequence, last_sequence, MAX_SEQUENCE_LEAD))

    def on_command(self, robot: int, step: int, answer: StepAnswer, now_s: float) -> list[Any]:
        """Robot ``robot``'s checked command for ``step``: the barrier's answer (lockstep;
        the step may close), or its latest command (real time)."""
        if not self.lockstep:
            self._latest[robot] = answer
            return []
        if not self.running or self.stepping_over:
            return []
        outcome = self.barrier.answer(robot, step, answer, now_s)
        effects: list[Any] = []
        if outcome == LockstepBarrier.REJOINED:
            effects.append(info(f"robot {robot} rejoined at step {self.barrier.step} "
                                f"(answered step {step})"))
        elif outcome == LockstepBarrier.CONFLICT:
            effects.append(Dropped(f"a second, different answer of robot {robot} to step "
                                   f"{step}: the first stands (another publisher on its "
                                   f"topic?)"))
        elif outcome == LockstepBarrier.FUTURE:
            effects.append(warn(f"ignored a {outcome} command of robot {robot} for step "
                                f"{step} (current step {self.barrier.step})"))
        elif outcome != LockstepBarrier.ACCEPTED:
            effects.append(LogLine(Level.DEBUG, f"ignored a {outcome} command of robot "
                                                f"{robot} for step {step}"))
        effects.extend(self._check_step_complete(now_s))
        return effects

    def on_liveliness(self, robot: int, alive: bool, restarted: bool,
                      now_s: float) -> list[LogLine]:
        """The middleware reported robot ``robot``'s liveliness asserted (by a new process:
        ``restarted``) or lost."""
        if alive:
            self._unseen.seen(robot)
            if restarted:
                self.barrier.restarted(robot, now_s)
            else:
                self.barrier.trust(robot, now_s)
            return [info(f"robot {robot}: liveliness asserted"
                         + (" by a new process (restarted)" if restarted else ""))]
        self.barrier.suspect(robot, now_s)
        return [warn(f"robot {robot}: liveliness lost (process dead, stopped or wedged, or "
                     f"its assertions lost on the network)")]

    def _suspect_the_unseen(self, now_s: float) -> list[Any]:
        """A robot whose liveliness was not reported a lease into the run is suspect, as if
        its liveliness had been lost (``liveliness_grace_s`` to answer a step instead of
        ``robot_timeout_s``) until it is reported. A robot that died before the middleware
        reported its liveliness was otherwise waited for ``robot_timeout_s``, and a team of
        such robots one after the other."""
        effects: list[Any] = []
        for robot in self._unseen.due(now_s):
            if robot in self.barrier.stopped:
                continue
            self.barrier.suspect(robot, now_s)
            effects.append(warn(
                f"robot {robot}: no liveliness seen {self._lease_s:g} s into the run; "
                f"given {self.barrier.suspect_timeout_s:g} s to answer until it is"))
        return effects

    @staticmethod
    def _lost(robot: int, why: str) -> LogLine:
        """The line run_team.sh --respawn reacts to (it restarts the robot's process)."""
        return warn(f"robot {robot} lost: {why}; the team goes on without it (zero motion) "
                    f"until it answers again")

    # -- the relay (relay mode) -------------------------------------------------------------

    def update_heard(self, sender: int, sequence: int, size_bytes: int, payload: Any,
                     publication_sequence: int | None, now_s: float) -> list[Any]:
        """A record of ``sender``'s stream heard on its update topic (``size_bytes`` on the
        wire, the message's publication sequence number if known); the step may close."""
        self.relay.update_heard(sender, sequence, size_bytes, self.sim.step, payload,
                                publication_sequence)
        return self._check_step_complete(now_s)

    def history_problem(self, sender: int, owner: int) -> str | None:
        """Reason to drop ``sender``'s copy of a record of robot ``owner``'s stream."""
        if owner != sender and 0 <= owner < self.num_robots:
            return None
        return f"a record of robot {owner} is no teammate's of robot {sender}"

    def history_heard(self, sender: int, owner: int, sequence: int, size_bytes: int,
                      payload: Any) -> None:
        """``sender``'s copy of a record of restarted robot ``owner``'s stream."""
        self.relay.history_heard(sender, owner, sequence, size_bytes, self.sim.step, payload)

    def request_problem(self, requester: int, owner: int, first_sequence: int,
                        last_sequence: int, observer: int) -> str | None:
        """Reason to drop a robot's request for records of ``owner``'s stream (``observer``:
        the id of the evaluator, whose requests are no link traffic)."""
        n = self.num_robots
        if not (0 <= requester < n and 0 <= owner < n):
            return f"robot ids {requester} -> {owner} are not robots of this team"
        if requester == owner:
            return None  # a restarted robot asks every teammate for its own stream
        return request_problem(requester, first_sequence, last_sequence, owner, n, observer)

    def request_heard(self, requester: int, owner: int, first_sequence: int, size_bytes: int,
                      payload: Any, publication_sequence: int | None,
                      now_s: float) -> list[Any]:
        """A robot's request for records of ``owner``'s stream; the step may close."""
        self.relay.request_heard(requester, owner, first_sequence, size_bytes, self.sim.step,
                                 payload, publication_sequence)
        return self._check_step_complete(now_s)

    def missing_messages(self, answers: dict[int, StepAnswer]) -> list[int]:
        """Robots whose answers (robot -> StepAnswer) count team messages the relay has not
        heard yet."""
        return self.relay.holds(_sent_counts(answers))

    def offer(self, frame: Frame) -> None:
        """A frame a robot of the same process (em-sim) sends while the current step is
        processed."""
        self.relay.offer(frame)

    def update_counts(self) -> UpdateDeliveryCounts:
        """Relay mode: the on-time / late / never counts of the team updates before the
        current step."""
        return self.relay.ledger.counts(self.sim.step)

    def link_summary(self) -> list[LogLine]:
        """Relay mode: one line with what the links did so far (none without the relay)."""
        return [] if self.relay is None else [info(self.relay.summary_line(self.sim.step))]

    # -- stepping ---------------------------------------------------------------------------

    def _check_step_complete(self, now_s: float) -> list[Any]:
        """Lockstep: advance as long as every live robot has answered the current step."""
        effects: list[Any] = []
        while (self.running and not self.stepping_over and self.barrier.complete
               and self._relay_heard_step(now_s, effects)
               and self._lost_team_waited_for(now_s, effects)):
            answers = self.barrier.close()
            effects.extend(self._note_absent(now_s))
            effects.extend(self._advance(answers, self.barrier.all_done, now_s))
        return effects

    def _note_absent(self, now_s: float) -> list[LogLine]:
        """Lockstep, at the close of a step: name the unfinished robots it is taken without
        (lost, or restarting, not answering): a line when that set changes, then one every
        ``ABSENT_LINE_PERIOD_S`` wall seconds with the count of steps taken without them.
        INFO: the robot's loss is the WARN line (``_lost``); these say what the world did."""
        barrier, step = self.barrier, self.barrier.step
        absent = tuple(r for r in range(self.num_robots)
                       if r in barrier.stopped and not barrier.finished[r])
        names = ", ".join(f"{r}" + (" (restarting)" if r in barrier.rejoining else "")
                          for r in absent)
        if absent != self._absent:
            before, count = self._absent, self._absent_steps
            self._absent, self._absent_steps = absent, int(bool(absent))
            self._absent_line_s = now_s + ABSENT_LINE_PERIOD_S
            lines = []
            if before:
                lines.append(info(f"step {step}: {count} steps were taken without robots "
                                  f"{', '.join(map(str, before))}"))
            if absent:
                lines.append(info(f"step {step} taken without robots {names}: not answering, "
                                  f"their vehicles stand still"))
            return lines
        if not absent:
            return []
        self._absent_steps += 1
        if now_s < self._absent_line_s:
            return []
        self._absent_line_s = now_s + ABSENT_LINE_PERIOD_S
        return [info(f"step {step} taken without robots {names}: {self._absent_steps} steps "
                     f"without them so far")]

    def _lost_team_waited_for(self, now_s: float, effects: list[Any]) -> bool:
        """False while the world still waits for a team whose every unfinished robot is lost
        to come back (``lost_team_wait_s``; run_team.sh --respawn restarts them): without
        the wait, a team wedged at once ended its mission before any restart."""
        if not self.barrier.team_lost:
            self._team_lost_since_s = None
            return True
        wait_s = self.settings.lost_team_wait_s
        if self._team_lost_since_s is None:
            self._team_lost_since_s = now_s
            if wait_s > 0:
                effects.append(warn(f"every robot that has not finished is lost; waiting up "
                                    f"to {wait_s:g} s for one to come back before ending the "
                                    f"mission"))
        return now_s - self._team_lost_since_s >= wait_s

    def _relay_heard_step(self, now_s: float, effects: list[Any]) -> bool:
        """Relay mode: True once the relay heard every team message the step's answers count
        (they travel on other topics than the answers, so they may come later), or
        ``robot_timeout_s`` passed (logged: the step goes on without them)."""
        if self.relay is None:
            return True
        answers = self.barrier.answers()
        missing = self.missing_messages(answers)
        if not missing:
            self._frames_wait_since_s = None
            return True
        if self._frames_wait_since_s is None:
            self._frames_wait_since_s = now_s
        if now_s - self._frames_wait_since_s < self.barrier.robot_timeout_s:
            return False
        effects.append(warn(f"step {self.barrier.step}: team messages of robots {missing} "
                            f"counted in their answers never reached the relay; going on "
                            f"without them (not waited for again)"))
        self.relay.written_off(_sent_counts(answers))
        self._frames_wait_since_s = None
        return True

    def tick(self, now_s: float) -> list[Any]:
        """Real-time mode: advance with each robot's latest command."""
        return self._advance(self._latest, all(answer.finished for answer in self._latest),
                             now_s)

    def _advance(self, answers: list[StepAnswer], everyone_done: bool,
                 now_s: float) -> list[Any]:
        """Apply one command per robot (id order), advance and publish the next step."""
        if self.stepping_over:
            return []
        if everyone_done:
            return self._end_stepping("every robot finished or stopped")
        self.advance((answer.linear_x, answer.angular_z) for answer in answers)
        return self._publish_step(now_s)

    def advance(self, twists: Iterable[tuple[float, float]]) -> None:
        """Close the current step: start its transmissions (relay mode) with the true
        positions of the step, apply each robot's twist ``(linear_x [m/s], angular_z
        [rad/s])`` in robot id order and advance the world one step."""
        sim = self.sim
        if self.relay is not None:
            self.relay.transmit(sim.step, sim.true_positions())
        for robot, (linear_x, angular_z) in enumerate(twists):
            sim.apply_command(robot, linear_x, angular_z)
        sim.advance()

    def step_messages(self) -> list[Any]:
        """What the world publishes at the current step: the deliveries due before it (relay
        mode), /clock, every robot's sensors (each robot's own noise streams, in id order),
        at a keyframe step the truth of each robot's scan when the sonar is not the paper's
        ideal one, and the ground truth."""
        sim, relay, n = self.sim, self.relay, self.num_robots
        effects: list[Any] = [] if relay is None else relay.deliveries(sim.step)
        effects.append(PublishClock(sim.stamp_s))
        sequences = tuple(self.barrier.team_sequences) if self.lockstep else ()
        sensors = [PublishSensors(robot, sim.sense(robot), sequences, None if relay is None
                                  else (relay.delivered_updates[robot],
                                        relay.delivered_requests[robot]))
                   for robot in range(n)]
        self._step_sensors = sensors
        effects.extend(sensors)
        if (not self.params.sensors.ideal_sonar
                and sim.step % self.params.slam.keyframe_interval_steps == 0):
            effects.extend(PublishSonarTruth(robot, sim.step, sim.stamp_s,
                                             sensors[robot].frame.landmarks,
                                             sim.detection_sources(robot))
                           for robot in range(n))
        effects.append(PublishTruth(sim.stamp_s, tuple(sim.true_pose(r) for r in range(n))))
        return effects

    def _publish_step(self, now_s: float) -> list[Any]:
        """The link counts when the evaluator evaluates (relay mode), the step's messages,
        then the end of the stepping at the final step or the barrier opened (lockstep)."""
        sim = self.sim
        final = sim.step >= self.final_step
        effects: list[Any] = []
        if self.relay is not None and (final or sim.step % METRICS_INTERVAL_STEPS == 0):
            effects.append(PublishLinkCounts(sim.step, self.update_counts()))
        effects.extend(self.step_messages())
        if sim.step % LOG_EVERY_STEPS == 0:
            effects.append(info(f"step {sim.step} (t = {sim.stamp_s:g} s)" + (
                "" if self.relay is None else f"; {self.relay.summary_line(sim.step)}")))
        if final:
            effects.extend(self._end_stepping(f"final step {self.final_step} reached"))
        elif self.lockstep:
            self.barrier.open(sim.step, now_s)
        return effects

    def _end_stepping(self, reason: str) -> list[Any]:
        self.stepping_over = True
        sim = self.sim
        return self.link_summary() + [
            info(f"stepping over at step {sim.step} (t = {sim.stamp_s:g} s): {reason}; still "
                 f"serving the latched topics until stopped"),
            self._status(True, reason)]

    def _status(self, stepping_over: bool, reason: str) -> PublishStatus:
        return PublishStatus(self.sim.step, self.sim.stamp_s, stepping_over, reason)
