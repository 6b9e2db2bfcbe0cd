"""Every node of a run carries its identity (``run_id``) and drops what another run on the
same domain publishes, with one throttled WARN naming that run (issue 40, point 1):
session level, without ROS."""
from __future__ import annotations

from em_exploration_ros.core.agent.input_checks import RejectionLog, reason_kind
from em_exploration_ros.core.node_settings import (EvaluatorNodeSettings, RobotNodeSettings,
                                                   WorldNodeSettings, checked_settings)
from em_exploration_ros.core.sessions.evaluator_session import EvaluatorSession
from em_exploration_ros.core.sessions.robot_session import RobotSession
from em_exploration_ros.core.sessions.world_session import WorldSession
from test_evaluator_session import PARAMS

RUN, OTHER = 7_000_000_000_123, 42


def sessions(run_id: int) -> list:
    return [WorldSession(PARAMS, WorldNodeSettings(run_id=run_id), 0.0),
            RobotSession(1, PARAMS, RobotNodeSettings(robot_id=1, run_id=run_id)),
            EvaluatorSession(PARAMS, EvaluatorNodeSettings(run_id=run_id), 0.0, 3.0)]


def test_each_session_drops_a_message_of_another_run_naming_both_runs():
    for session in sessions(RUN):
        assert session.run_problem(RUN) is None
        assert session.run_problem(OTHER) == (
            f"of run {OTHER}, not of this node's run {RUN} (another run on the domain)")
        assert session.run_problem(0) is not None  # a node started by hand, without one


def test_nodes_started_by_hand_share_run_0():
    for settings in (WorldNodeSettings(), RobotNodeSettings(), EvaluatorNodeSettings()):
        assert settings.run_id == 0
    for session in sessions(0):
        assert session.run_problem(0) is None and session.run_problem(RUN) is not None


def test_the_run_id_setting_takes_any_positive_int64():
    for cls in (WorldNodeSettings, RobotNodeSettings, EvaluatorNodeSettings):
        assert checked_settings(cls, {"run_id": 2**63 - 1}).run_id == 2**63 - 1
        for bad in (-1, 2**63):
            try:
                checked_settings(cls, {"run_id": bad})
            except ValueError:
                continue
            raise AssertionError(f"{cls.__name__} took run_id {bad}")


def test_another_runs_messages_share_one_throttled_line_per_topic():
    """The node's input guard throttles per topic and kind of reason: every run's id is
    blanked in the kind, so a flood from other runs makes one line every period."""
    world = sessions(RUN)[0]
    reasons = [world.run_problem(other) for other in (OTHER, OTHER + 1, 3)]
    assert len({reason_kind(r) for r in reasons}) == 1
    log = RejectionLog(5.0)
    counts = [log.note("/robot_0/motion_command " + reason_kind(r), 1.0) for r in reasons]
    assert counts[0] is not None and counts[1:] == [None, None]
