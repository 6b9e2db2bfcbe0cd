"""What one robot offers its links at a step: a gap request, re-sends, its new update.

Over modelled links (``core/links/link_model.py``) a robot sends its team data at steps only, so
that a seeded lockstep run repeats exactly: while processing step ``k`` it offers, in this
order,

1. a request for one gap of its inbox, addressed to the stream's owner (``GapRequests``:
   at most one per ``links.repair_interval_s``, teammates in turn);
2. the records teammates asked it for, each re-sent as a **broadcast**: an acoustic modem
   is heard by every teammate in range, so a re-send may fill the same gap of several
   teammates at the cost of one transmission (``ResendScheduler``: at most every
   ``repair_interval_s`` per requester and at most half the queue at a time);
3. its new update (broadcast), if it has one.

em-sim (``core/sessions/team_runner.py``) and the ROS robot node in relay mode both use this
class, so they send the same frames at the same steps.
"""
from __future__ import annotations

from em_exploration_ros.core.links.gap_requests import GapRequests
from em_exploration_ros.core.links.link_model import Frame, FrameKind
from em_exploration_ros.core.links.resend import MAX_RESEND_RECORDS, ResendScheduler
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import TeamUpdate, TeamUpdateInbox, TeamUpdateOutbox
from em_exploration_ros.core.records.team_wire import cdr_size, request_cdr_size


class LinkSender:
    """One robot's step-driven sending over modelled links (see module docstring)."""

    def __init__(self, robot_id: int, params: ExplorationParams) -> None:
        n = params.world.num_robots
        links = params.links
        time_step_s = params.motion.time_step_s
        self.robot_id = robot_id
        self.teammates = tuple(r for r in range(n) if r != robot_id)
        self.time_step_s = time_step_s
        repair_steps = max(1, round(links.repair_interval_s / time_step_s))
        self.gap_requests = GapRequests(robot_id, n, repair_steps)
        self.resends = ResendScheduler(
            links.repair_interval_s, min(MAX_RESEND_RECORDS, max(1, links.queue_frames // 2)))

    def file_request(self, requester_id: int, first_sequence: int, last_sequence: int,
                     latest_sequence: int) -> None:
        """A request for records of this robot's stream reached it (through the links)."""
        self.resends.request(requester_id, first_sequence, last_sequence, latest_sequence)

    def frames(self, step: int, inbox: TeamUpdateInbox, outbox: TeamUpdateOutbox,
               update: TeamUpdate | None) -> list[Frame]:
        """The frames to offer while processing ``step``, in sending order: a gap request
        of ``inbox`` (payload: its ``MissingRange``), the due re-sends from ``outbox``
        and ``update`` (payload: the ``TeamUpdate``)."""
        frames = []
        gap = self.gap_requests.due(step, inbox)
        if gap is not None:
            frames.append(Frame(FrameKind.REQUEST, self.robot_id, (gap.robot_id,),
                                gap.first_sequence, request_cdr_size(), step, gap))
        for due in self.resends.due(step * self.time_step_s):
            for record in outbox.resend(due.first_sequence, due.last_sequence):
                frames.append(Frame(FrameKind.RESEND, self.robot_id, self.teammates,
                                    record.sequence, cdr_size(record), step, record))
        if update is not None:
            frames.append(Frame(FrameKind.UPDATE, self.robot_id, self.teammates,
                                update.sequence, cdr_size(update), step, update))
        return frames
