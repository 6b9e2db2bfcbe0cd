"""The world's side of the lockstep protocol, one step at a time (no ROS; wall time given).

Step k is *open* while the world waits for every live robot's answer (its motion command
for step k). The barrier repairs itself before it gives up on anyone:

- a robot whose answer is missing ``resend_period_s`` after the step opened (or after the
  previous re-send) is due a re-send of the step's sensor data (``due_for_resend``): a
  robot that missed the start or lost a packet answers then; a robot that already
  answered but whose answer was lost answers again;
- a robot still silent ``robot_timeout_s`` after the step opened for it is *stopped*: it
  stands still and is not waited for, and keeps its last barrier entry. A robot whose
  liveliness the middleware reports lost is *suspect* (``suspect``) until it is reported
  alive again (``trust``): it gets only ``suspect_timeout_s`` to answer, counted from the
  loss report for as long as it has not answered since (not again from each new step), else
  from the step's opening. A live robot answers within a second, so a liveliness report
  lost on a lossy network changes nothing, while a dead or wedged robot is given up after
  the lease plus ``suspect_timeout_s`` instead of ``robot_timeout_s``; so is a robot whose
  new process reports its liveliness (``restarted``) for the open step;
- a stopped robot that answers again (a wedged process that recovered, or a process
  restarted with the same id) *rejoins*: an answer to the open step is used at once, an
  answer to an earlier step puts it back on the list of robots the open step waits for,
  with a fresh deadline;
- a robot whose new process reported its liveliness is *rejoining* until it answers, for
  at most ``robot_timeout_s``: the run is not over while it is (``all_done``), and when no
  robot is live, the open step waits for it (``complete``) instead of the world stepping
  on, or over, with nobody (every robot of a ``--respawn`` team killed within seconds
  once ended the mission).

Nothing is kept beyond one step: bookkeeping is O(number of robots).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class StepAnswer:
    """A robot's MotionCommand for one step: velocity (m/s, rad/s), barrier entry, finished,
    and how many team messages (update-topic records, requests) it has published in all
    (the link relay's hand-over, ``core/links/link_relay.py``)."""

    linear_x: float
    angular_z: float
    team_sequence: int
    finished: bool
    team_messages: int = 0
    team_requests: int = 0


#: What a robot that does not move answers.
STAND_STILL = StepAnswer(0.0, 0.0, 0, False)


class LockstepBarrier:
    """Book-keeping of the lockstep protocol (see module docstring)."""

    ACCEPTED, REJOINED, STALE, DUPLICATE, CONFLICT, FUTURE = (
        "accepted", "rejoined", "stale", "duplicate", "conflicting", "future")

    def __init__(self, num_robots: int, robot_timeout_s: float,
                 resend_period_s: float = math.inf, suspect_timeout_s: float = math.inf) -> None:
        """``robot_timeout_s``: wall seconds a robot may stay silent on a step before it is
        stopped (``suspect_timeout_s`` for a suspect robot, if shorter);
        ``resend_period_s``: wall seconds between re-sends of a step to a robot whose answer
        is missing (inf: never)."""
        self.num_robots = num_robots
        self.robot_timeout_s = robot_timeout_s
        self.resend_period_s = resend_period_s
        self.suspect_timeout_s = suspect_timeout_s
        self.suspects: set[int] = set()
        self._silent_since_report: dict[int, float] = {}  # suspect -> its loss report [s]
        self.step = -1
        self.stopped: set[int] = set()
        self.rejoining: dict[int, float] = {}  # robot -> wall deadline [s]
        self.finished = [False] * num_robots
        self.team_sequences = [0] * num_robots
        self._answers: dict[int, StepAnswer] = {}
        self._deadline_s = [math.inf] * num_robots
        self._next_resend_s = [math.inf] * num_robots

    def open(self, step: int, now_s: float) -> None:
        """Start waiting for the answers to ``step``; ``now_s`` is monotonic wall time [s]."""
        self.step = step
        self._answers = {}
        for robot in range(self.num_robots):
            self._arm(robot, now_s)

    def _arm(self, robot: int, now_s: float) -> None:
        self._deadline_s[robot] = now_s + self._timeout_s(robot)
        reported_s = self._silent_since_report.get(robot)
        if robot in self.suspects and reported_s is not None:
            # Silent since its loss was reported: a new step does not restart its short
            # timeout (two robots wedged at once, one of them after answering the open step,
            # held the team twice as long).
            self._deadline_s[robot] = min(self._deadline_s[robot],
                                          reported_s + self.suspect_timeout_s)
        self._next_resend_s[robot] = now_s + self.resend_period_s

    def _timeout_s(self, robot: int) -> float:
        if robot in self.suspects:
            return min(self.robot_timeout_s, self.suspect_timeout_s)
        return self.robot_timeout_s

    def suspect(self, robot: int, now_s: float) -> None:
        """The robot's liveliness was reported lost at ``now_s``: it has at most
        ``suspect_timeout_s`` from now to answer the open step (and each later one) until
        ``trust``."""
        self.suspects.add(robot)
        self._silent_since_report.setdefault(robot, now_s)
        self._deadline_s[robot] = min(self._deadline_s[robot], now_s + self._timeout_s(robot))

    def trust(self, robot: int, now_s: float) -> None:
        """The robot's process reported its liveliness again at ``now_s``: it was alive and
        only its assertions were lost on the network (as under packet loss), so it gets
        ``robot_timeout_s`` again, on the open step from ``now_s``. (Healthy robots on lossy
        links kept the short deadline of their last loss report, were stopped when a step
        took longer, and were restarted by ``run_team.sh --respawn``.)"""
        self._silent_since_report.pop(robot, None)
        if robot in self.suspects:
            self.suspects.discard(robot)
            self._deadline_s[robot] = max(self._deadline_s[robot], now_s + self.robot_timeout_s)

    def restarted(self, robot: int, now_s: float) -> None:
        """A new process of the robot reported its liveliness at ``now_s``: the one that was
        to answer is gone, even if its own loss was never reported (a process restarted
        within its liveliness lease). The new one first recovers its stream from its
        teammates, so, as after a loss, it has ``suspect_timeout_s`` from now to answer the
        open step; later steps get ``robot_timeout_s`` again. It is *rejoining* until it
        answers, for at most ``robot_timeout_s``."""
        self.suspect(robot, now_s)
        self.suspects.discard(robot)
        self._silent_since_report.pop(robot, None)
        self.rejoining[robot] = now_s + self.robot_timeout_s

    def answer(self, robot_id: int, step: int, answer: StepAnswer, now_s: float) -> str:
        """File a robot's answer; returns how it was taken (ACCEPTED, REJOINED or why not).

        REJOINED: a stopped robot answered again and is waited for from now on (its answer
        counts when it is for the open step), with ``robot_timeout_s`` to answer the open
        step: its answer shows it alive, so a loss reported before (suspect) no longer
        shortens it. (With the 4 s of a suspect, a restarted robot catching up from an old
        step was stopped again, the world ran on with the others more than 1000 steps
        ahead, and the robot never rejoined.) CONFLICT: a second answer to the open step
        that differs from the first, which stands (two publishers on one robot's topic)."""
        rejoined = robot_id in self.stopped and step <= self.step
        self._silent_since_report.pop(robot_id, None)  # any answer shows the process alive
        if step <= self.step:
            self.rejoining.pop(robot_id, None)
        if rejoined:
            self.stopped.discard(robot_id)
            self.suspects.discard(robot_id)
            self._arm(robot_id, now_s)
        if step < self.step:
            return self.REJOINED if rejoined else self.STALE
        if step > self.step:
            return self.FUTURE
        if robot_id in self._answers:
            return self.DUPLICATE if self._answers[robot_id] == answer else self.CONFLICT
        if robot_id in self.stopped:  # stopped and answering the open step: handled above
            return self.STALE
        self._answers[robot_id] = answer
        return self.REJOINED if rejoined else self.ACCEPTED

    def answers(self) -> dict[int, StepAnswer]:
        """The answers to the open step received so far, by robot id."""
        return dict(self._answers)

    def waiting_for(self) -> list[int]:
        """Live robots that have not answered the open step, in id order."""
        return [r for r in range(self.num_robots)
                if r not in self.stopped and r not in self._answers]

    def due_for_resend(self, now_s: float) -> list[int]:
        """Robots (live or stopped) without an answer to the open step whose re-send is due
        at ``now_s``; each is due again ``resend_period_s`` later."""
        due = []
        for robot in range(self.num_robots):
            if robot not in self._answers and now_s >= self._next_resend_s[robot]:
                due.append(robot)
                self._next_resend_s[robot] = now_s + self.resend_period_s
        return due

    def expire(self, now_s: float) -> list[int]:
        """Stop the live robots still silent at their deadline, and stop waiting for
        rejoining robots past theirs; returns the robots newly stopped."""
        late = [r for r in self.waiting_for() if now_s >= self._deadline_s[r]]
        self.stopped.update(late)
        for robot, deadline_s in list(self.rejoining.items()):
            if now_s >= deadline_s:
                del self.rejoining[robot]
        return late

    def stop(self, robot_ids: list[int]) -> list[int]:
        """Treat robots as stopped from now on (e.g. never connected); returns those that
        were live."""
        newly = [r for r in robot_ids if r not in self.stopped]
        self.stopped.update(newly)
        return newly

    @property
    def complete(self) -> bool:
        """True when every live robot has answered the open step, and some robot is live or
        none is rejoining."""
        if len(self.stopped) == self.num_robots and self.rejoining:
            return False
        return not self.waiting_for()

    def close(self) -> list[StepAnswer]:
        """The step's answers in robot id order (stopped robots stand still) and update the
        barrier (team sequences) and finished flags for the next step."""
        answers = []
        for robot in range(self.num_robots):
            answer = self._answers.get(robot)
            if answer is None:
                answers.append(STAND_STILL)
                continue
            answers.append(answer)
            self.team_sequences[robot] = answer.team_sequence
            self.finished[robot] = answer.finished
        return answers

    @property
    def team_lost(self) -> bool:
        """True when the run could end only because robots are lost: every robot has
        finished or is stopped and not rejoining, and some stopped one had not finished."""
        return self.all_done and any(r in self.stopped and not self.finished[r]
                                     for r in range(self.num_robots))

    @property
    def all_done(self) -> bool:
        """True when every robot has finished or is stopped and not rejoining."""
        return all(self.finished[r] or (r in self.stopped and r not in self.rejoining)
                   for r in range(self.num_robots))
