"""The link model between robots (core/links/link_model.py), the wire sizes of team data
(core/records/team_wire.py: a request's bytes) and em-sim under imperfect links."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from em_exploration_ros.core.links.link_model import (DeliveryLedger, Frame, FrameKind, TeamLinks,
                                                      loss_draw, perfect_links)
from em_exploration_ros.core.params import ExplorationParams, LinkParams
from em_exploration_ros.core.records.team_wire import cdr_size, request_cdr_size
from em_exploration_ros.core.sessions.team_runner import TeamRunner

DT = 0.2


def _links(**overrides) -> TeamLinks:
    return TeamLinks(dataclasses.replace(LinkParams(), **overrides), 3, DT, seed=7)


def _update(sender: int, seq: int, step: int, size: int = 100) -> Frame:
    return Frame(FrameKind.UPDATE, sender, tuple(r for r in range(3) if r != sender), seq,
                 size, step, payload=(sender, seq))


CLOSE = np.array([[0.0, 0.0], [10.0, 0.0], [40.0, 0.0]])


def _arrivals(links: TeamLinks, steps: int, positions=CLOSE) -> dict[tuple, int]:
    """{(receiver, payload): arrival step} after transmitting steps 0..steps-1."""
    arrivals = {}
    for step in range(steps):
        for delivery in links.deliveries(step):
            arrivals.setdefault((delivery.receiver, delivery.frame.payload), step)
        links.transmit(step, positions)
    for delivery in links.deliveries(10**9):
        arrivals.setdefault((delivery.receiver, delivery.frame.payload), -1)
    return arrivals


def test_perfect_links_deliver_everything_at_the_next_step():
    links = _links()
    assert perfect_links(links.params)
    links.offer(_update(0, 1, 0))
    links.offer(_update(1, 1, 0))
    links.transmit(0, CLOSE)
    assert links.deliveries(0) == []
    got = {(d.receiver, d.frame.payload) for d in links.deliveries(1)}
    assert got == {(1, (0, 1)), (2, (0, 1)), (0, (1, 1)), (2, (1, 1))}
    assert links.counts.delivered == 4 and links.counts.lost == 0


def test_range_uses_true_positions_at_the_transmission_step():
    links = _links(range_m=15.0)
    links.offer(_update(0, 1, 0))
    links.transmit(0, CLOSE)  # robot 1 at 10 m, robot 2 at 40 m
    assert {d.receiver for d in links.deliveries(1)} == {1}
    assert links.counts.out_of_range == 1
    links.offer(_update(0, 2, 1))
    links.transmit(1, np.array([[0.0, 0.0], [30.0, 0.0], [14.0, 0.0]]))
    assert {d.receiver for d in links.deliveries(2)} == {2}


def test_loss_draw_is_fixed_by_its_key_and_has_the_stated_rate():
    assert loss_draw(3, FrameKind.UPDATE, 0, 1, 5, 10) == loss_draw(3, FrameKind.UPDATE, 0, 1,
                                                                      5, 10)
    assert loss_draw(3, FrameKind.UPDATE, 0, 1, 5, 10) != loss_draw(3, FrameKind.UPDATE, 0, 2,
                                                                      5, 10)
    draws = np.array([loss_draw(0, FrameKind.UPDATE, 0, 1, seq, seq) for seq in range(20000)])
    assert 0.0 <= draws.min() and draws.max() < 1.0
    assert abs(np.mean(draws < 0.3) - 0.3) < 0.015


def test_loss_does_not_depend_on_the_order_frames_reach_the_relay():
    forward = _links(loss_probability=0.5, queue_frames=20)
    backward = _links(loss_probability=0.5, queue_frames=20)
    frames = [_update(sender, seq, 0) for sender in range(3) for seq in range(1, 30)]
    for frame in frames:
        forward.offer(dataclasses.replace(frame))
    for frame in reversed(frames):
        backward.offer(dataclasses.replace(frame))
    got_forward = set(_arrivals(forward, 3))
    got_backward = set(_arrivals(backward, 3))
    assert got_forward == got_backward
    assert forward.counts.dropped == backward.counts.dropped == 3 * 9 * 2  # 9 of 29 too many
    assert 0.3 < forward.counts.lost / (20 * 3 * 2) < 0.7


def test_latency_delays_arrival_by_whole_steps():
    links = _links(latency_s=1.0)  # 5 steps of 0.2 s
    links.offer(_update(0, 1, 3))
    arrivals = _arrivals(links, 12)
    assert arrivals[(1, (0, 1))] == 3 + 5


def test_bandwidth_spaces_transmissions_and_the_queue_is_bounded_with_tail_drop():
    links = _links(bandwidth_bytes_per_s=100.0, queue_frames=3)  # 100 B frame: 1 s = 5 steps
    for seq in range(1, 6):
        links.offer(_update(0, seq, 0))
    arrivals = _arrivals(links, 30)
    assert links.counts.dropped == 4  # frames 4 and 5 x two addressees
    assert [arrivals[(1, (0, seq))] for seq in (1, 2, 3)] == [5, 10, 15]
    assert (1, (0, 4)) not in arrivals
    assert links.counts.bytes_sent == 300


def test_ledger_counts_on_time_late_and_never():
    ledger = DeliveryLedger(3)
    ledger.sent(0, 1, 0)
    ledger.delivered(0, 1, 1, 1)  # on time
    ledger.delivered(0, 2, 1, 7)  # late
    ledger.sent(1, 1, 0)
    ledger.delivered(1, 0, 1, 1)  # robot 2 never gets it
    ledger.sent(2, 1, 50)  # not due before step 20
    counts = ledger.counts(next_step=20)
    assert (counts.sent, counts.on_time, counts.late, counts.never) == (4, 2, 1, 1)


@pytest.fixture(scope="module")
def short_run_updates():
    """Team updates of a short real run (keyframes with readings, landmarks, targets)."""
    params = ExplorationParams().replace(world={"width_m": 30.0, "height_m": 30.0,
                                                "num_landmarks": 4},
                                         run={"max_steps": 60})
    runner = TeamRunner(params)
    sent = []
    links = runner.world.relay.links
    original = links.offer

    def spy(frame):
        if frame.kind == FrameKind.UPDATE:
            sent.append(frame)
        return original(frame)

    links.offer = spy
    runner.run()
    return sent


def test_frames_carry_the_wire_size_of_what_they_carry(short_run_updates):
    serialization = pytest.importorskip("rclpy.serialization")
    from em_exploration_ros.core.records.team_wire import TeamWireFormat
    from em_exploration_ros.nodes.conversions import team_update_to_msg
    assert short_run_updates
    form = TeamWireFormat(ExplorationParams())
    for frame in short_run_updates:
        wire = serialization.serialize_message(team_update_to_msg(frame.payload, form))
        assert frame.size_bytes == cdr_size(frame.payload) == len(wire)
    from em_exploration_msgs.msg import TeamUpdateRequest
    request = TeamUpdateRequest(requester_id=1, robot_id=2, first_sequence=3, last_sequence=9)
    assert request_cdr_size() == len(serialization.serialize_message(request))


def _small_run(**links) -> TeamRunner:
    params = ExplorationParams().replace(
        world={"width_m": 40.0, "height_m": 40.0, "num_landmarks": 5},
        run={"max_steps": 900, "seed": 1}, links=links)
    return TeamRunner(params)


def _targets(summary) -> list:
    return [[(t.x, t.y, t.type) for t in robot.targets] for robot in summary.robots]


@pytest.mark.parametrize("links", [{"range_m": 15.0}, {"loss_probability": 0.3},
                                   {"bandwidth_bytes_per_s": 60.0}],
                         ids=["range15", "loss30", "bw60"])
def test_team_copes_with_poor_links_and_is_deterministic(links):
    first = _small_run(**links).run()
    again = _small_run(**links).run()
    assert _targets(first) == _targets(again)
    assert first.team_updates == again.team_updates
    counts = first.team_updates
    assert counts["late"] + counts["never"] > 0
    assert counts["on_time"] + counts["late"] + counts["never"] == counts["sent"]
    assert not first.stop_reason.startswith("stalled")
    assert first.decisions > 0 and first.explored_ratio > 0.3


def test_gap_requests_one_gap_per_interval_teammates_in_turn():
    from em_exploration_ros.core.links.gap_requests import GapRequests
    from em_exploration_ros.core.records.team_data import TeamUpdate, TeamUpdateInbox
    inbox = TeamUpdateInbox(0, 3)
    for robot in (1, 2):
        inbox.receive(TeamUpdate(robot, 1, 0.0))
        inbox.receive(TeamUpdate(robot, 4, 0.6))  # 2..3 missing from both
    inbox.pop_ready()
    requests = GapRequests(0, 3, interval_steps=25)
    first = requests.due(10, inbox)
    assert (first.robot_id, first.first_sequence, first.last_sequence) == (1, 2, 3)
    assert requests.due(34, inbox) is None  # not yet: one request per 25 steps
    assert requests.due(35, inbox).robot_id == 2  # the other teammate's turn
    assert requests.due(60, inbox).robot_id == 1
    for robot in (1, 2):
        inbox.receive(TeamUpdate(robot, 2, 0.2))
        inbox.receive(TeamUpdate(robot, 3, 0.4))
    inbox.pop_ready()
    assert requests.due(100, inbox) is None


def test_perfect_links_deliver_every_update_on_time_in_a_run():
    summary = _small_run().run()
    counts = summary.team_updates
    assert counts["sent"] > 0 and counts["sent"] == counts["on_time"]
