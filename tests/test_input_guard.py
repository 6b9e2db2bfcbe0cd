"""The message checks every node applies before it touches state, and ``publish_or_log``
(nodes/input_guard.py)."""
from __future__ import annotations

import math
import textwrap
import types

import numpy as np
import pytest
import rclpy
import rclpy.logging
from nav_msgs.msg import Odometry, Path
from rclpy.node import Node
from rclpy.serialization import serialize_message
from std_msgs.msg import String
from em_exploration_msgs.msg import (GivenUpTarget, Keyframe, Meeting, MotionCommand, TeamUpdate,
                                     TeamUpdateRequest)
from std_msgs.msg import Header

from em_exploration_ros.nodes.conversions import path_to_msg
from em_exploration_ros.core.records.update_screening import only_sender
from em_exploration_ros.nodes.input_guard import (InputGuard, content_problem, publish_or_log,
                                                  screened_team_updates, serialized_size,
                                                  size_limited)
from em_exploration_ros.nodes.message_bounds import (FRAME_ID_ROOM, motion_command_bytes,
                                                     request_bytes)
from em_exploration_ros.nodes.node_main import RCLError

from ros_process import NodeProcess


def long_path(poses: int) -> Path:
    stamps = np.arange(poses) * 2.0
    return path_to_msg(2.0 * poses, stamps, np.zeros((poses, 3)))


def guard() -> InputGuard:
    return InputGuard(types.SimpleNamespace(get_logger=lambda: rclpy.logging.get_logger("t")))


def test_content_problem_finds_a_bad_value_deep_in_thousands_of_nested_messages():
    path = long_path(3000)
    assert content_problem(path) is None
    path.poses[2999].pose.orientation.w = math.nan
    assert "not finite" in content_problem(path)
    path.poses[2999].pose.orientation.w = 1.0
    path.poses[1500].header.stamp.sec = -5
    assert content_problem(path) == "stamp is negative (-5 s)"
    path.poses[1500].header.stamp.sec = 5
    path.poses[7].pose.position.y = -2e9
    assert "implausibly large" in content_problem(path)


def test_content_problem_checks_fixed_float_arrays():
    odometry = Odometry()
    assert content_problem(odometry) is None
    odometry.twist.covariance[35] = math.inf
    assert "not finite" in content_problem(odometry)


def test_size_limited_drops_a_longer_message_before_deserializing_it():
    received: list[Path] = []
    inputs = guard()
    limit = serialized_size(long_path(10))
    on_bytes = size_limited(inputs, "/robot_0/estimated_path", Path, limit, received.append)
    on_bytes(serialize_message(long_path(11)))
    assert received == [] and inputs.dropped == 1
    on_bytes(serialize_message(long_path(10)))
    assert inputs.dropped == 1 and len(received) == 1 and len(received[0].poses) == 10
    assert received[0].poses[9].header.stamp.sec == 18


def test_size_limited_drops_bytes_that_are_not_the_type():
    received: list[Path] = []
    inputs = guard()
    on_bytes = size_limited(inputs, "/robot_0/landmarks", Path, 10_000, received.append)
    on_bytes(b"\x00\x01\x00\x00" + b"\xff" * 40)  # a count of 2^32 - 1 poses
    on_bytes(b"\x00\x01")
    assert received == [] and inputs.dropped == 2


def test_screened_team_updates_reads_only_what_passes_its_head():
    received: list[TeamUpdate] = []
    inputs = guard()
    expected = {1: 5}
    on_bytes = screened_team_updates(
        inputs, "/robot_1/team/updates",
        lambda run_id: None if run_id == 7 else f"of run {run_id}", only_sender(1),
        expected.get, received.append)

    def send(**fields) -> None:
        on_bytes(serialize_message(TeamUpdate(**{"run_id": 7, "robot_id": 1, **fields})))

    send(run_id=8, sequence=5)
    send(robot_id=2, sequence=5)
    send(sequence=5, keyframes=[Keyframe()] * 1001)
    send(sequence=5 + 10_001)
    assert received == [] and inputs.dropped == 4
    send(sequence=4, keyframes=[Keyframe()] * 400)  # held already, 20 kB: ignored unread
    assert received == [] and inputs.dropped == 4
    on_bytes(serialize_message(TeamUpdate(run_id=7, robot_id=1, sequence=6))[:30])
    assert received == [] and inputs.dropped == 5  # its head passes, its body is cut short
    send(sequence=4, keyframes=[Keyframe()] * 300)  # held already, 15 kB: read
    send(sequence=5, step=3)
    send(sequence=5 + 10_000)
    assert [(m.sequence, m.step) for m in received] == [(4, 0), (5, 3), (10_005, 0)]
    assert inputs.dropped == 5


def test_screened_team_updates_hands_on_the_message_info():
    received = []
    on_bytes = screened_team_updates(guard(), "/robot_0/team/updates", lambda _: None,
                                     only_sender(0), None,
                                     lambda m, info: received.append((m.sequence, info)),
                                     with_info=True)
    on_bytes(serialize_message(TeamUpdate(sequence=3)), {"publication_sequence_number": 9})
    assert received == [(3, {"publication_sequence_number": 9})]


def test_size_limited_hands_on_the_message_info():
    received = []
    on_bytes = size_limited(guard(), "/team/update_requests", TeamUpdateRequest,
                            request_bytes(), lambda m, info: received.append((m.robot_id, info)),
                            with_info=True)
    on_bytes(serialize_message(TeamUpdateRequest(robot_id=2)), {"publication_sequence_number": 4})
    assert received == [(2, {"publication_sequence_number": 4})]


@pytest.mark.parametrize("message_class, bound", [(TeamUpdateRequest, request_bytes),
                                                   (MotionCommand, motion_command_bytes)])
def test_a_bounded_message_is_read_up_to_its_bound_and_dropped_past_it(message_class, bound):
    """A request or command with a frame id of the room allowed is read; one character more
    is dropped unread. A command's bound holds both of its arrays full."""
    received: list = []
    inputs = guard()
    on_bytes = size_limited(inputs, "/topic", message_class, bound(), received.append)
    fields = ({"given_up": [GivenUpTarget()] * 4, "meetings": [Meeting()] * 4}
              if message_class is MotionCommand else {})
    for frame_chars in (FRAME_ID_ROOM, FRAME_ID_ROOM + 4):
        on_bytes(serialize_message(message_class(
            header=Header(frame_id="x" * frame_chars), **fields)))
    assert len(received) == 1 and len(received[0].header.frame_id) == FRAME_ID_ROOM
    assert inputs.dropped == 1


class RecordingLogger:
    """Stands for a node's logger: keeps the ERROR lines."""

    def __init__(self) -> None:
        self.errors: list[str] = []

    def error(self, message: str, **_throttle) -> None:
        self.errors.append(message)


@pytest.fixture
def node(monkeypatch):
    """A node on its own context, logging ERRORs to ``node.get_logger().errors``."""
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node("publish_or_log_test", context=context)
    logger = RecordingLogger()
    monkeypatch.setattr(node, "get_logger", lambda: logger)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_publish_after_the_context_was_shut_down_is_the_stop_not_an_error(node):
    """Ctrl-C shuts the context down while a callback may still publish: rcl refuses with
    "publisher's context is invalid"; that is the process stopping, not an ERROR."""
    publisher = node.create_publisher(String, "late", 10)
    assert publish_or_log(publisher, String(data="before"), node, "a message")
    node.context.shutdown()
    with pytest.raises(RCLError, match="context is invalid"):
        publisher.publish(String(data="after"))
    assert not publish_or_log(publisher, String(data="after"), node, "a late message")
    assert node.get_logger().errors == []


def test_a_publish_refused_while_the_context_is_valid_is_still_an_error(node):
    def refuse(_message: String) -> None:
        raise RCLError("Failed to publish: the middleware refused")

    publisher = types.SimpleNamespace(topic_name="/refused", publish=refuse)
    assert not publish_or_log(publisher, String(data="x"), node, "a refused message")
    assert node.get_logger().errors == [
        "could not publish a refused message on /refused: Failed to publish: the middleware "
        "refused"]


# A node whose timer callback sends itself SIGINT, waits until rclpy's signal thread shut its
# context down (as a callback still running at a Ctrl-C, or one a stopped process runs when
# SIGCONT delivers the pending SIGINT), then publishes through publish_or_log.
LATE_PUBLISHING_NODE = textwrap.dedent("""
    import os, signal, sys, time
    from rclpy.node import Node
    from std_msgs.msg import String
    from em_exploration_ros.nodes.input_guard import publish_or_log
    from em_exploration_ros.nodes.node_main import run_node

    class LatePublisher(Node):
        def __init__(self):
            super().__init__("late_publisher")
            self.publisher = self.create_publisher(String, "late", 10)
            self.timer = self.create_timer(0.01, self.tick)

        def tick(self):
            self.timer.cancel()
            os.kill(os.getpid(), signal.SIGINT)
            deadline = time.monotonic() + 5.0
            while self.context.ok() and time.monotonic() < deadline:
                time.sleep(0.001)
            sent = publish_or_log(self.publisher, String(data="late"), self, "a late message")
            print(f"context ok: {self.context.ok()}; sent: {sent}", flush=True)

    sys.exit(run_node(LatePublisher, "late_publisher"))
""")


def test_ctrl_c_during_a_callback_that_publishes_logs_no_error(tmp_path):
    code, output = NodeProcess.run_script(LATE_PUBLISHING_NODE, tmp_path / "node.log", 30.0)
    assert code == 0, output
    assert "context ok: False; sent: False" in output, output
    assert "[ERROR]" not in output and "context is invalid" not in output, output
