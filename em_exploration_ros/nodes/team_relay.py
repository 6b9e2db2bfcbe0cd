"""The world node's link relay: team data between robots through the link model (ROS shell).

Created by em-world when the ``links.*`` parameters are not perfect. The bookkeeping is
``core.links.link_relay.LinkRelay``; this module hears the robots' team topics on the world
node, checks every message, and publishes what the links deliver on each receiver's own
topics. Topics (QoS ``TEAM_QOS``):

- hears ``/robot_<i>/team/updates`` (TeamUpdate: new updates and re-sends),
  ``/team/update_requests`` (TeamUpdateRequest from robots; the evaluator's requests, with
  the OBSERVER id, are not link traffic and are left to the robots) and
  ``/robot_<s>/team/history_copies`` (robot s's copies of a restarted teammate's records,
  relay mode's form of ``/robot_<i>/team/history``, which does not say who sent a copy);
- delivers on ``/robot_<i>/team/delivered_updates`` (TeamUpdate) and
  ``/robot_<i>/team/delivered_requests`` (TeamUpdateRequest);
- publishes ``/world/link_counts`` (TeamLinkCounts, ``GROUND_TRUTH_QOS``: the evaluator may
  lag) before the deliveries of every ``METRICS_INTERVAL_STEPS``-th step and of the final
  step: the on-time / late / never counts em-sim's summary holds, for the evaluator's.

A real deployment replaces this relay (and the delivered topics) with a modem bridge that
carries the three heard topics between vehicles.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from em_exploration_msgs.msg import TeamLinkCounts, TeamUpdate, TeamUpdateRequest
from rclpy.node import Node

from em_exploration_ros.core.agent.input_checks import request_problem
from em_exploration_ros.core.records import team_data
from em_exploration_ros.core.records.team_data import InvalidTeamUpdate
from em_exploration_ros.core.records.team_wire import TeamWireFormat, cdr_size, request_cdr_size
from em_exploration_ros.core.evaluation.run_monitor import METRICS_INTERVAL_STEPS
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.links.link_relay import LinkRelay, SentCounts
from em_exploration_ros.core.links.link_model import FrameKind
from em_exploration_ros.core.sessions.lockstep import StepAnswer
from em_exploration_ros.nodes.conversions import robot_namespace
from em_exploration_ros.nodes.input_guard import (InputGuard, checked_team_update,
                                                  publish_or_log)
from em_exploration_ros.nodes.message_info import MessageInfo, publication_sequence
from em_exploration_ros.nodes.qos import GROUND_TRUTH_QOS, TEAM_QOS
from em_exploration_ros.nodes.team_topics import (LINK_COUNTS_TOPIC, REQUESTS_TOPIC,
                                                  delivered_requests_topic,
                                                  delivered_updates_topic, history_copies_topic)


def _sent_counts(answers: dict[int, StepAnswer]) -> dict[int, SentCounts]:
    """What each robot's answer (robot -> StepAnswer) says it has published."""
    return {robot: SentCounts(a.team_messages, a.team_requests) for robot, a in answers.items()}


class TeamRelay:
    """Hears, checks and relays team data on ``node`` (see module docstring). ``open_step``
    returns the step whose frames the world is collecting (the step open in lockstep);
    ``on_heard`` is called after each frame heard (the world's step may now be complete)."""

    def __init__(self, node: Node, params: ExplorationParams, inputs: InputGuard,
                 open_step: Callable[[], int], on_heard: Callable[[], None]) -> None:
        self.node = node
        self.inputs = inputs
        self.num_robots = params.world.num_robots
        self.relay = LinkRelay(params)
        self.wire = TeamWireFormat(params)
        self._open_step = open_step
        self._on_heard = on_heard
        robots = range(self.num_robots)
        self.update_pubs = [node.create_publisher(TeamUpdate, delivered_updates_topic(r),
                                                  TEAM_QOS) for r in robots]
        self.request_pubs = [node.create_publisher(
            TeamUpdateRequest, delivered_requests_topic(r), TEAM_QOS) for r in robots]
        self.counts_pub = node.create_publisher(TeamLinkCounts, LINK_COUNTS_TOPIC,
                                                GROUND_TRUTH_QOS)
        for robot in robots:
            ns = robot_namespace(robot)
            node.create_subscription(
                TeamUpdate, f"/{ns}/team/updates",
                lambda message, info, sender=robot: self._on_update(sender, message, info),
                TEAM_QOS)
            node.create_subscription(
                TeamUpdate, history_copies_topic(robot),
                lambda message, sender=robot: self._on_history(sender, message), TEAM_QOS)
        node.create_subscription(TeamUpdateRequest, REQUESTS_TOPIC, self._on_request, TEAM_QOS)

    def robot_listens(self, robot: int) -> bool:
        """True when ``robot`` subscribes to both of its delivered topics."""
        return (self.update_pubs[robot].get_subscription_count() >= 1
                and self.request_pubs[robot].get_subscription_count() >= 1)

    def _checked(self, topic: str, message: TeamUpdate,
                 robot_id: int) -> team_data.TeamUpdate | None:
        """The message as core data if it is a valid record of ``robot_id``'s stream."""
        try:
            update = checked_team_update(message, self.wire)
        except InvalidTeamUpdate as error:
            self.inputs.drop(topic, f"rejected a team update: {error}")
            return None
        if update.robot_id != robot_id:
            self.inputs.drop(topic, f"robot_id {update.robot_id} on robot {robot_id}'s topic")
            return None
        return update

    def _on_update(self, sender: int, message: TeamUpdate, info: MessageInfo) -> None:
        update = self._checked(f"/{robot_namespace(sender)}/team/updates", message, sender)
        if update is not None:
            self.relay.update_heard(sender, update.sequence, cdr_size(update),
                                    self._open_step(), message, publication_sequence(info))
            self._on_heard()

    def _on_history(self, sender: int, message: TeamUpdate) -> None:
        """``sender``'s copy of a record of a restarted teammate's stream."""
        topic = history_copies_topic(sender)
        owner = int(message.robot_id)
        problem = (None if owner != sender and 0 <= owner < self.num_robots
                   else f"a record of robot {owner} is no teammate's of robot {sender}")
        if not self.inputs.check(topic, problem):
            return
        update = self._checked(topic, message, owner)
        if update is not None:
            self.relay.history_heard(sender, owner, update.sequence, cdr_size(update),
                                     self._open_step(), message)

    def _on_request(self, message: TeamUpdateRequest, info: MessageInfo) -> None:
        requester, owner = int(message.requester_id), int(message.robot_id)
        if requester == TeamUpdateRequest.OBSERVER:
            return  # the evaluator's: robots hear it directly
        n = self.num_robots
        if not (0 <= requester < n and 0 <= owner < n):
            problem = f"robot ids {requester} -> {owner} are not robots of this team"
        elif requester == owner:
            problem = None  # a restarted robot asks every teammate for its own stream
        else:
            problem = request_problem(requester, int(message.first_sequence),
                                      int(message.last_sequence), owner, n,
                                      TeamUpdateRequest.OBSERVER)
        if self.inputs.check(REQUESTS_TOPIC, problem):
            self.relay.request_heard(requester, owner, int(message.first_sequence),
                                     request_cdr_size(), self._open_step(), message,
                                     publication_sequence(info))
            self._on_heard()

    def missing_from(self, answers: dict[int, StepAnswer]) -> list[int]:
        """Robots whose answers (robot -> StepAnswer) count team messages not heard yet."""
        return self.relay.holds(_sent_counts(answers))

    def write_off(self, answers: dict[int, StepAnswer]) -> None:
        """Stop waiting for what ``answers`` count and was not heard (given up on)."""
        self.relay.written_off(_sent_counts(answers))

    def transmit(self, step: int, true_positions: np.ndarray) -> None:
        """Start the transmissions of ``step`` (true positions ``(N, 2)`` [m], world frame)."""
        self.relay.transmit(step, true_positions)

    def deliver(self, step: int, final: bool) -> None:
        """Publish what reaches each receiver before ``step`` (``final``: the run's last
        step), after the update counts of the step if it is one the evaluator evaluates."""
        if final or step % METRICS_INTERVAL_STEPS == 0:
            counts = self.relay.ledger.counts(step)
            publish_or_log(self.counts_pub, TeamLinkCounts(
                step=step, sent=counts.sent, on_time=counts.on_time, late=counts.late,
                never=counts.never), self.node, f"the link counts of step {step}")
        for delivery in self.relay.deliveries(step):
            frame, receiver = delivery.frame, delivery.receiver
            if frame.kind == FrameKind.REQUEST:
                publish_or_log(self.request_pubs[receiver], frame.payload, self.node,
                               f"a request for robot {receiver}")
            else:
                publish_or_log(self.update_pubs[receiver], frame.payload, self.node,
                               f"robot {frame.sender}'s record for robot {receiver}")

    def delivered_counts(self, robot: int) -> tuple[int, int]:
        """Records and requests delivered to ``robot`` so far."""
        return self.relay.delivered_updates[robot], self.relay.delivered_requests[robot]

    def summary_line(self, step: int) -> str:
        """What the links did, for the world's log at the end of stepping."""
        counts = self.relay.links.counts
        updates = self.relay.ledger.counts(step)
        return (f"links: {updates.sent} (update, teammate) pairs: {updates.on_time} on time, "
                f"{updates.late} late, {updates.never} never; frames per receiver: "
                f"{counts.delivered} delivered, {counts.lost} lost, {counts.out_of_range} out "
                f"of range, {counts.dropped} dropped (full queue); {counts.bytes_sent} bytes sent")
