"""LeanExecutor: the team's executor delivers what rclpy's SingleThreadedExecutor delivers.

One process, one ROS context per test, real DDS on the test run's own domain: messages,
timers, services and clients, coroutine callbacks, entities created and destroyed by
callbacks, exceptions, and shutdown. Every test runs on rclpy's executor as well, so what
it asserts is rclpy's contract, not a habit of ours.
"""
from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator

import pytest
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy
from rclpy.task import Future
from std_msgs.msg import Int32
from std_srvs.srv import Trigger

from em_exploration_ros.nodes.lean_executor import LeanExecutor

#: Reliable and kept, so a message published before the reader matched still arrives.
QOS = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE,
                 durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
DEADLINE_S = 10.0


EXECUTOR_CLASSES = [SingleThreadedExecutor, LeanExecutor]
EXECUTORS = pytest.mark.parametrize("executor_class", EXECUTOR_CLASSES, ids=["rclpy", "lean"])


@contextmanager
def node_on(executor_class: type) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """A node on its own context, added to a new executor of ``executor_class``."""
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("lean_executor_test", context=context)
    executor = executor_class(context=context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture(params=EXECUTOR_CLASSES, ids=["rclpy", "lean"])
def ros(request: pytest.FixtureRequest) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """A node on an executor of each kind."""
    with node_on(request.param) as node_and_executor:
        yield node_and_executor


def spin_until(executor: LeanExecutor, condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + DEADLINE_S
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        executor.spin_once(timeout_sec=0.1)


def test_messages_arrive_in_order_with_their_info(ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros
    received: list[int] = []
    infos: list[object] = []
    node.create_subscription(Int32, "numbers", lambda m: received.append(m.data), QOS)
    node.create_subscription(Int32, "numbers", lambda m, info: infos.append(info), QOS)
    publisher = node.create_publisher(Int32, "numbers", QOS)
    for value in range(50):
        publisher.publish(Int32(data=value))
    spin_until(executor, lambda: len(received) == 50 and len(infos) == 50, "50 messages")
    assert received == list(range(50))
    assert all(isinstance(info, dict) and "source_timestamp" in info for info in infos)


def test_timers_fire_and_a_cancelled_timer_stops(ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros
    ticks = {"a": 0, "b": 0}
    timer_b = None

    def on_a() -> None:
        ticks["a"] += 1
        if ticks["a"] == 3:
            timer_b.cancel()

    node.create_timer(0.01, on_a)
    timer_b = node.create_timer(0.01, lambda: ticks.__setitem__("b", ticks["b"] + 1))
    spin_until(executor, lambda: ticks["a"] >= 10, "ten ticks of timer a")
    assert 1 <= ticks["b"] <= 3  # at most one tick per wake-up after a's third cancels it


def test_a_service_answers_a_client_and_the_future_completes(
        ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros

    def answer(_request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, "done"
        return response

    node.create_service(Trigger, "trigger", answer)
    client = node.create_client(Trigger, "trigger")
    spin_until(executor, client.service_is_ready, "the service")
    future = client.call_async(Trigger.Request())
    executor.spin_until_future_complete(future, timeout_sec=DEADLINE_S)
    assert future.done() and future.result().success and future.result().message == "done"


def test_a_coroutine_callback_waits_for_a_future_set_by_a_later_callback(
        ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros
    gate: Future = Future()
    log: list[str] = []

    async def on_number(message: Int32) -> None:
        log.append(f"start {message.data}")
        await gate
        log.append(f"end {message.data}")

    node.create_subscription(Int32, "numbers", on_number, QOS)
    # Its own group: the coroutine holds the node's default (mutually exclusive) group.
    def open_gate() -> None:
        if log and not gate.done():  # only once the coroutine waits
            log.append("gate")
            gate.set_result(1)

    node.create_timer(0.05, open_gate, callback_group=MutuallyExclusiveCallbackGroup())
    node.create_publisher(Int32, "numbers", QOS).publish(Int32(data=7))
    spin_until(executor, lambda: "end 7" in log, "the coroutine's end")
    assert log == ["start 7", "gate", "end 7"]


def test_entities_made_and_destroyed_by_callbacks_take_effect(
        ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros
    first: list[int] = []
    second: list[int] = []
    subscriptions = {}

    def on_first(message: Int32) -> None:
        first.append(message.data)
        if message.data == 2:  # hand over to a new subscription of another topic
            node.destroy_subscription(subscriptions["first"])
            subscriptions["second"] = node.create_subscription(
                Int32, "second", lambda m: second.append(m.data), QOS)

    subscriptions["first"] = node.create_subscription(Int32, "first", on_first,
                                                      QoSProfile(depth=100))
    first_pub = node.create_publisher(Int32, "first", QoSProfile(depth=100))
    second_pub = node.create_publisher(Int32, "second", QOS)
    spin_until(executor, lambda: first_pub.get_subscription_count() == 1, "the reader")
    for value in range(3):
        first_pub.publish(Int32(data=value))
    spin_until(executor, lambda: "second" in subscriptions, "the hand-over")
    for value in range(3, 6):
        first_pub.publish(Int32(data=value))  # nobody reads these any more
        second_pub.publish(Int32(data=value))
    spin_until(executor, lambda: len(second) == 3, "the new subscription's messages")
    for _ in range(5):
        executor.spin_once(timeout_sec=0.02)
    assert first == [0, 1, 2]
    assert second == [3, 4, 5]


def test_a_subscription_destroyed_behind_its_nodes_back_is_skipped() -> None:
    """Beyond rclpy's contract (its executor raises InvalidHandle here): the destroyed
    subscription is left out of the next wait set and the others are served."""
    with node_on(LeanExecutor) as (node, executor):
        serve_beside_a_subscription_destroyed_behind_its_nodes_back(node, executor)


def serve_beside_a_subscription_destroyed_behind_its_nodes_back(
        node: Node, executor: LeanExecutor) -> None:
    kept: list[int] = []
    dropped: list[int] = []
    doomed = node.create_subscription(Int32, "doomed", lambda m: dropped.append(m.data), QOS)
    node.create_subscription(Int32, "kept", lambda m: kept.append(m.data), QOS)
    doomed_pub = node.create_publisher(Int32, "doomed", QOS)
    kept_pub = node.create_publisher(Int32, "kept", QOS)
    executor.spin_once(timeout_sec=0.05)  # the wait set exists, with both
    doomed.destroy()  # not node.destroy_subscription: the node still lists it
    for value in range(3):
        doomed_pub.publish(Int32(data=value))
        kept_pub.publish(Int32(data=value))
    spin_until(executor, lambda: len(kept) == 3, "the kept subscription's messages")
    executor.spin_once(timeout_sec=0.05)
    assert dropped == []
    assert all(held is not doomed.handle for held in executor._plan.held)  # and freed


def test_an_exception_in_a_callback_reaches_the_spinner(
        ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros

    def fail(_message: Int32) -> None:
        raise RuntimeError("callback failed")

    node.create_subscription(Int32, "numbers", fail, QOS)
    node.create_publisher(Int32, "numbers", QOS).publish(Int32(data=1))
    with pytest.raises(RuntimeError, match="callback failed"):
        spin_until(executor, lambda: False, "the failing callback")


def test_a_done_future_ends_spin_until_future_complete(
        ros: tuple[Node, LeanExecutor]) -> None:
    node, executor = ros
    done: Future = Future()
    count = {"n": 0}

    def on_tick() -> None:
        count["n"] += 1
        if count["n"] == 5:
            done.set_result(True)

    node.create_timer(0.01, on_tick)
    executor.spin_until_future_complete(done, timeout_sec=DEADLINE_S)
    assert done.done() and count["n"] == 5


@EXECUTORS
def test_shutting_the_context_down_ends_the_spin(executor_class: type) -> None:
    with node_on(executor_class) as (node, executor):
        spinning = threading.Event()
        node.create_timer(0.01, spinning.set)
        outcome: list[str] = []

        def spin() -> None:
            try:
                executor.spin()
                outcome.append("returned")
            except ExternalShutdownException:
                outcome.append("external shutdown")

        spinner = threading.Thread(target=spin)
        spinner.start()
        assert spinning.wait(DEADLINE_S), "the executor never ran a callback"
        rclpy.shutdown(context=node.context)
        spinner.join(timeout=DEADLINE_S)
        assert not spinner.is_alive()
        assert outcome in (["external shutdown"], ["returned"])


def test_spinning_until_a_future_adds_one_wake_up_to_it_not_one_per_callback() -> None:
    """rclpy's executor adds a done-callback to the future at every ``spin_once``, so the
    future holds one closure per callback run until it completes (15 MB in a flooded
    evaluator); the team's executor adds one. The future's callbacks are read from rclpy's
    ``Future._callbacks``, where a pending future keeps them."""
    with node_on(LeanExecutor) as (node, executor):
        done: Future = Future()
        count = {"n": 0}

        def on_tick() -> None:
            count["n"] += 1
            if count["n"] == 200:
                assert len(done._callbacks) <= 2  # spin_until_future_complete's and ours
                done.set_result(True)

        node.create_timer(0.001, on_tick)
        executor.spin_until_future_complete(done, timeout_sec=DEADLINE_S)
        assert done.done() and count["n"] == 200
