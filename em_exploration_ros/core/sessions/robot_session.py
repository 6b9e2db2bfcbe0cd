"""One robot's team protocol, without ROS: what it does with each input, as effects.

``RobotSession`` owns the robot's ``RobotAgent`` and decides, for every input the driver
hands it (its scan and dead reckoning as core data, teammates' records and requests, a
liveliness change, a tick of wall time), what the robot does; it returns the effects to
perform (``robot_effects``: publish a command, a record, a request; journal a record; exit;
``effects.LogLine``). It never reads a clock: wall times ``now_s`` [s, monotonic] and the
world's clock ``world_step`` are arguments. The ROS robot node (``nodes/robot_node.py``)
and em-sim (``team_runner.TeamRunner``) both drive it, so there is one protocol.

Lockstep: each scan carries the world's barrier (``team_sequences``). The robot processes
a step only when it holds every teammate's records up to the barrier, asking for missing
ones again (a request every ``request_period_s``) while it waits; a teammate silent past
``barrier_timeout_s`` is skipped with a warning, and not waited for again until the
records given up on arrive (``TeamUpdateInbox.waive``: their sender may be dead). In
real-time mode the barrier is empty and steps are processed as they come. A step the world
sends again (its barrier repair) is answered again with the same command. When the sensor
data of the awaited step is missing but a later step is complete and the world's clock
reached it, the world went on without this robot: it resumes there
(``core.agent.rejoin.step_to_resume_at``).

Relay mode (``links.*`` not perfect, and em-sim): the robot hears no teammate directly. The
links deliver teammates' records and requests; each scan says how many have been delivered
in all (``ScanInput.delivered``), and the step waits for those instead of the barrier's
sequence numbers (``core.links.delivery_tally``; after ``barrier_timeout_s`` the missing
ones are written off, not waited for again). The robot sends at steps only
(``core.links.link_sender.LinkSender``: gap request, broadcast re-sends, new update), and
its command counts what it has sent (``team_messages``, ``team_requests``). Otherwise
re-sends asked of it go out rate-limited per requester and merged
(``core.links.resend``), at most every ``resend_interval_s``.

Rejoin: a robot whose first step is not step 0 was restarted after a crash. It asks its
teammates for its own earlier stream (a request with itself as owner; each teammate re-sends
what it holds of it), waits until it holds it up to the sequence number the world's barrier
names for it (``rejoin_settle_s``, at most ``rejoin_timeout_s``), then resumes
(``RobotAgent.resume``): its graph, targets and numbering continue where its stream left
off. With journals (``state_dir``), the robot journals every record it makes and every
teammate's record it applies, and a restarted robot reads them back first
(``ReadJournals`` -> ``journals_read``), so it rejoins even when no teammate holds its
stream. A restarted teammate's request for its own stream is served from what this robot
holds, at most once per ``request_period_s`` per teammate.

The world watch: a world that leaves the graph is logged at once; after
``world_lost_timeout_s`` the robot exits with code 4 (``Exit``).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from em_exploration_ros.core.agent.clock_watch import ClockWatch
from em_exploration_ros.core.agent.input_checks import (MAX_STEP_LEAD, RejectionLog,
                                                        barrier_problem,
                                                        history_request_problem,
                                                        request_problem, run_problem,
                                                        size_problem, step_problem)
from em_exploration_ros.core.agent.rejoin import (OwnHistoryRecovery, StreamArchive,
                                                  keyframe_ranges, records_beyond_the_team,
                                                  step_to_resume_at)
from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.agent.world_watch import WorldEvent, WorldWatch
from em_exploration_ros.core.links.delivery_tally import RECORDS, REQUESTS, DeliveryTally
from em_exploration_ros.core.links.link_model import FrameKind, perfect_links
from em_exploration_ros.core.links.link_sender import LinkSender
from em_exploration_ros.core.links.resend import ResendScheduler
from em_exploration_ros.core.node_settings import RobotNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.readings import LandmarkReading, TeammateReading
from em_exploration_ros.core.records.team_data import (MAX_SEQUENCE_LEAD, InvalidTeamUpdate,
                                                       TeamUpdate, TeamUpdateInbox)
from em_exploration_ros.core.records.wire_model import (command_to_twist, sim_time_s,
                                                        twist_to_increment_covariance)
from em_exploration_ros.core.sessions.effects import Dropped, LogLine, error, info, warn
from em_exploration_ros.core.sessions.robot_effects import (
    AppendJournal, CommandReply, Exit, Journal, KeyframeEstimate, PublishCorrespondences,
    PublishDecision, PublishEstimates, PublishHistory, PublishRequest, PublishTransforms,
    PublishUpdate, ReadJournals, SendCommand, SendFrame, StartJournal)
from em_exploration_ros.core.slam.team_slam import body_to_map_covariance

EXIT_WORLD_GONE = 4
#: The requester id of a process that is not a robot (the evaluator), as
#: em_exploration_msgs/TeamUpdateRequest.OBSERVER.
OBSERVER_ID = 2**32 - 1
#: Steps without an estimate of its own pose (10 s simulated) before a robot says so; again
#: after twice, four times, ... as many.
UNANCHORED_WARN_STEPS = 50


@dataclass(frozen=True)
class ScanInput:
    """What a robot takes from one sonar scan of the world: its ``step``, ``stamp`` (sec,
    nanosec, sim time), readings (body frame), the world's barrier ``team_sequences`` (the
    last sequence number of each robot the team holds; empty in real-time mode) and, in
    relay mode, the links' deliveries to it in all (records, requests)."""

    step: int
    stamp: tuple[int, int]
    landmarks: tuple[LandmarkReading, ...]
    teammates: tuple[TeammateReading, ...]
    team_sequences: tuple[int, ...] = ()
    delivered: tuple[int, int] = (0, 0)


@dataclass(frozen=True)
class OdometryInput:
    """Dead reckoning of one step: ``pose`` (3,) x [m], y [m], yaw [rad] in the robot's odom
    frame and the 6x6 twist covariance as on the wire."""

    pose: np.ndarray
    twist_covariance: np.ndarray


@dataclass(frozen=True)
class JournalRecords:
    """A journal as read back by the driver: what it is (``what``, ``path``, for log lines),
    a problem of the file (None if none) and its records decoded up to the first unusable
    one."""

    what: str
    path: str
    problem: str | None
    records: list[TeamUpdate]


def requester_name(requester_id: int) -> str:
    """How a log line names the sender of a request for records."""
    if requester_id == OBSERVER_ID:
        return "the evaluator (observer)"
    return f"robot {requester_id}"


class RobotSession:
    """One robot's team protocol (see module docstring). Every input method returns the
    effects to perform, in order. ``relay_mode``: None for the links' own
    (``links.*`` not perfect); ``journaled``: whether the driver keeps journals
    (``state_dir``); ``log_period_s``: the driver's period of throttled lines;
    ``make_agent``: makes the robot's brain from its id, the parameters and the anchor (a
    benchmark or test gives its own collaborators, ``RobotAgent``'s keyword arguments);
    ``started_s``: the driver's wall time [s, monotonic] at its start, if it wants a line
    when no scan came ``FIRST_STEP_AFTER_S`` after it."""

    def __init__(self, robot_id: int, params: ExplorationParams, settings: RobotNodeSettings,
                 relay_mode: bool | None = None, journaled: bool = False,
                 log_period_s: float = 5.0,
                 make_agent: Callable[[int, ExplorationParams, np.ndarray],
                                      RobotAgent] = RobotAgent,
                 started_s: float | None = None) -> None:
        self.robot_id = robot_id
        self._make_agent = make_agent
        self.params = params
        self.settings = settings
        self.num_robots = params.world.num_robots
        self.time_step_s = params.motion.time_step_s
        self.relay_mode = not perfect_links(params.links) if relay_mode is None else relay_mode
        self.journaled = journaled
        self.agent: RobotAgent | None = None
        self.inbox = TeamUpdateInbox(robot_id, self.num_robots)
        self.resends = ResendScheduler(settings.resend_interval_s)
        self.link_sender = LinkSender(robot_id, params)
        self.team_messages = self.team_requests = 0
        self.deliveries = DeliveryTally()  # relay mode
        self.archive = StreamArchive(robot_id, self.num_robots)
        self.rejected_updates = 0
        self._recovery: OwnHistoryRecovery | None = None
        self._journal_barrier: list[int] | None = None  # awaiting the journals read back
        self._journaled_team: list[TeamUpdate] = []  # applied by the earlier process
        self._served_history: dict[int, float] = {}
        self._served_history_log = RejectionLog(log_period_s)
        self._last_reply: CommandReply | None = None
        self._slam_recoveries_logged = 0
        self._scans: dict[int, ScanInput] = {}
        self._odometry: dict[int, OdometryInput] = {}
        self._next_step: int | None = None
        self._waiting_since: float | None = None
        self._last_request = 0.0
        self._barrier: dict[int, int] = {}
        self._world_watch = WorldWatch(settings.world_lost_timeout_s)
        # The world's steps (from the first scan on); with the start's wall time [s], it
        # says when none came yet.
        self._clock = ClockWatch(started_s=started_s)
        self._next_world_check_s = 0.0
        self._recorder_wait_since: float | None = None
        self._recorder_listens = not settings.wait_for_recorder
        self._recorder_missing: list[str] = []
        self._out: list = []

    # -- queries of the driver -----------------------------------------------------------

    @property
    def awaits_recorder(self) -> bool:
        """True until the recorder listens (or was waited for long enough): the driver then
        tells ``recorder_topics`` before each input."""
        return not self._recorder_listens

    def processed(self, step: int) -> bool:
        """True for a step this robot has processed (or skipped)."""
        return self._next_step is not None and step < self._next_step

    def sensor_step_problem(self, step: int, odometry: bool, world_step: int) -> str | None:
        """Reason to drop sensor data (a scan; ``odometry``: dead reckoning) of ``step``:
        outside the run, stale, too far ahead (``core.agent.input_checks.step_problem``:
        more than ``MAX_STEP_LEAD`` steps, unless the world's clock ``world_step`` is there
        already) or no room left for more pending steps."""
        pending = self._odometry if odometry else self._scans
        lead = MAX_STEP_LEAD
        if self._next_step is not None and step > self._next_step + lead:
            lead = max(lead, world_step - self._next_step)
        return (step_problem(step, self._next_step, self.params.run.max_steps, lead)
                or (size_problem(len(pending) + 1, MAX_STEP_LEAD, "pending steps")
                    if step not in pending else None))

    def run_problem(self, run_id: int) -> str | None:
        """Reason to drop a message of another run (its ``run_id`` not this robot's)."""
        return run_problem(run_id, self.settings.run_id)

    def barrier_problem(self, team_sequences: tuple[int, ...], step: int) -> str | None:
        """Reason to drop a scan of ``step`` for its barrier (implausible against what this
        robot received)."""
        expected_next = {r: self.inbox.next_expected(r) for r in range(self.num_robots)
                         if r != self.robot_id}
        return barrier_problem(team_sequences, self.num_robots, expected_next,
                               MAX_SEQUENCE_LEAD, own=(self.robot_id, step))

    def world_check_due(self, now_s: float) -> bool:
        """True when ``tick`` wants to know whether the world is on the graph (once a
        second)."""
        return now_s >= self._next_world_check_s

    # -- inputs --------------------------------------------------------------------------

    def anchor(self, pose: np.ndarray, now_s: float, world_step: int) -> list:
        """Robot 0's launch pose (x [m], y [m], yaw [rad], map frame): the agent starts.
        The anchor is the world's, so the world is there."""
        if self.agent is not None:
            return []
        self.agent = self._make_agent(self.robot_id, self.params, pose)
        self._world_heard(now_s)
        self._out.append(info(f"map anchored at robot 0's launch pose "
                              f"{np.round(pose, 3).tolist()}"))
        return self._process(now_s, world_step)

    def scan_again(self, step: int) -> list:
        """The world sent a step this robot processed again (its answer did not arrive):
        the same command again."""
        if self._last_reply is not None and self._last_reply.step == step:
            return [SendCommand(self._last_reply, again=True)]
        return []

    def scan(self, scan: ScanInput, now_s: float, world_step: int) -> list:
        """A checked scan (``sensor_step_problem``, ``barrier_problem``) of a step not
        processed yet."""
        self._scans[scan.step] = scan
        self._drop_stale_while_recovering(scan.step)
        self._world_heard(now_s)
        self._step_seen(scan.step, now_s)
        return self._process(now_s, world_step)

    def odometry(self, step: int, odometry: OdometryInput, now_s: float,
                 world_step: int) -> list:
        """Checked dead reckoning of ``step`` (one already processed is ignored: a re-sent
        step)."""
        if self.processed(step):
            return []
        self._odometry[step] = odometry
        self._drop_stale_while_recovering(step)
        return self._process(now_s, world_step)

    def team_update(self, record: TeamUpdate | InvalidTeamUpdate, sender: int | None,
                    now_s: float, world_step: int) -> list:
        """A teammate's record (``sender``: whose topic it came on; None when relayed), or
        why its message was refused."""
        self._file_team_update(record, sender)
        return self._process(now_s, world_step)

    def delivered_update(self, owner: int, record: TeamUpdate | InvalidTeamUpdate,
                         publication_sequence: int | None, now_s: float,
                         world_step: int) -> list:
        """Relay mode: a record of robot ``owner`` the links delivered (a teammate's, or a
        copy of this robot's own after a restart), with its delivery's publication sequence
        number if known."""
        self.deliveries.heard(RECORDS, publication_sequence)
        if owner == self.robot_id:
            self._receive_own(record)
        else:
            self._file_team_update(record, None)
        return self._process(now_s, world_step)

    def delivered_request(self, asker: int, owner: int, first_sequence: int,
                          last_sequence: int, publication_sequence: int | None, now_s: float,
                          world_step: int) -> list:
        """Relay mode: a request the links delivered: a teammate's for this robot's records
        (re-sent at a coming step, ``LinkSender``) or a restarted teammate's for its own."""
        self.deliveries.heard(REQUESTS, publication_sequence)
        if asker == owner:
            self._serve_history(asker, first_sequence, last_sequence, now_s)
        else:
            problem = (f"request for robot {owner}'s records" if owner != self.robot_id
                       else None) or request_problem(asker, first_sequence, last_sequence,
                                                     self.robot_id, self.num_robots,
                                                     OBSERVER_ID)
            if problem:
                self._out.append(Dropped(problem))
            elif self.agent is not None:
                self.link_sender.file_request(asker, first_sequence, last_sequence,
                                              self.agent.outbox.last_sequence)
        return self._process(now_s, world_step)

    def update_request(self, asker: int, owner: int, first_sequence: int, last_sequence: int,
                       now_s: float) -> list:
        """A request heard on the shared request topic: a teammate's (or the evaluator's)
        for some of this robot's records, re-sent rate-limited per requester; a restarted
        teammate's for its own stream, served from what this robot holds."""
        if self.relay_mode and asker != OBSERVER_ID:
            return []  # a teammate's request reaches this robot through the links
        if asker == owner == self.robot_id:  # its own request after a restart, heard back
            return []
        if asker == owner:
            self._serve_history(asker, first_sequence, last_sequence, now_s)
            return self._take()
        if owner != self.robot_id:
            return []  # addressed to a teammate
        problem = request_problem(asker, first_sequence, last_sequence, self.robot_id,
                                  self.num_robots, OBSERVER_ID)
        if problem:
            return [Dropped(problem)]
        if self.agent is None:
            return []
        if self.relay_mode:  # re-sent at a coming step, through the links
            self.link_sender.file_request(asker, first_sequence, last_sequence,
                                          self.agent.outbox.last_sequence)
            return []
        self.resends.request(asker, first_sequence, last_sequence,
                             self.agent.outbox.last_sequence)
        self._send_due_resends(now_s)
        return self._take()

    def own_history(self, record: TeamUpdate | InvalidTeamUpdate) -> list:
        """A teammate's copy of one of this robot's earlier records (after a restart)."""
        self._receive_own(record)
        return self._take()

    def teammate_liveliness(self, teammate: int, alive: bool, restarted: bool) -> list:
        """A teammate's liveliness changed."""
        if alive:
            return [info(f"teammate {teammate}: liveliness asserted"
                         + (" by a new process (restarted)" if restarted else ""))]
        return [warn(f"teammate {teammate}: liveliness lost (process dead, stopped or "
                     f"wedged, or its assertions lost on the network)")]

    def recorder_topics(self, missing: list[str]) -> None:
        """The topics this robot publishes that the recorder does not listen to yet."""
        self._recorder_missing = missing

    def journals_read(self, own: JournalRecords, team: JournalRecords, now_s: float,
                      world_step: int) -> list:
        """After a restart (``ReadJournals``): this robot's earlier records and the
        teammates' records it had applied, from its journals, checked against the world's
        barrier; the teammates' copies fill what they lack. Then it asks for its stream."""
        barrier, self._journal_barrier = self._journal_barrier, None
        taken_own = self._file_journaled(own, barrier, self._recovery.receive)
        teammates = self._file_journaled(team, barrier, self.inbox.receive)
        # Applied by the earlier process: the archive holds them from now on, so they are
        # served to a restarted teammate and not journaled again when applied.
        self.archive.keep(teammates)
        self._journaled_team = teammates
        self._out.append(StartJournal(Journal.TEAM, tuple(teammates), fresh=False))
        self._out.append(info(
            f"read {len(taken_own)} records of this robot's stream from its journal "
            f"{own.path} (the team holds it up to sequence "
            f"{self._recovery.needed_sequence}) and {len(teammates)} of its teammates' "
            f"from {team.path}"))
        self._last_request = now_s
        self._request(self.robot_id, 1, 0)
        return self._process(now_s, world_step)

    def tick(self, now_s: float, world_step: int, world_present: bool | None) -> list:
        """Wall time passed (10 Hz): re-send what was asked for; ask again for missing
        records (or, after a restart, for this robot's own stream); give up waiting on
        silent teammates; ``world_present`` (None: not looked, see ``world_check_due``):
        whether the world publishes this robot's scans."""
        if not self.relay_mode:  # relay mode: re-sends go at steps (LinkSender)
            self._send_due_resends(now_s)
        if world_present is not None:
            self._next_world_check_s = now_s + 1.0
            self._world_event(self._world_watch.update(world_present, now_s))
        self._watch_the_clock(world_step, now_s)
        if self._recorder_wait_since is not None and not self._recorder_listens:
            self._process(now_s, world_step, take=False)
        elif self._next_step is not None and any(step > self._next_step
                                                 for step in self._scans):
            self._process(now_s, world_step, take=False)  # the world's clock may be there
        if self._recovery is not None:
            if self._recovery.complete(now_s):
                self._process(now_s, world_step, take=False)
            elif (self._recovery.short_of
                  and now_s - self._last_request >= self.settings.request_period_s):
                self._last_request = now_s
                self._request(self.robot_id, 1, 0)
            return self._take()
        # Missing records are asked for while the step waits for them, and after it stopped
        # waiting (``waive``) until they arrive.
        wanted = self.inbox.waived()
        if self._waiting_since is not None:
            wanted.update({robot: max(limit, wanted.get(robot, 0))
                           for robot, limit in self._barrier.items()})
        if (not self.relay_mode and wanted
                and now_s - self._last_request >= self.settings.request_period_s):
            self._last_request = now_s
            for gap in self.inbox.missing(wanted):
                self._request(gap.robot_id, gap.first_sequence, gap.last_sequence)
        if (self._waiting_since is not None
                and now_s - self._waiting_since > self.settings.barrier_timeout_s):
            self._stop_waiting()
            self._process(now_s, world_step, ignore_barrier=True, take=False)
        return self._take()

    def team_graph_line(self) -> LogLine | None:
        """One line with the keyframes of every robot this robot's graph holds."""
        if self.agent is None:
            return None
        parts = []
        for robot in range(self.num_robots):
            indices, _ = self.agent.slam.trajectory(robot)
            parts.append(f"robot {robot}: {keyframe_ranges(indices)}")
        return info("team graph keyframes: " + "; ".join(parts))

    # -- stepping ------------------------------------------------------------------------

    def _take(self) -> list:
        out, self._out = self._out, []
        return out

    def _process(self, now_s: float, world_step: int, ignore_barrier: bool = False,
                 take: bool = True) -> list:
        """Process every step whose sensor data (and barrier) is complete, in order."""
        while self.agent is not None:
            if self._next_step is None and self._scans:
                self._next_step = min(self._scans)
                first = self._scans[self._next_step]
                if self._next_step > 0:
                    # Restarted: the deliveries before this process subscribed are not its own.
                    self.deliveries.start_at(first.delivered)
                    self._start_recovery(first, now_s)
                elif self.journaled:
                    self._out.append(StartJournal(Journal.OWN, (), fresh=True))
                    self._out.append(StartJournal(Journal.TEAM, (), fresh=True))
            if self._recovery is not None:
                if self._journal_barrier is not None or not self._recovery.complete(now_s):
                    break
                self._resume()
            step = self._next_step
            if step is None:
                break
            if step not in self._scans or step not in self._odometry:
                if not self._skip_to_the_worlds_step(world_step):
                    break
                step = self._next_step
            if not self._recorder_listens and not self._recorder_listening(now_s):
                break
            scan = self._scans[step]
            limits = {robot: int(seq) for robot, seq in enumerate(scan.team_sequences)
                      if robot != self.robot_id and not self.relay_mode}
            if not ignore_barrier and not self._team_data_held(scan, limits):
                if self._waiting_since is None:
                    self._waiting_since = now_s
                self._barrier = limits
                break
            self._waiting_since, ignore_barrier = None, False
            self._step(scan, self._odometry.pop(step), limits or None)
            del self._scans[step]
            self._next_step = step + 1
        return self._take() if take else []

    def _team_data_held(self, scan: ScanInput, limits: dict[int, int]) -> bool:
        """True when this robot holds the team data it must apply before the scan's step:
        in relay mode everything the links delivered, otherwise every teammate's records up
        to the barrier ``limits``."""
        if not self.relay_mode:
            return not limits or self.inbox.holds_up_to(limits)
        return self.deliveries.holds(scan.delivered)

    def _stop_waiting(self) -> None:
        """The step waited ``barrier_timeout_s``: go on without the missing records (or
        deliveries), and do not wait for them again at every step."""
        missing = "teammates' updates " + ", ".join(
            f"robot {gap.robot_id} #{gap.first_sequence}-{gap.last_sequence}"
            for gap in self.inbox.missing(self._barrier))
        self.inbox.waive(self._barrier)
        scan = self._scans.get(self._next_step)
        if self.relay_mode and scan is not None:
            needed = scan.delivered
            missing = (f"deliveries of the link relay (records, requests: held "
                       f"{self.deliveries.held()} of {needed})")
            self.deliveries.write_off(needed)
        self._out.append(warn(f"step {self._next_step}: {missing} still missing after "
                              f"{self.settings.barrier_timeout_s} s; going on without them"))
        self._barrier = {}

    def _skip_to_the_worlds_step(self, world_step: int) -> bool:
        """While the sensor data of the awaited step is missing: if a later step is complete
        and the world's clock reached it, the world went on without this robot (it was wedged,
        stopped or starved; ``core.agent.rejoin.step_to_resume_at``): drop the older data and
        resume at that step, with one moving step's odometry covariance for the motion since
        (``RobotAgent.skip_steps``). Returns True if it skipped."""
        awaited = self._next_step
        if all(step <= awaited for step in self._scans):  # the usual case: nothing later
            return False
        resume_at = step_to_resume_at(awaited, self._scans.keys() & self._odometry.keys(),
                                      world_step)
        if resume_at is None:
            return False
        self._resume_at(resume_at)
        self._waiting_since = None
        self.agent.skip_steps()
        self._out.append(warn(
            f"the world went on without this robot: resuming at step {resume_at}, "
            f"{resume_at - awaited} steps after step {awaited}, whose sensor data is lost "
            f"(the world held the vehicle still meanwhile)"))
        return True

    def _recorder_listening(self, now_s: float) -> bool:
        """Before the first step: True once the recorder subscribes to every topic this robot
        publishes, or ``recorder_wait_s`` passed (logged). Most topics are volatile: what is
        published before the recorder's subscription matched never reaches it. Until then
        the step waits (``tick`` looks again; the world re-sends the step)."""
        missing = self._recorder_missing
        if self._recorder_wait_since is None:
            self._recorder_wait_since = now_s
        waited = now_s - self._recorder_wait_since
        if not missing:
            self._out.append(info(f"the recorder listens to every topic of this robot after "
                                  f"{waited:.1f} s: answering the first step"))
        elif waited >= self.settings.recorder_wait_s:
            self._out.append(warn(
                f"the recorder does not listen to {', '.join(missing)} after {waited:.1f} s; "
                "answering the first step anyway (the recording misses what these topics "
                "carry before it subscribes)"))
        else:
            return False
        self._recorder_listens = True
        return True

    def _step(self, scan: ScanInput, odometry: OdometryInput,
              limits: dict[int, int] | None) -> None:
        agent, out = self.agent, self._out
        step = scan.step
        stamp_s = sim_time_s(step, self.time_step_s)
        released = self.inbox.pop_ready(limits)
        meetings_before = len(agent.meeting_effects)  # the teammates' records may add one
        ties_before = len(agent.slam.landmark_correspondences)  # (and correspondences)
        agent.apply_team_updates(released)
        for update in self.archive.keep(released):
            if self.journaled:
                out.append(AppendJournal(Journal.TEAM, update))
        decisions_before, given_up_before = len(agent.decisions), len(agent.given_up)
        command = agent.step(StepInput(
            step, stamp_s, odometry.pose,
            twist_to_increment_covariance(odometry.twist_covariance, self.time_step_s),
            scan.landmarks, scan.teammates))
        self._warn_if_unanchored(agent.steps_unanchored)
        update = agent.take_outgoing()
        if update is not None and self.journaled:
            out.append(AppendJournal(Journal.OWN, update))
        if self.relay_mode:
            self._send_frames(step, update)
        elif update is not None:
            self._publish(update, f"team update {update.sequence} (teammates will ask for it "
                                  f"again)")
        out.append(PublishTransforms(stamp_s, odometry.pose))
        linear_x, angular_z = command_to_twist(command.turn_rad, command.forward_m,
                                               self.time_step_s)
        ties = agent.slam.landmark_correspondences[ties_before:]
        if ties:  # published before the answer to the step
            out.append(PublishCorrespondences(step, scan.stamp, tuple(ties)))
        reply = CommandReply(self.robot_id, step, scan.stamp, linear_x, angular_z,
                             agent.outbox.last_sequence, self.team_messages,
                             self.team_requests, command.finished, float(agent.blocked_s),
                             len(agent.given_up), tuple(agent.given_up[given_up_before:]),
                             len(agent.slam.recoveries),
                             tuple(agent.meeting_effects[meetings_before:]))
        out.append(SendCommand(reply))
        self._last_reply = reply
        if step % self.params.slam.keyframe_interval_steps == 0:
            out.append(PublishEstimates(stamp_s, self._latest_keyframe()))
        if len(agent.decisions) != decisions_before:
            out.append(PublishDecision(stamp_s))
        self._log_slam_recoveries()

    def _latest_keyframe(self) -> KeyframeEstimate | None:
        """This robot's latest keyframe in its graph, with its marginal covariance (one
        iSAM2 marginal), in the map frame; None before it has one."""
        slam = self.agent.slam
        latest = slam.latest_index(self.robot_id)
        if latest is None:
            return None
        pose = slam.pose(self.robot_id, latest)
        covariance = body_to_map_covariance(pose, slam.pose_covariance(self.robot_id, latest))
        return KeyframeEstimate(
            sim_time_s(latest * self.params.slam.keyframe_interval_steps, self.time_step_s),
            pose, covariance)

    def _warn_if_unanchored(self, steps: int) -> None:
        """A robot without an estimate of its own pose stands still: say so after
        ``UNANCHORED_WARN_STEPS`` such steps, and again after 2x, 4x, ... as many."""
        intervals, rest = divmod(steps, UNANCHORED_WARN_STEPS)
        if steps == 0 or rest or intervals & (intervals - 1):
            return
        self._out.append(warn(
            f"no estimate of this robot's own pose for {steps} steps "
            f"({steps * self.time_step_s:g} s): nothing the team holds ties its trajectory "
            f"to the map (for a robot other than 0, a teammate's reading of it); it stands "
            f"still until a teammate's reading of it arrives"))

    def _log_slam_recoveries(self) -> None:
        """A warning for every SLAM update re-solved in batch since the last call."""
        recoveries = self.agent.slam.recoveries
        for recovery in recoveries[self._slam_recoveries_logged:]:
            self._out.append(warn(recovery.describe()))
        self._slam_recoveries_logged = len(recoveries)

    def _send_frames(self, step: int, update: TeamUpdate | None) -> None:
        """Relay mode: what this robot sends at ``step`` (``LinkSender``): a gap request, the
        due re-sends, its new update (counted)."""
        for frame in self.link_sender.frames(step, self.inbox, self.agent.outbox, update):
            if frame.kind == FrameKind.REQUEST:
                self.team_requests += 1
            else:
                self.team_messages += 1
            self._out.append(SendFrame(frame))

    def _publish(self, update: TeamUpdate, what: str) -> None:
        """Publish a record of this robot's stream on its update topic (counted)."""
        self.team_messages += 1
        self._out.append(PublishUpdate(update, what))

    def _request(self, owner: int, first_sequence: int, last_sequence: int) -> None:
        """Ask robot ``owner`` for records ``first..last`` of its stream (counted)."""
        self.team_requests += 1
        self._out.append(PublishRequest(owner, first_sequence, last_sequence))

    def _send_due_resends(self, now_s: float) -> None:
        if self.agent is None:
            return
        for due in self.resends.due(now_s):
            resent = self.agent.outbox.resend(due.first_sequence, due.last_sequence)
            for update in resent:
                self._publish(update, f"re-sent update {update.sequence}")
            if resent:
                self._out.append(info(
                    f"re-sent {len(resent)} of updates {resent[0].sequence}.."
                    f"{resent[-1].sequence} for {requester_name(due.requester_id)}",
                    throttle_key="resend"))

    def _file_team_update(self, record: TeamUpdate | InvalidTeamUpdate,
                          sender: int | None) -> None:
        """File a teammate's record in the inbox (dropped with a WARN if bad)."""
        try:
            if isinstance(record, InvalidTeamUpdate):
                raise record
            self.inbox.receive(record, sender)
        except InvalidTeamUpdate as problem:
            self.rejected_updates += 1
            self._out.append(Dropped(f"rejected a team update: {problem}"))

    def _receive_own(self, record: TeamUpdate | InvalidTeamUpdate) -> None:
        """A copy of one of this robot's earlier records, while it recovers its stream."""
        if self._recovery is None:
            return
        try:
            if isinstance(record, InvalidTeamUpdate):
                raise record
            self._recovery.receive(record)
        except InvalidTeamUpdate as problem:
            self.rejected_updates += 1
            self._out.append(warn(f"rejected a relayed record of this robot's history: "
                                  f"{problem}"))

    def _serve_history(self, requester: int, first_sequence: int, last_sequence: int,
                       now_s: float) -> None:
        """Re-send what this robot holds of a restarted teammate's stream (the records it
        applied, then those the barrier still holds back), the teammate's request checked
        first (``history_request_problem``), at most once per ``request_period_s`` per
        teammate, logged at most once per log period per teammate. Nothing tells a forged
        request from a real one (DDS carries no identity without security), so that bound
        is what a forger gets."""
        problem = history_request_problem(requester, first_sequence, last_sequence,
                                          self.robot_id, self.num_robots)
        if problem:
            self._out.append(Dropped(problem))
            return
        last = self._served_history.get(requester, -float("inf"))
        if now_s - last < self.settings.request_period_s:
            return
        self._served_history[requester] = now_s
        held = self.archive.held(requester) + self.inbox.held_back(requester)
        self._out.append(PublishHistory(requester, tuple(held)))
        served = self._served_history_log.note(str(requester), now_s)
        if served is not None:
            times = f" ({served} times since the last line)" if served > 1 else ""
            self._out.append(info(f"robot {requester} asked for its own stream (restarted): "
                                  f"re-sent the {len(held)} records of it this robot "
                                  f"holds{times}"))

    # -- world watch ---------------------------------------------------------------------

    def _world_heard(self, now_s: float) -> None:
        """A message of the world arrived, so it is there: a world that leaves before the
        once-a-second graph check first saw it is still noticed when it leaves."""
        self._world_event(self._world_watch.update(True, now_s))

    def _world_event(self, event: WorldEvent | None) -> None:
        timeout = self.settings.world_lost_timeout_s
        if event == WorldEvent.LOST:
            self._out.append(warn(f"the world left the ROS graph (no publisher of "
                                  f"/robot_{self.robot_id}/sonar); waiting up to "
                                  f"{timeout:g} s for it to come back"))
        elif event == WorldEvent.BACK:
            self._out.append(info("the world is back on the ROS graph"))
        elif event == WorldEvent.GONE:
            self._out.append(error(f"the world has been gone for {timeout:g} s; exiting "
                                   f"(code {EXIT_WORLD_GONE})"))
            self._out.append(Exit(EXIT_WORLD_GONE))

    def _step_seen(self, step: int, now_s: float) -> None:
        """A step of the world seen (a scan, or /clock once a scan came): say so when the
        world's steps come again after ``ClockWatch`` said they stopped."""
        stood_s = self._clock.seen(step, now_s)
        if stood_s is not None:
            self._out.append(info(f"the world's steps come again: step {step} after "
                                  f"{stood_s:.1f} s without a new one"))

    def _watch_the_clock(self, world_step: int, now_s: float) -> None:
        """Warn when no new step came from the world for ``CLOCK_STOPPED_S`` wall seconds
        (then every ``CLOCK_STOPPED_REPEAT_S``) while the run is not over, saying what this
        robot knows of who holds the step (in lockstep the world waits for every answer).
        Before the first scan, say so as information ``FIRST_STEP_AFTER_S`` after the start
        (then as often): a robot restarted by hand that gets nothing from the world waited
        in silence."""
        if self._clock.step is None:  # not started: at a first start the world waits
            waited_s = self._clock.no_first_step(now_s)
            if waited_s is not None:
                self._out.append(info(
                    f"no scan from the world yet, {waited_s:.0f} s after this robot started "
                    f"(at a run's start the world holds its first step until the team is "
                    f"connected)"))
            return
        self._step_seen(world_step, now_s)
        if self._run_over():
            return
        stood_s = self._clock.stopped(now_s)
        if stood_s is None:
            return
        step = self._clock.step
        if self._recovery is not None:
            known = "this robot recovers its stream after a restart"
        elif self._waiting_since is not None:
            known = (f"this robot waits for teammates' records before it answers step "
                     f"{self._next_step}")
        elif self._last_reply is not None and self._last_reply.step == step:
            known = "this robot answered it"
        else:
            known = "this robot has not answered it"
        self._out.append(warn(f"no new step from the world for {stood_s:.1f} s (last step "
                              f"{step}; {known})"))

    def _run_over(self) -> bool:
        """True once no further step is due: the run's last step processed, or this robot
        and every teammate finished (the world then stops stepping)."""
        if self._next_step is not None and self._next_step > self.params.run.max_steps:
            return True
        agent = self.agent
        return (agent is not None and agent.finished
                and len(agent.finished_teammates) >= self.num_robots - 1)

    # -- rejoin --------------------------------------------------------------------------

    def _drop_stale_while_recovering(self, step: int) -> None:
        """While a restarted robot recovers its stream, the world goes on without it (its
        vehicle stands still) and may run thousands of steps ahead: keep only the newest
        step's sensor data, so that it resumes at the world's open step instead of
        replaying stale steps it could never catch up with."""
        if self._recovery is None or self._next_step is None or step <= self._next_step:
            return
        self._resume_at(step)

    def _resume_at(self, step: int) -> None:
        """Make ``step`` the next one to process: the sensor data of earlier steps goes."""
        for pending in (self._scans, self._odometry):
            for old in [k for k in pending if k < step]:
                del pending[old]
        self._next_step = step

    def _start_recovery(self, scan: ScanInput, now_s: float) -> None:
        """This process starts in the middle of a run: it was restarted after a crash."""
        barrier = list(scan.team_sequences)
        needed = int(barrier[self.robot_id]) if barrier else 0
        self._recovery = OwnHistoryRecovery(self.robot_id, self.num_robots, needed, now_s,
                                            self.settings.rejoin_settle_s,
                                            self.settings.rejoin_timeout_s)
        self._out.append(warn(
            f"first step is {scan.step}, not 0: restarted in a running team; asking the "
            f"teammates for this robot's stream (the team holds it up to sequence {needed})"))
        if self.journaled:  # read back first (``journals_read``), then asked for
            self._journal_barrier = barrier
            self._out.append(ReadJournals())
            return
        self._last_request = now_s
        self._request(self.robot_id, 1, 0)

    def _file_journaled(self, journal: JournalRecords, team_holds: list[int],
                        file: Callable[[TeamUpdate], object]) -> list[TeamUpdate]:
        """File a journal's records with ``file`` up to the first one it refuses (WARN);
        none if they cannot be this run's (WARN). Returns those filed."""
        if journal.problem is not None:
            self._out.append(warn(f"{journal.what}: {journal.problem}"))
        # (Without a barrier, in real-time mode, there is nothing to check them against.)
        foreign = (records_beyond_the_team(journal.records, team_holds) if team_holds
                   else None)
        if foreign is not None:
            self._out.append(warn(f"{journal.what} {journal.path}: {foreign}"))
            return []
        taken = []
        for update in journal.records:
            try:
                file(update)
            except InvalidTeamUpdate as problem:
                self._out.append(warn(f"{journal.what} {journal.path}: record "
                                      f"{update.robot_id}/{update.sequence} refused "
                                      f"({problem}); not read on"))
                break
            taken.append(update)
        return taken

    def _take_journaled_team(self) -> list[TeamUpdate]:
        """The teammates' records the earlier process applied (its team journal), in its
        order, taken out of the inbox to be replayed by ``RobotAgent.resume``."""
        journaled, self._journaled_team = self._journaled_team, []
        limits: dict[int, int] = {}
        for update in journaled:
            limits[update.robot_id] = max(update.sequence, limits.get(update.robot_id, 0))
        released = {(u.robot_id, u.sequence) for u in self.inbox.pop_ready(limits)}
        return [u for u in journaled if (u.robot_id, u.sequence) in released]

    def _resume(self) -> None:
        recovery, self._recovery = self._recovery, None
        history = recovery.history()
        if recovery.short_of:
            self._out.append(error(
                f"resuming without {recovery.short_of} records of this robot's stream (up to "
                f"sequence {recovery.needed_sequence}): no teammate sent them; they are "
                f"re-sent empty, and the motion since the last keyframe recovered is linked "
                f"with the odometry covariance of every step since"))
        self.agent.resume(history, recovery.needed_sequence, self._next_step,
                          self._take_journaled_team())
        if self.journaled:
            self._out.append(StartJournal(Journal.OWN, tuple(self.agent.outbox.resend(1, 0)),
                                          fresh=False))
        self._log_slam_recoveries()
        keyframes = np.array([keyframe.index for update in history
                              for keyframe in update.keyframes], dtype=int)
        self._out.append(info(
            f"rejoined: recovered {len(history)} records of this robot's stream (keyframes "
            f"{keyframe_ranges(keyframes)}, {len(self.agent.decisions)} targets); continuing "
            f"at sequence {self.agent.outbox.last_sequence + 1}"))
