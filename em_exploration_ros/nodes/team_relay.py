"""The world node's link relay: team data between robots through the link model (ROS shell).

Created by em-world when the ``links.*`` parameters are not perfect. What is relayed when
is the world's session's (``core.sessions.world_session.WorldSession``, with
``core.links.link_relay.LinkRelay``); this module hears the robots' team topics on the world
node, checks and converts every message for the session, and publishes the deliveries and
link counts it returns. Topics (QoS ``TEAM_QOS``):

- hears ``/robot_<i>/team/updates`` (TeamUpdate: new updates and re-sends),
  ``/team/update_requests`` (TeamUpdateRequest from robots; the evaluator's requests, with
  the OBSERVER id, are not link traffic and are left to the robots) and
  ``/robot_<s>/team/history_copies`` (robot s's copies of a restarted teammate's records,
  relay mode's form of ``/robot_<i>/team/history``, which does not say who sent a copy),
  each read raw: a record deserialized only when its head passes
  (``input_guard.screened_team_updates``), a request only when it is no longer than the
  largest valid one;
- delivers on ``/robot_<i>/team/delivered_updates`` (TeamUpdate) and
  ``/robot_<i>/team/delivered_requests`` (TeamUpdateRequest);
- publishes ``/world/link_counts`` (TeamLinkCounts, ``GROUND_TRUTH_QOS``: the evaluator may
  lag) before the deliveries of every ``METRICS_INTERVAL_STEPS``-th step and of the final
  step: the on-time / late / never counts em-sim's summary holds, for the evaluator's.

A real deployment replaces this relay (and the delivered topics) with a modem bridge that
carries the three heard topics between vehicles.
"""
from __future__ import annotations

import time
from typing import Any, Callable

from em_exploration_msgs.msg import TeamLinkCounts, TeamUpdate, TeamUpdateRequest
from rclpy.node import Node

from em_exploration_ros.core.links.link_model import Delivery, FrameKind
from em_exploration_ros.core.records import team_data
from em_exploration_ros.core.records.team_data import InvalidTeamUpdate
from em_exploration_ros.core.records.team_wire import TeamWireFormat, cdr_size, request_cdr_size
from em_exploration_ros.core.records.update_screening import only_sender
from em_exploration_ros.core.sessions.world_effects import PublishLinkCounts
from em_exploration_ros.core.sessions.world_session import WorldSession
from em_exploration_ros.nodes.conversions import robot_namespace
from em_exploration_ros.nodes.input_guard import (InputGuard, checked_team_update,
                                                  publish_or_log, screened_team_updates,
                                                  size_limited)
from em_exploration_ros.nodes.message_bounds import request_bytes
from em_exploration_ros.nodes.message_info import MessageInfo, publication_sequence
from em_exploration_ros.nodes.qos import GROUND_TRUTH_QOS, TEAM_QOS
from em_exploration_ros.nodes.team_topics import (LINK_COUNTS_TOPIC, REQUESTS_TOPIC,
                                                  delivered_requests_topic,
                                                  delivered_updates_topic, history_copies_topic)


class TeamRelay:
    """Hears, checks and relays team data on ``node`` for ``session`` (see module
    docstring); ``perform`` is handed the effects of what is heard (the world's step may
    now be complete)."""

    def __init__(self, node: Node, session: WorldSession, inputs: InputGuard,
                 perform: Callable[[list[Any]], None]) -> None:
        self.node = node
        self.session = session
        self.inputs = inputs
        self.wire = TeamWireFormat(session.params)
        self._perform = perform
        robots = range(session.num_robots)
        self.update_pubs = [node.create_publisher(TeamUpdate, delivered_updates_topic(r),
                                                  TEAM_QOS) for r in robots]
        self.request_pubs = [node.create_publisher(
            TeamUpdateRequest, delivered_requests_topic(r), TEAM_QOS) for r in robots]
        self.counts_pub = node.create_publisher(TeamLinkCounts, LINK_COUNTS_TOPIC,
                                                GROUND_TRUTH_QOS)
        # Every topic is read raw: records are screened by their head, requests longer than
        # the largest valid one dropped, before anything is deserialized.
        for robot in robots:
            topic = f"/{robot_namespace(robot)}/team/updates"
            node.create_subscription(TeamUpdate, topic, screened_team_updates(
                inputs, topic, session.run_problem, only_sender(robot), None,
                lambda message, info, sender=robot: self._on_update(sender, message, info),
                with_info=True), TEAM_QOS, raw=True)
            topic = history_copies_topic(robot)
            node.create_subscription(TeamUpdate, topic, screened_team_updates(
                inputs, topic, session.run_problem,
                lambda owner, sender=robot: session.history_problem(sender, owner), None,
                lambda message, sender=robot: self._on_history(sender, message)),
                TEAM_QOS, raw=True)
        node.create_subscription(TeamUpdateRequest, REQUESTS_TOPIC, size_limited(
            inputs, REQUESTS_TOPIC, TeamUpdateRequest, request_bytes(), self._on_request,
            with_info=True), TEAM_QOS, raw=True)

    def robot_listens(self, robot: int) -> bool:
        """True when ``robot`` subscribes to both of its delivered topics."""
        return (self.update_pubs[robot].get_subscription_count() >= 1
                and self.request_pubs[robot].get_subscription_count() >= 1)

    def _checked(self, topic: str, message: TeamUpdate) -> team_data.TeamUpdate | None:
        """The message (its head screened: of this run, of a robot the topic may carry) as
        core data, if its content is valid."""
        try:
            return checked_team_update(message, self.wire)
        except InvalidTeamUpdate as error:
            self.inputs.drop(topic, f"rejected a team update: {error}")
            return None

    def _on_update(self, sender: int, message: TeamUpdate, info: MessageInfo) -> None:
        update = self._checked(f"/{robot_namespace(sender)}/team/updates", message)
        if update is not None:
            self._perform(self.session.update_heard(
                sender, update.sequence, cdr_size(update), message, publication_sequence(info),
                time.monotonic()))

    def _on_history(self, sender: int, message: TeamUpdate) -> None:
        """``sender``'s copy of a record of a restarted teammate's stream (its head passed:
        of this run, of a teammate of ``sender``)."""
        owner = int(message.robot_id)
        update = self._checked(history_copies_topic(sender), message)
        if update is not None:
            self.session.history_heard(sender, owner, update.sequence, cdr_size(update),
                                       message)

    def _on_request(self, message: TeamUpdateRequest, info: MessageInfo) -> None:
        requester, owner = int(message.requester_id), int(message.robot_id)
        if not self.inputs.check(REQUESTS_TOPIC, self.session.run_problem(int(message.run_id))):
            return
        if requester == TeamUpdateRequest.OBSERVER:
            return  # the evaluator's: robots hear it directly
        first, last = int(message.first_sequence), int(message.last_sequence)
        if self.inputs.check(REQUESTS_TOPIC, self.session.request_problem(
                requester, owner, first, last, TeamUpdateRequest.OBSERVER)):
            self._perform(self.session.request_heard(
                requester, owner, first, request_cdr_size(), message,
                publication_sequence(info), time.monotonic()))

    def deliver(self, delivery: Delivery) -> None:
        """Publish a record or request the links deliver, on its receiver's topic."""
        frame, receiver = delivery.frame, delivery.receiver
        if frame.kind == FrameKind.REQUEST:
            publish_or_log(self.request_pubs[receiver], frame.payload, self.node,
                           f"a request for robot {receiver}")
        else:
            publish_or_log(self.update_pubs[receiver], frame.payload, self.node,
                           f"robot {frame.sender}'s record for robot {receiver}")

    def link_counts(self, effect: PublishLinkCounts) -> None:
        """The on-time / late / never counts of the team updates, for the evaluator."""
        counts, step = effect.counts, effect.step
        publish_or_log(self.counts_pub, TeamLinkCounts(
            run_id=self.session.settings.run_id, step=step, sent=counts.sent,
            on_time=counts.on_time, late=counts.late, never=counts.never), self.node,
            f"the link counts of step {step}")
