"""The links between robots: which transmission reaches which teammate, and when.

The simulator side owns this model (it alone knows the true positions). Every piece of
team data a robot sends - a ``TeamUpdate`` of its stream, a re-sent one, a request for
missing records - is a *frame* offered to the sender's channel while it processes step
``k``. The channel is one shared acoustic-modem-like medium per sender:

- **Bandwidth** (``links.bandwidth_bytes_per_s`` B, 0 = unlimited): a frame of S bytes
  occupies the sender's channel for S / B seconds; frames wait in a FIFO queue of at most
  ``links.queue_frames`` frames per sender. A frame offered to a full queue **is dropped**
  (tail drop: the frames already waiting keep their places; the stream's gap repair asks
  for the dropped record again). A frame whose transmission starts is no longer in the
  queue.
- **Range** (``links.range_m``, 0 = unlimited): a frame reaches a receiver only if the two
  robots' TRUE positions at the step the transmission starts are at most this far apart.
- **Loss** (``links.loss_probability``): each (frame, receiver) is lost independently with
  this probability. The draw is counter based: a hash of (seed, frame kind, sender,
  receiver, stream key, step the transmission starts), never of the order in which frames
  happen to reach the relay, so em-sim and the ROS relay draw the same.
- **Latency** (``links.latency_s``): added after the end of the transmission.

A frame sent while processing step ``k`` is delivered before the receiver processes step
``m``, the first step whose time ``m * dt`` is at or after the arrival time, and never
before ``k + 1``: with perfect links (every parameter at its default) every frame of step
``k`` arrives at step ``k + 1``, which is exactly the team's timing without a link model.

Nothing here knows ROS or the robots' contents: a frame carries an opaque payload.
"""
from __future__ import annotations

import hashlib
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

from em_exploration_ros.core.params import LinkParams

#: Floating-point slack when a time is compared with a step's time [s].
_TIME_EPS_S = 1e-9


class FrameKind(IntEnum):
    """What a frame carries (part of the loss draw's key); frames a sender offers in one
    step join its queue in this order (small control frames first)."""

    REQUEST = 0  #: a request for missing records of the receiver's stream
    RESEND = 1  #: a record of the sender's stream sent again on request
    UPDATE = 2  #: a record of the sender's stream, first transmission
    HISTORY = 3  #: a restarted robot's own records, relayed back by a teammate


@dataclass
class Frame:
    """One transmission offered to a sender's channel.

    ``receivers``: the robots it is addressed to (a broadcast update: every teammate; a
    re-send or request: one robot). ``key``: the stream key of the loss draw (a sequence
    number, or the first sequence of a requested range). ``size_bytes``: bytes on the
    wire. ``sent_step``: the step during which the sender produced it.
    """

    kind: FrameKind
    sender: int
    receivers: tuple[int, ...]
    key: int
    size_bytes: int
    sent_step: int
    payload: Any = None


@dataclass(frozen=True)
class Delivery:
    """A frame that reaches ``receiver`` before it processes ``step``."""

    step: int
    receiver: int
    frame: Frame


@dataclass
class LinkCounts:
    """What the links did with the frames offered so far (one count per frame and
    addressed receiver): ``delivered``, ``lost`` (loss draw), ``out_of_range``, ``dropped``
    (offered to a full queue: tail drop, the queued frames stay), and the bytes
    transmitted."""

    delivered: int = 0
    lost: int = 0
    out_of_range: int = 0
    dropped: int = 0
    bytes_sent: int = 0


def perfect_links(params: LinkParams) -> bool:
    """True when ``params`` deliver every frame to every addressee at the next step."""
    return (params.range_m == 0.0 and params.loss_probability == 0.0
            and params.latency_s == 0.0 and params.bandwidth_bytes_per_s == 0.0)


def loss_draw(seed: int, kind: FrameKind, sender: int, receiver: int, key: int,
              step: int) -> float:
    """A uniform number in [0, 1) fixed by its arguments (BLAKE2b of the packed integers):
    the same transmission draws the same number in every process and in any order."""
    packed = struct.pack("<qqqqqq", seed, int(kind), sender, receiver, key, step)
    digest = hashlib.blake2b(packed, digest_size=8).digest()
    return int.from_bytes(digest, "little") / 2.0**64


@dataclass
class _Channel:
    """One sender's queue and the time its channel is free again [s]."""

    queue: deque[Frame] = field(default_factory=deque)
    free_at_s: float = 0.0


class TeamLinks:
    """The link model of a team (see module docstring).

    Per step ``k``: ``deliveries(k)`` hands out what arrives before step ``k`` is processed;
    robots ``offer`` the frames they produce while processing it (in any order);
    ``transmit(k, positions)`` then queues them and starts every transmission the channels
    allow, with the true positions of step ``k``. Memory: the queues (bounded) and the
    frames in flight (bounded by what the channels can carry within the latency).
    """

    def __init__(self, params: LinkParams, num_robots: int, time_step_s: float,
                 seed: int) -> None:
        self.params = params
        self.num_robots = num_robots
        self.time_step_s = time_step_s
        self.seed = seed
        self.counts = LinkCounts()
        self._channels = [_Channel() for _ in range(num_robots)]
        self._in_flight: dict[int, list[Delivery]] = {}
        self._offered: list[Frame] = []

    def offer(self, frame: Frame) -> None:
        """Hand a frame to its sender's channel. It joins the queue at the next
        ``transmit``, with the other frames of its step in a canonical order (step, kind,
        key, addressees), so the order in which frames reach the relay changes nothing."""
        if not 0 <= frame.sender < self.num_robots:
            raise ValueError(f"frame sender {frame.sender} is not a robot of this team")
        self._offered.append(frame)

    def _enqueue_offered(self) -> None:
        """Queue the offered frames in canonical order; tail drop on a full queue."""
        offered, self._offered = self._offered, []
        offered.sort(key=lambda f: (f.sent_step, f.sender, f.kind, f.key, f.receivers))
        for frame in offered:
            queue = self._channels[frame.sender].queue
            if len(queue) >= self.params.queue_frames:
                self.counts.dropped += len(frame.receivers)
            else:
                queue.append(frame)

    def transmit(self, step: int, positions: np.ndarray) -> None:
        """Start every transmission whose channel is free by the time of ``step``; decide
        range and loss per addressee with ``positions`` ((N, 2) true positions [m], world
        frame, at ``step``) and schedule the deliveries."""
        self._enqueue_offered()
        now_s = step * self.time_step_s
        bandwidth = self.params.bandwidth_bytes_per_s
        for channel in self._channels:
            while channel.queue:
                frame = channel.queue[0]
                start_s = max(channel.free_at_s, frame.sent_step * self.time_step_s)
                if start_s > now_s + _TIME_EPS_S:
                    break
                channel.queue.popleft()
                end_s = start_s + (frame.size_bytes / bandwidth if bandwidth > 0 else 0.0)
                channel.free_at_s = end_s
                self.counts.bytes_sent += frame.size_bytes
                arrival_step = max(frame.sent_step + 1, self._first_step_at(
                    end_s + self.params.latency_s))
                for receiver in frame.receivers:
                    if self._reaches(frame, receiver, step, positions):
                        self._in_flight.setdefault(arrival_step, []).append(
                            Delivery(arrival_step, receiver, frame))
                        self.counts.delivered += 1

    def deliveries(self, step: int) -> list[Delivery]:
        """What arrives before ``step`` is processed (and was not handed out before), in
        the order the transmissions started (sender id order within a step)."""
        due = sorted(s for s in self._in_flight if s <= step)
        return [d for s in due for d in self._in_flight.pop(s)]

    def _first_step_at(self, time_s: float) -> int:
        return int(math.ceil(time_s / self.time_step_s - _TIME_EPS_S))

    def _reaches(self, frame: Frame, receiver: int, step: int, positions: np.ndarray) -> bool:
        p = self.params
        if p.range_m > 0.0:
            distance = float(np.hypot(*(positions[frame.sender, :2] - positions[receiver, :2])))
            if distance > p.range_m:
                self.counts.out_of_range += 1
                return False
        if p.loss_probability > 0.0 and loss_draw(
                self.seed, frame.kind, frame.sender, receiver, frame.key,
                step) < p.loss_probability:
            self.counts.lost += 1
            return False
        return True


@dataclass(frozen=True)
class UpdateDeliveryCounts:
    """For every (update, teammate) pair of a run: delivered ``on_time`` (at the step after
    it was sent, as over a perfect link), ``late`` (later, by latency, queueing or a
    re-send) or ``never``."""

    sent: int
    on_time: int
    late: int
    never: int


class DeliveryLedger:
    """When each teammate first received each record of each robot's stream.

    Memory: one entry per record sent and one per (record, receiver) delivered, i.e. the
    size of the streams themselves.
    """

    def __init__(self, num_robots: int) -> None:
        self.num_robots = num_robots
        self._sent_step: dict[tuple[int, int], int] = {}
        self._first_delivery: dict[tuple[int, int, int], int] = {}

    def sent(self, sender: int, sequence: int, step: int) -> None:
        """Record ``sequence`` of ``sender``'s stream was first sent during ``step``."""
        self._sent_step.setdefault((sender, sequence), step)

    def delivered(self, sender: int, receiver: int, sequence: int, step: int) -> None:
        """A copy of the record reached ``receiver`` before ``step``."""
        self._first_delivery.setdefault((sender, receiver, sequence), step)

    def counts(self, next_step: int) -> UpdateDeliveryCounts:
        """The counts over every record a perfect link would have delivered before
        ``next_step`` (the first step not processed) and every teammate of its sender."""
        on_time = late = never = 0
        for (sender, sequence), step in self._sent_step.items():
            if step + 1 >= next_step:
                continue
            for receiver in range(self.num_robots):
                if receiver == sender:
                    continue
                first = self._first_delivery.get((sender, receiver, sequence))
                if first is None:
                    never += 1
                elif first <= step + 1:
                    on_time += 1
                else:
                    late += 1
        return UpdateDeliveryCounts(on_time + late + never, on_time, late, never)
