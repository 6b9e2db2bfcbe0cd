"""RobotAgent's rendezvous mechanics: request, wait, arrival, timeout, release, finish and
lost teammates, driven through the agent's public inputs (own steps, teammates' updates)."""
from __future__ import annotations

import numpy as np
import pytest

from em_exploration_ros.core.agent.robot_agent import RobotAgent, StepInput
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planning.planner_api import (CandidateUtility, Decision,
                                                          PlanningContext)
from em_exploration_ros.core.records.readings import KeyframeMeasurements, TeammateReading
from em_exploration_ros.core.records.team_data import (FrontierType, RendezvousEvent,
                                                       RendezvousState, TargetRecord, TeamUpdate)

PARAMS = ExplorationParams()
ANCHOR = np.array([10.0, 50.0, 0.0])        # robot 0's launch pose (map frame)
TEAMMATE_TARGET = np.array([40.0, 55.0])     # robot 1's target, 30.4 m from robot 0
ODOM_COVARIANCE = np.eye(3) * 1e-6


class PreferRendezvous:
    """Planner for these tests: the first rendezvous candidate, else the first candidate."""

    name = "PREFER_RENDEZVOUS"

    def choose(self, context: PlanningContext) -> Decision:
        meets = [c for c in context.candidates if c.kind == FrontierType.RENDEZVOUS]
        chosen = (meets or list(context.candidates))[0]
        return Decision(chosen, [CandidateUtility(c, 0.0, 0.0, 0.0, 0.0)
                                 for c in context.candidates], 0.0)


def sense(agent: RobotAgent, step: int, odom_xy=(0.0, 0.0), see_robot_1: bool = False):
    """One step of robot 0's own sensing at ``step`` (0.2 s each); robot 0 moved to
    ``odom_xy`` [m] in its odom frame."""
    readings = ((TeammateReading(1, np.array([0.0, 5.0, 0.0]), np.eye(3) * 1e-4),)
                if see_robot_1 else ())
    return agent.step(StepInput(step, step * PARAMS.motion.time_step_s,
                                np.array([*odom_xy, 0.0]), ODOM_COVARIANCE,
                                teammates=readings))


def update_from_1(sequence: int, stamp_s: float, *, keyframe: bool = False,
                  target: np.ndarray | None = None, events=(), finished: bool = False):
    keyframes = (KeyframeMeasurements(1, 0, 0.0, True, -1, np.zeros(3), np.zeros((3, 3)),
                                      (), ()),) if keyframe else ()
    targets = (TargetRecord(1, 0, stamp_s, target, FrontierType.EXPLORATION, None, 0.0),
               ) if target is not None else ()
    return TeamUpdate(1, sequence, stamp_s, keyframes, targets, tuple(events), finished)


def event_from_1(state: RendezvousState, stamp_s: float, point, timeout_s: float = 100.0,
                 requester: int = 1, partner: int = 0, rendezvous_id: int = 3):
    return RendezvousEvent(rendezvous_id, requester, partner, 1, state, stamp_s,
                           np.asarray(point, dtype=float), timeout_s)


def events_of(agent: RobotAgent) -> list[RendezvousEvent]:
    update = agent.take_outgoing()
    return [] if update is None else list(update.rendezvous)


def requester(params: ExplorationParams = PARAMS) -> RobotAgent:
    """Robot 0 that has just requested a rendezvous with robot 1 at robot 1's target."""
    agent = RobotAgent(0, params, ANCHOR, planner=PreferRendezvous())
    agent.apply_team_updates([update_from_1(1, 0.0, keyframe=True, target=TEAMMATE_TARGET)])
    sense(agent, 0, see_robot_1=True)
    return agent


def test_request_carries_a_wait_limit_scaled_by_the_travel() -> None:
    agent = requester()
    assert agent.target.kind == FrontierType.RENDEZVOUS and agent.target.partner_id == 1
    update = agent.take_outgoing()
    [request] = update.rendezvous
    assert request.state == RendezvousState.REQUEST and request.partner_id == 1
    travel = np.hypot(*(TEAMMATE_TARGET - ANCHOR[:2]))
    frontiers = PARAMS.frontiers
    assert request.timeout_s == pytest.approx(
        frontiers.rendezvous_timeout_factor * travel / PARAMS.motion.speed_mps
        + frontiers.rendezvous_timeout_margin_s)
    assert update.targets[0].partner_id == 1 and not update.finished


def test_requester_that_times_out_sends_release_and_drops_the_meeting() -> None:
    agent = requester()
    [request] = events_of(agent)
    late_step = int(np.ceil(request.timeout_s / PARAMS.motion.time_step_s)) + 1
    sense(agent, 5)
    assert agent.rendezvous.meeting_of(0) is not None and events_of(agent) == []
    agent.apply_team_updates([update_from_1(2, (late_step - 1) * PARAMS.motion.time_step_s)])
    sense(agent, late_step)
    released = [e for e in events_of(agent) if e.state == RendezvousState.RELEASE]
    assert [(e.requester_id, e.rendezvous_id) for e in released] == [(0, request.rendezvous_id)]
    # It chose again (the same teammate's target is still the only rendezvous): a new id.
    assert agent.rendezvous.meeting_of(0).rendezvous_id != request.rendezvous_id


def test_requester_gives_up_when_the_partner_releases() -> None:
    agent = requester()
    [request] = events_of(agent)
    release = RendezvousEvent(request.rendezvous_id, 0, 1, 1, RendezvousState.RELEASE, 0.4,
                              TEAMMATE_TARGET, request.timeout_s)
    agent.apply_team_updates([update_from_1(2, 0.4, events=[release])])
    assert agent.rendezvous.meeting_of(0) is None and agent.target is None


def test_partner_waits_at_the_meeting_point_until_both_arrived() -> None:
    agent = RobotAgent(0, PARAMS, ANCHOR)
    meeting_point = ANCHOR[:2] + [4.0, 0.0]
    agent.apply_team_updates([update_from_1(1, 0.0, keyframe=True, events=[
        event_from_1(RendezvousState.REQUEST, 0.0, meeting_point)])])
    command = sense(agent, 0, see_robot_1=True)
    assert command.forward_m > 0.0 and agent.decisions == []   # heads for the meeting point
    np.testing.assert_allclose(agent.rendezvous.is_waiting(0), meeting_point)
    command = sense(agent, 1, odom_xy=(4.0, 0.0))                # arrived: stops and says so
    assert (command.turn_rad, command.forward_m) == (0.0, 0.0)
    [arrived] = events_of(agent)
    assert arrived.state == RendezvousState.ARRIVED and arrived.sender_id == 0
    assert sense(agent, 2, odom_xy=(4.0, 0.0)).forward_m == 0.0  # still waiting
    agent.apply_team_updates([update_from_1(2, 0.6, events=[
        event_from_1(RendezvousState.ARRIVED, 0.6, meeting_point)])])
    assert agent.rendezvous.open_meetings() == [] and agent.rendezvous.is_waiting(0) is None


def test_partner_stops_waiting_at_the_wait_limit_or_on_release() -> None:
    agent = RobotAgent(0, PARAMS, ANCHOR)
    point = ANCHOR[:2] + [4.0, 0.0]
    agent.apply_team_updates([update_from_1(1, 0.0, keyframe=True, events=[
        event_from_1(RendezvousState.REQUEST, 0.0, point, timeout_s=30.0)])])
    sense(agent, 0, see_robot_1=True)
    sense(agent, 149)                                            # t = 29.8 s
    np.testing.assert_allclose(agent.rendezvous.is_waiting(0), point)
    sense(agent, 150)                                            # t = 30 s: limit reached
    assert agent.rendezvous.is_waiting(0) is None
    agent.apply_team_updates([update_from_1(2, 30.2, events=[
        event_from_1(RendezvousState.REQUEST, 30.2, point, rendezvous_id=4)])])
    assert agent.rendezvous.is_waiting(0) is not None
    agent.apply_team_updates([update_from_1(3, 30.4, events=[
        event_from_1(RendezvousState.RELEASE, 30.4, point, rendezvous_id=4)])])
    assert agent.rendezvous.is_waiting(0) is None


def test_finished_robot_declines_requests_and_says_it_finished() -> None:
    agent = RobotAgent(0, PARAMS.replace(run={"until_explored": 0.0}), ANCHOR)
    agent.apply_team_updates([update_from_1(1, 0.0, keyframe=True)])
    sense(agent, 0, see_robot_1=True)
    assert agent.finished and agent.take_outgoing().finished
    agent.apply_team_updates([update_from_1(2, 0.2, events=[
        event_from_1(RendezvousState.REQUEST, 0.2, [30.0, 30.0])])])
    [release] = events_of(agent)
    assert release.state == RendezvousState.RELEASE and release.requester_id == 1
    assert agent.rendezvous.open_meetings() == []


def test_finished_teammate_is_no_candidate_and_ends_the_meeting() -> None:
    agent = requester()
    events_of(agent)
    assert 1 in agent.rendezvous_partners()
    agent.apply_team_updates([update_from_1(2, 0.2, finished=True)])
    assert agent.finished_teammates == {1} and agent.rendezvous_partners() == {}
    assert agent.rendezvous.meeting_of(0) is None and agent.target is None
    assert [e.state for e in events_of(agent)] == [RendezvousState.RELEASE]
    sense(agent, 1)
    assert agent.target.kind != FrontierType.RENDEZVOUS


def test_silent_partner_stays_a_candidate_and_the_requester_keeps_going() -> None:
    agent = requester()
    events_of(agent)
    silent_steps = int(PARAMS.frontiers.teammate_silent_after_s / PARAMS.motion.time_step_s)
    sense(agent, silent_steps)
    assert not agent.is_lost(1) and agent.rendezvous.meeting_of(0) is not None
    sense(agent, silent_steps + 1)
    assert agent.is_lost(1) and 1 in agent.rendezvous_partners()
    assert agent.rendezvous.meeting_of(0) is not None
    assert RendezvousState.RELEASE not in [e.state for e in events_of(agent)]


def test_partner_stops_waiting_for_a_requester_out_of_contact() -> None:
    agent = RobotAgent(0, PARAMS, ANCHOR)
    agent.apply_team_updates([update_from_1(1, 0.0, keyframe=True, events=[
        event_from_1(RendezvousState.REQUEST, 0.0, ANCHOR[:2] + [4.0, 0.0], timeout_s=1000.0)])])
    sense(agent, 0, see_robot_1=True)
    assert agent.rendezvous.is_waiting(0) is not None
    silent_steps = int(PARAMS.frontiers.teammate_silent_after_s / PARAMS.motion.time_step_s)
    sense(agent, silent_steps + 1, odom_xy=(4.0, 0.0))
    assert agent.is_lost(1) and agent.rendezvous.is_waiting(0) is None
    assert RendezvousState.RELEASE in [e.state for e in events_of(agent)]
