"""The world's relay of team data through the link model in the ROS system (no ROS here).

With links that are not perfect (``links.*``, ``core/links/link_model.py``) no robot hears a
teammate's topics directly: the world node, which alone knows the true positions, relays
every piece of team data through ``TeamLinks`` and delivers it on the receiver's own
topics. The node hands this class what it hears, with the step open at that moment:

- on ``/robot_<s>/team/updates``: a record of robot s's stream. A sequence number above the
  highest s has published is its new update (``FrameKind.UPDATE``), any other a re-send
  (``RESEND``); both are broadcast to every teammate;
- on ``/team/update_requests`` from robot r for robot o's records: a ``REQUEST`` to o; a
  robot asking for its own stream (it was restarted) asks every teammate;
- on ``/robot_<i>/team/history`` from teammate s: a ``HISTORY`` frame from s to i.

Lockstep, exactly as em-sim: a robot publishes what it sends at step k before it answers
step k, and its answer (MotionCommand) says how many update-topic messages and requests its
process has published so far. The world closes step k only once the relay ``holds`` them all
(DDS keeps one writer's messages in order, not those of different topics), then calls
``transmit(k, positions)``. Before it publishes step k+1 it delivers ``deliveries(k+1)`` and
each robot's SonarScan carries how many deliveries of each kind it has been sent in all,
so the robot processes step k+1 only once it holds them. Every frame of a step is thus
offered, queued, drawn and delivered as in ``TeamRunner``, and seeded runs choose the same
targets in both.

How many messages a robot has published is read from each message's publication sequence
number when the middleware gives one (the writer's own count, from 1 in every process): the
relay then knows how many a restarted process published, those it published before the
relay's reader matched its writer included, which DDS (volatile durability) never delivers.
Without one, the relay counts what it hears. Either way a count that is never reached costs
one wait: ``written_off`` takes the answers' counts as heard.

A restarted robot's history exchange happens outside the steps (its frames join the step
open when they arrive), so runs with restarts are not repeatable frame for frame.

The world's session (``core/sessions/world_session.py``) owns the relay, in em-world's relay
mode and always in em-sim, whose robots hand it their frames as they are (``offer``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from em_exploration_ros.core.links.delivery_tally import published_so_far
from em_exploration_ros.core.links.link_model import (Delivery, DeliveryLedger, Frame, FrameKind,
                                                      TeamLinks)
from em_exploration_ros.core.params import ExplorationParams


@dataclass(frozen=True)
class SentCounts:
    """How many messages a robot says it has published (its MotionCommand): records on its
    update topic (new updates and re-sends) and requests."""

    updates: int
    requests: int


class LinkRelay:
    """Team data through the link model, with the counts of the lockstep hand-over (see
    module docstring). Payloads are opaque: the node's messages, delivered as received."""

    def __init__(self, params: ExplorationParams) -> None:
        n = params.world.num_robots
        self.num_robots = n
        self.links = TeamLinks(params.links, n, params.motion.time_step_s, params.run.seed)
        self.ledger = DeliveryLedger(n)
        self.received = [SentCounts(0, 0) for _ in range(n)]
        self.delivered_updates = [0] * n
        self.delivered_requests = [0] * n
        self._latest_sequence = [0] * n

    def _teammates(self, robot: int) -> tuple[int, ...]:
        return tuple(r for r in range(self.num_robots) if r != robot)

    def update_heard(self, sender: int, sequence: int, size_bytes: int, step: int,
                     payload: Any, publication_sequence: int | None = None) -> FrameKind:
        """A record of ``sender``'s stream on its update topic while ``step`` is open, with the
        message's publication sequence number if known; returns whether it was taken as the
        new update or a re-send."""
        counts = self.received[sender]
        self.received[sender] = SentCounts(
            published_so_far(counts.updates, publication_sequence), counts.requests)
        kind = FrameKind.RESEND
        if sequence > self._latest_sequence[sender]:
            kind = FrameKind.UPDATE
            self._latest_sequence[sender] = sequence
            self.ledger.sent(sender, sequence, step)
        self.links.offer(Frame(kind, sender, self._teammates(sender), sequence, size_bytes,
                               step, payload))
        return kind

    def request_heard(self, requester: int, owner: int, first_sequence: int,
                      size_bytes: int, step: int, payload: Any,
                      publication_sequence: int | None = None) -> None:
        """A robot's request for records of ``owner``'s stream while ``step`` is open, with the
        message's publication sequence number if known."""
        counts = self.received[requester]
        self.received[requester] = SentCounts(
            counts.updates, published_so_far(counts.requests, publication_sequence))
        receivers = self._teammates(requester) if owner == requester else (owner,)
        self.links.offer(Frame(FrameKind.REQUEST, requester, receivers, first_sequence,
                               size_bytes, step, payload))

    def history_heard(self, sender: int, owner: int, sequence: int, size_bytes: int,
                      step: int, payload: Any) -> None:
        """``sender``'s copy of a record of restarted robot ``owner``'s stream."""
        self.links.offer(Frame(FrameKind.HISTORY, sender, (owner,), sequence, size_bytes,
                               step, payload))

    def offer(self, frame: Frame) -> None:
        """A frame handed over in one process (em-sim), its kind known from its sender
        (``link_sender.LinkSender``); a new update's first sending goes into the ledger."""
        if frame.kind == FrameKind.UPDATE:
            self.ledger.sent(frame.sender, frame.key, frame.sent_step)
        self.links.offer(frame)

    def holds(self, sent: dict[int, SentCounts]) -> list[int]:
        """The robots among ``sent`` (robot -> what its answer says it published) whose
        messages have not all been heard yet. A restarted process whose first message has not
        been heard yet is compared with its predecessor's count, so it may not be waited for."""
        return [robot for robot, counts in sorted(sent.items())
                if self.received[robot].updates < counts.updates
                or self.received[robot].requests < counts.requests]

    def written_off(self, sent: dict[int, SentCounts]) -> None:
        """Take what ``sent`` counts as heard: the world gave up waiting for it. Messages that
        never come are then not waited for again at every step."""
        for robot, counts in sent.items():
            heard = self.received[robot]
            self.received[robot] = SentCounts(max(heard.updates, counts.updates),
                                              max(heard.requests, counts.requests))

    def transmit(self, step: int, positions: np.ndarray) -> None:
        """Start the transmissions of ``step`` with the true positions ``(N, 2)`` [m]."""
        self.links.transmit(step, positions)

    def deliveries(self, step: int) -> list[Delivery]:
        """What reaches each receiver before ``step``, counted into ``delivered_*``."""
        due = self.links.deliveries(step)
        for delivery in due:
            frame, receiver = delivery.frame, delivery.receiver
            if frame.kind == FrameKind.REQUEST:
                self.delivered_requests[receiver] += 1
                continue
            self.delivered_updates[receiver] += 1
            if frame.kind != FrameKind.HISTORY:
                self.ledger.delivered(frame.sender, receiver, frame.key, step)
        return due

    def summary_line(self, step: int) -> str:
        """What the links did before ``step``, for the world's log."""
        counts = self.links.counts
        updates = self.ledger.counts(step)
        return (f"links: {updates.sent} (update, teammate) pairs: {updates.on_time} on time, "
                f"{updates.late} late, {updates.never} never; frames per receiver: "
                f"{counts.delivered} delivered, {counts.lost} lost, {counts.out_of_range} out "
                f"of range, {counts.dropped} dropped (full queue); {counts.bytes_sent} bytes sent")
