"""em-world: the world simulator node, the ROS shell of
``core.sessions.world_session.WorldSession``.

It is the system's clock and its only source of ground truth (topics:
``nodes/world_outputs.py``; subscribes ``/robot_i/motion_command`` and, in relay mode, the
team topics through ``nodes/team_relay.py``). The protocol - when to start, the lockstep
barrier with its re-sends, lost and rejoining robots, the relay's hand-over, real-time
ticks, the end of the stepping - is the session's (its module docstring); this node declares
the parameters, creates the publishers, subscriptions and timers, converts messages into
the session's inputs and performs the effects it returns. Once stepping is over the node
keeps spinning so late subscribers still get the latched topics.

Run: ``python -m em_exploration_ros.nodes.world_node --ros-args --params-file
config/exploration.yaml -p world.num_robots:=3``
"""
from __future__ import annotations

import sys
import time
from typing import Any

from em_exploration_msgs.msg import MotionCommand

from em_exploration_ros.core.links.link_model import Delivery
from em_exploration_ros.core.node_settings import WorldNodeSettings
from em_exploration_ros.core.sessions.effects import LogLine
from em_exploration_ros.core.sessions.lockstep import StepAnswer
from em_exploration_ros.core.sessions.world_effects import (Dropped, PublishClock,
                                                            PublishLinkCounts, PublishSensors,
                                                            PublishSonarTruth, PublishStatus,
                                                            PublishTruth, StartTicking)
from em_exploration_ros.core.sessions.world_session import TeamConnections, WorldSession
from em_exploration_ros.nodes.conversions import WORLD_NODE_NAME, robot_namespace
from em_exploration_ros.nodes.input_guard import (InputGuard, content_problem, header_problem,
                                                  size_limited)
from em_exploration_ros.nodes.lean_node import LeanNode
from em_exploration_ros.nodes.message_bounds import motion_command_bytes
from em_exploration_ros.nodes.liveliness import watch_liveliness
from em_exploration_ros.nodes.log_lines import LineWriter
from em_exploration_ros.nodes.node_main import run_node
from em_exploration_ros.nodes.qos import LIVELINESS_LEASE_S, SENSOR_QOS
from em_exploration_ros.nodes.recorder_presence import topics_not_recorded
from em_exploration_ros.nodes.ros_params import (declare_exploration_params,
                                                 declare_node_settings, refuse_unknown_overrides)
from em_exploration_ros.nodes.sim_clock import install_validated_clock
from em_exploration_ros.nodes.team_relay import TeamRelay
from em_exploration_ros.nodes.world_outputs import WorldOutputs

#: Wall period of the timer that checks start-up connections and robot timeouts [s].
_POLL_PERIOD_S = 0.05


class WorldNode(LeanNode):
    """The world simulator (see module docstring)."""

    def __init__(self) -> None:
        super().__init__(WORLD_NODE_NAME)
        self.inputs = InputGuard(self)
        install_validated_clock(self, self.inputs)
        self.settings = declare_node_settings(self, WorldNodeSettings)
        self.params = declare_exploration_params(self)
        refuse_unknown_overrides(self)
        self.num_robots = self.params.world.num_robots
        self.session = WorldSession(self.params, self.settings, time.monotonic(),
                                    LIVELINESS_LEASE_S)
        self.lines = LineWriter(self)
        self.outputs = WorldOutputs(self, self.params, self.settings.run_id)
        self.relay = (None if self.session.relay is None
                      else TeamRelay(self, self.session, self.inputs, self._perform))
        # Read raw: a command longer than the largest valid one is dropped unread.
        self.command_subs = []
        for robot in range(self.num_robots):
            topic = f"/{robot_namespace(robot)}/motion_command"
            self.command_subs.append(self.create_subscription(MotionCommand, topic, size_limited(
                self.inputs, topic, MotionCommand, motion_command_bytes(),
                lambda message, robot=robot: self._on_command(robot, message)),
                SENSOR_QOS, raw=True))
        watch_liveliness(self, list(range(self.num_robots)), self._on_liveliness)
        self.outputs.mission(self.session.sim.world, self.session.sim.stamp_s)
        self._poll_timer = self.create_timer(_POLL_PERIOD_S, self._poll)
        self._tick_timer = None
        self.lines.write(self.session.greeting())

    # -- start-up: who is connected ---------------------------------------------------------

    def robot_started(self, robot: int) -> bool:
        """True when robot ``robot``'s node runs: it listens to its sensors (and, in relay
        mode, to what the links deliver to it) and publishes its commands."""
        return ((self.relay is None or self.relay.robot_listens(robot))
                and self.outputs.sonar_pubs[robot].get_subscription_count() >= 1
                and self.outputs.odom_pubs[robot].get_subscription_count() >= 1
                and self.command_subs[robot].get_publisher_count() >= 1)

    def robot_connected(self, robot: int) -> bool:
        """True when robot ``robot`` runs and its team updates have their listeners (the
        teammates, plus the evaluator if required)."""
        teammates = self.num_robots - 1 if self.relay is None else 1  # relay: the world hears
        listeners = teammates + (1 if self.settings.wait_for_evaluator else 0)
        return (self.robot_started(robot) and self.count_subscribers(
            f"/{robot_namespace(robot)}/team/updates") >= listeners)

    def _observers_connected(self) -> bool:
        evaluator = all(pub.get_subscription_count() >= 1 for pub in self.outputs.truth_pubs)
        return ((not self.settings.wait_for_evaluator or evaluator)
                and (not self.settings.wait_for_recorder or not topics_not_recorded(self)))

    def _connections(self) -> TeamConnections:
        robots = range(self.num_robots)
        return TeamConnections(tuple(self.robot_started(r) for r in robots),
                               tuple(self.robot_connected(r) for r in robots),
                               self._observers_connected())

    # -- inputs -----------------------------------------------------------------------------

    def _poll(self) -> None:
        """Start-up: wait for the connections; lockstep: re-sends and robot timeouts."""
        session = self.session
        if not session.polling:
            self._poll_timer.cancel()
            return
        self._perform(session.poll(time.monotonic(),
                                   None if session.running else self._connections()))

    def _on_liveliness(self, robot: int, alive: bool, restarted: bool) -> None:
        self._perform(self.session.on_liveliness(robot, alive, restarted, time.monotonic()))

    def _on_command(self, robot: int, message: MotionCommand) -> None:
        topic = f"/{robot_namespace(robot)}/motion_command"
        twist = message.twist
        linear_x, angular_z = float(twist.linear.x), float(twist.angular.z)
        if not self.inputs.check(
                topic, self.session.run_problem(int(message.run_id)),
                header_problem(message.header, f"{robot_namespace(robot)}/base_link"),
                content_problem(message),
                self.session.command_problem(robot, int(message.robot_id), linear_x, angular_z,
                                             int(message.team_sequence))):
            return
        answer = StepAnswer(linear_x, angular_z, int(message.team_sequence),
                            bool(message.finished), int(message.team_messages),
                            int(message.team_requests))
        self._perform(self.session.on_command(robot, int(message.step), answer,
                                              time.monotonic()), topic)

    def _tick(self) -> None:
        self._perform(self.session.tick(time.monotonic()))
        if self.session.stepping_over:
            self._tick_timer.cancel()

    # -- effects ----------------------------------------------------------------------------

    def _perform(self, effects: list[Any], topic: str = "") -> None:
        """Publish, log or schedule what the session asks (``topic``: the one whose input
        the effects answer, for a drop)."""
        outputs = self.outputs
        for effect in effects:
            kind = type(effect)
            if kind is PublishSensors:
                outputs.sensors(effect)
            elif kind is Delivery:
                self.relay.deliver(effect)
            elif kind is PublishClock:
                outputs.clock(effect)
            elif kind is PublishTruth:
                outputs.truth(effect)
            elif kind is PublishSonarTruth:
                outputs.sonar_truth(effect)
            elif kind is LogLine:
                self.lines.write(effect)
            elif kind is PublishLinkCounts:
                self.relay.link_counts(effect)
            elif kind is PublishStatus:
                outputs.status(effect)
            elif kind is Dropped:
                self.inputs.drop(topic, effect.reason)
            elif kind is StartTicking:
                self._tick_timer = self.create_timer(effect.period_s, self._tick)
            else:
                raise TypeError(f"no way to perform {effect!r}")

    def log_links(self) -> None:
        """Relay mode: one line with what the links did so far."""
        self._perform(self.session.link_summary())


def main(args: list[str] | None = None) -> int:
    """Entry point of em-world; returns the exit code (2 for invalid parameters)."""
    return run_node(WorldNode, WORLD_NODE_NAME, args, wrap_up=_log_links)


def _log_links(node: WorldNode) -> int:
    """At the end (Ctrl-C, SIGTERM): what the links did, for the run's logs."""
    node.log_links()
    return 0


if __name__ == "__main__":
    sys.exit(main())
