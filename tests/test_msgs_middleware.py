"""Every em_exploration_msgs type crosses the real middleware between two OS processes intact.

A child process (this file run as a script) publishes one sample of every type, each on its
own topic, with reliable + transient-local QoS, so the sample stays available to a subscriber
that matches later. The test process subscribes to all topics with the same QoS and compares
what arrives with the sample it builds itself (msg_samples is deterministic).
"""
from __future__ import annotations

import re
import select
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_samples import canonical_cdr, make_sample, message_class, message_type_names

TYPE_NAMES = message_type_names()

QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                 reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.TRANSIENT_LOCAL)

# Bounds: the child's start-up (rclpy import, one node, one publisher per type), the exchange,
# the child's clean exit, and the child's own lifetime should the test process vanish.
READY_TIMEOUT_S = 20.0
RECEIVE_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 5.0
CHILD_LIFETIME_S = 60.0


def topic_of(name: str) -> str:
    """Return the test topic of a message type, e.g. TeamUpdate -> /em_msgs_test/team_update."""
    return "/em_msgs_test/" + re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


def publish_samples() -> None:
    """Child process: publish every sample, report "ready", and live until stdin closes."""
    rclpy.init()
    node = rclpy.create_node("em_msgs_test_publisher")
    publishers = []
    for name in TYPE_NAMES:
        msg_class = message_class(name)
        publisher = node.create_publisher(msg_class, topic_of(name), QOS)
        publisher.publish(make_sample(msg_class))
        publishers.append(publisher)
    print("ready", flush=True)
    # Transient-local samples are served by the middleware's own threads: no spinning needed.
    select.select([sys.stdin], [], [], CHILD_LIFETIME_S)
    node.destroy_node()
    rclpy.shutdown()


def _wait_for_ready(child: subprocess.Popen[str], stderr_path: Path) -> None:
    """Wait until the child printed "ready"; fail with its stderr if it died or hung."""
    assert child.stdout is not None
    readable, _, _ = select.select([child.stdout], [], [], READY_TIMEOUT_S)
    line = child.stdout.readline() if readable else ""
    if line.strip() != "ready":
        child.kill()
        child.wait(timeout=EXIT_TIMEOUT_S)
        pytest.fail(f"publisher process not ready (exit code {child.returncode}):\n"
                    f"{stderr_path.read_text()}")


def _receive_all(child: subprocess.Popen[str]) -> dict[str, Any]:
    """Subscribe to every test topic in this process and return the first message of each."""
    received: dict[str, Any] = {}
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("em_msgs_test_subscriber", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        for name in TYPE_NAMES:
            node.create_subscription(message_class(name), topic_of(name),
                                     lambda msg, name=name: received.setdefault(name, msg), QOS)
        deadline = time.monotonic() + RECEIVE_TIMEOUT_S
        while len(received) < len(TYPE_NAMES) and time.monotonic() < deadline:
            if child.poll() is not None:
                break
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    return received


@pytest.fixture(scope="module")
def received(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """Run the publisher process and return what this process received from it, by type."""
    # stderr goes to a file: a pipe nobody reads could fill up and block the child.
    stderr_path = tmp_path_factory.mktemp("publisher") / "stderr.txt"
    with stderr_path.open("w") as stderr:
        child = subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, stderr=stderr, text=True)
    try:
        _wait_for_ready(child, stderr_path)
        yield _receive_all(child)
    finally:
        assert child.stdin is not None and child.stdout is not None
        child.stdin.close()  # tells the child to exit
        try:
            child.wait(timeout=EXIT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        child.stdout.close()


def test_message_types_found() -> None:
    """The .msg files are discovered, so the parametrized test below is not vacuous."""
    assert TYPE_NAMES, "no .msg files found in msg_schemas/msg"


@pytest.mark.parametrize("name", TYPE_NAMES)
def test_message_crosses_processes_intact(name: str, received: dict[str, Any]) -> None:
    """The message received from the other process equals the sample, field for field."""
    assert name in received, f"no {name} received on {topic_of(name)}"
    expected = make_sample(message_class(name))
    assert received[name] == expected
    assert canonical_cdr(received[name]) == canonical_cdr(expected)


if __name__ == "__main__":
    # Run as the publisher process (the script's folder, tests/, is on sys.path).
    publish_samples()
