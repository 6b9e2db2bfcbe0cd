"""em-record counts what was published while it recorded but never reached it
(bag_format/message_losses.py): from the writers' publication sequence numbers, without
false counts on topics with several writers."""
from __future__ import annotations

import re
import signal
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from ros_process import REPO_ROOT, NodeProcess, wait_until
from std_msgs.msg import UInt32

from em_exploration_ros.bag_format.bag_reader import BagScanner
from em_exploration_ros.bag_format.message_losses import MessageLosses

TOPIC = "/em_test/flood"
BURST = 300
#: Messages after the burst, one per poll until em-record reports the gap, at most this many.
MAX_MARKERS = 100


def test_a_single_writers_gaps_are_counted_and_reported_once():
    losses = MessageLosses(writers=1)
    for sequence in (1, 2, 5, 6, 10):
        losses.received(sequence)
    assert losses.lost == 5
    assert losses.unreported() == 5 and losses.unreported() == 0
    losses.received(None)  # a middleware without numbers: nothing to say
    losses.received(11)
    assert losses.lost == 5


def test_two_writers_interleaved_count_no_losses():
    losses = MessageLosses(writers=1)  # the second writer appeared after the last poll
    for sequence in (500, 501, 1, 502, 2, 3, 503):
        losses.received(sequence)
    assert losses.lost == 0
    losses.writers(2)
    for sequence in (504, 4, 600, 5):
        losses.received(sequence)
    assert losses.lost == 0


def test_a_restarted_writer_is_counted_again_once_it_is_alone():
    losses = MessageLosses(writers=1)
    for sequence in (40, 41):
        losses.received(sequence)
    losses.received(3)  # the restarted process: its first two never reached the recorder
    assert losses.lost == 0  # ... but nothing tells it from a second writer yet
    losses.writers(2)  # the dead one still matched
    losses.received(4)
    losses.writers(1)
    for sequence in (50, 51, 54):  # the first after the poll starts the count afresh
        losses.received(sequence)
    assert losses.lost == 2


def _recorded_values(bag: Path, *, tolerant: bool = False) -> list[int]:
    """The ``data`` of every message of TOPIC in the bag so far, in file order."""
    scanner = BagScanner(bag / f"{bag.name}_0.mcap", tolerant=tolerant)
    return [deserialize_message(message.data, UInt32).data
            for channel, message in scanner.messages() if channel.topic == TOPIC]


def test_em_record_reports_every_message_it_did_not_receive(tmp_path: Path):
    """A best-effort flood while the recorder is stopped (SIGSTOP) with a keep-last queue of
    one: most of the burst is lost. Message k carries data k and is its writer's
    publication k + 1, so what em-record reports lost must be exactly the values missing
    from the bag between its first and last message, whatever reached it when."""
    bag = tmp_path / "rec"
    recorder = NodeProcess([
        "python", "-m", "em_exploration_ros.tools.record", "-o", str(bag), "--topics", TOPIC,
        "--queue-depth", "1", "--poll-interval", "0.2", "--chunk-interval", "0.1"],
        tmp_path / "record.log", {"PYTHONPATH": str(REPO_ROOT)})
    context = rclpy.Context()
    rclpy.init(context=context)
    node = None
    try:
        with recorder:
            node = Node("em_test_flood", context=context)
            publisher = node.create_publisher(
                UInt32, TOPIC, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
            wait_until(lambda: publisher.get_subscription_count() >= 1, 30.0,
                       "em-record subscribed")
            recorder.wait_for_output(f"recording {TOPIC}", 30.0)
            publisher.publish(UInt32(data=0))
            wait_until(lambda: _recorded_values(bag, tolerant=True) == [0], 30.0,
                       "the first message in the bag (its chunk closed)")
            recorder.signal_group(signal.SIGSTOP)
            for count in range(1, BURST):
                publisher.publish(UInt32(data=count))
            recorder.signal_group(signal.SIGCONT)
            # Markers until the poll that counted the gap says so: in one CI run none of five
            # sent at once reached the recorder within 30 s, which left it nothing to count
            # the gap by (why was not found: stops of 0.5, 2 and 5 s lost none here).
            markers = iter(range(BURST, BURST + MAX_MARKERS))

            def publish_marker() -> None:
                value = next(markers, None)
                if value is not None:
                    publisher.publish(UInt32(data=value))

            publish_marker()
            recorder.wait_for_output(f"{TOPIC}: ", 30.0, while_waiting=publish_marker)
            assert recorder.stop() == 0, recorder.output()
    finally:
        # The node goes with the test, pass or fail: its publisher left in the graph made
        # every later recording of the session record an empty /em_test/flood too.
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    output = recorder.output()
    values = _recorded_values(bag)
    missing = values[-1] - values[0] + 1 - len(values)
    assert values == sorted(values) and values[0] == 0 and len(values) < BURST // 2, values
    reported = re.search(r"(\d+) messages published while recording never reached the "
                         rf"recorder: {TOPIC} (\d+)", output)
    assert reported, output
    assert int(reported.group(1)) == int(reported.group(2)) == missing > 0, (values, output)
    assert re.search(rf"{TOPIC}: \d+ messages published while recording never reached", output)
