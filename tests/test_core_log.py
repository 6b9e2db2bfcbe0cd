"""The ROS-free core's Python log records reach a node's ROS logger (``nodes/core_log``)."""
from __future__ import annotations

import logging
import textwrap

from ros_process import NodeProcess

from em_exploration_ros.nodes.core_log import PACKAGE_LOGGER, core_logs_to


class RecordingLogger:
    """A stand-in for rclpy's ``RcutilsLogger``: keeps (severity, text) per call."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def __getattr__(self, severity: str):
        if severity not in {"debug", "info", "warning", "error", "fatal"}:
            raise AttributeError(severity)
        return lambda text: self.lines.append((severity, text))


def test_each_level_goes_to_its_severity_and_debug_stays_out():
    ros = RecordingLogger()
    core = logging.getLogger("em_exploration_ros.core.slam.team_slam")
    with core_logs_to(ros):
        core.debug("not at INFO")
        core.info("robot %d finished: %s", 1, "explored")
        core.warning("late readings left out")
        core.error("planner failed")
        core.critical("cannot go on")
    assert ros.lines == [("info", "robot 1 finished: explored"),
                         ("warning", "late readings left out"),
                         ("error", "planner failed"), ("fatal", "cannot go on")]


def test_a_record_with_a_traceback_carries_it_and_a_bad_format_raises_nothing(capsys):
    ros = RecordingLogger()
    core = logging.getLogger("em_exploration_ros.core.agent.robot_agent")
    with core_logs_to(ros):
        try:
            raise RuntimeError("boom")
        except RuntimeError:
            core.exception("planner failed")
        core.warning("%d readings", "not a number")
    assert len(ros.lines) == 1
    severity, text = ros.lines[0]
    assert severity == "error" and text.startswith("planner failed\nTraceback")
    assert "RuntimeError: boom" in text
    assert "--- Logging error ---" in capsys.readouterr().err  # logging's own report


def test_outside_the_block_nothing_is_forwarded_and_the_logger_is_as_before():
    package = logging.getLogger(PACKAGE_LOGGER)
    before = package.level, package.propagate, list(package.handlers)
    ros = RecordingLogger()
    with core_logs_to(ros):
        pass
    logging.getLogger("em_exploration_ros.core.x").warning("after the block")
    assert ros.lines == []
    assert (package.level, package.propagate, list(package.handlers)) == before


# A node whose callback and wrap-up log through core modules' Python loggers, run by the
# nodes' common main.
CORE_LOGGING_NODE = textwrap.dedent("""
    import logging, sys
    from rclpy.node import Node
    from rclpy.task import Future
    from em_exploration_ros.nodes.node_main import run_node

    class CoreLogging(Node):
        def __init__(self):
            super().__init__("core_logging", namespace="/robot_4")
            self.done = Future()
            self.create_timer(0.01, self.tick)

        def tick(self):
            logging.getLogger("em_exploration_ros.core.agent.robot_agent").info(
                "robot 4 finished: %s", "probe")
            logging.getLogger("em_exploration_ros.core.slam.team_slam").warning(
                "a keyframe's late readings left out")
            self.done.set_result(True)

    def wrap_up(node):
        logging.getLogger("em_exploration_ros.core.planning.em_step").error("at wrap-up")
        return 0

    sys.exit(run_node(CoreLogging, "core_logging", wrap_up=wrap_up))
""")


def test_a_node_process_logs_the_core_s_lines_under_its_name(tmp_path):
    code, output = NodeProcess.run_script(CORE_LOGGING_NODE, tmp_path / "node.log", 60.0)
    assert code == 0, output
    for severity, text in (("INFO", "robot 4 finished: probe"),
                           ("WARN", "a keyframe's late readings left out"),
                           ("ERROR", "at wrap-up")):
        lines = [line for line in output.splitlines() if text in line]
        assert len(lines) == 1, output  # once, not also bare on stderr
        assert lines[0].startswith(f"[{severity}]") and "[robot_4.core_logging]:" in lines[0]
