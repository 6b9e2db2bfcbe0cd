"""The node processes' own settings (not exploration parameters), one table per node.

Each class lists one node's settings with default, description and range, like the
exploration parameters of ``core.params`` (same field metadata, same checks): the nodes
declare them from here as read-only ROS parameters (``nodes.ros_params``), and a
parameter file's node sections (``/em_world:``, ``/robot_0/em_robot:``) are checked
against them before any process starts (``core.params_yaml.check_parameter_document``).
A new setting of a node belongs in its table.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from em_exploration_ros.core.params import param_field, replace_checked

LOCKSTEP, REALTIME = "lockstep", "realtime"


def run_id_field() -> Any:
    """The ``run_id`` setting every node has (the same value for every node of a run)."""
    return param_field(
        0, "Identity of the run this node belongs to, carried by every project message it "
        "publishes: a message of another run_id is dropped with a WARN naming that run "
        "(run_team.sh gives each run a new one; nodes started by hand share 0 unless given "
        "one).", 0, 2**63 - 1)


@dataclass(frozen=True)
class WorldNodeSettings:
    """em-world (node name ``em_world``)."""

    run_id: int = run_id_field()
    clock_mode: str = param_field(
        LOCKSTEP, "lockstep: a step waits for every robot's command (deterministic); "
        "realtime: steps at a fixed wall rate with the latest commands.",
        choices=(LOCKSTEP, REALTIME))
    realtime_factor: float = param_field(1.0, "Realtime mode: simulation seconds per wall second.",
                                         0.01, 1000.0)
    robot_timeout_s: float = param_field(
        30.0, "Lockstep: wall seconds a robot may stay silent on a step before it is treated "
        "as lost (zero motion until it answers again).", 0.01, 1e6)
    liveliness_grace_s: float = param_field(
        4.0, "Lockstep: wall seconds a robot whose liveliness was reported lost may stay "
        "silent on a step before it is treated as lost (a live robot answers within this "
        "even when a lossy network delayed its liveliness).", 0.01, 1e6)
    step_resend_s: float = param_field(
        2.0, "Lockstep: wall seconds between re-sends of a step's sensor messages to a robot "
        "whose answer is missing.", 0.01, 1e6)
    startup_timeout_s: float = param_field(
        60.0, "Wall seconds to wait for every robot to connect before the first step; robots "
        "not connected by then are treated as stopped.", 0.0, 1e6)
    startup_settle_s: float = param_field(
        2.0, "Wall seconds every connection must hold before the first step, so the "
        "middleware has matched the robots' team-update streams too (the graph shows a "
        "reader before every writer delivers to it: when Fast DDS misses a participant's "
        "first announcements, a robot and the evaluator find each other only at the next, "
        "up to 1 s later with config/fastdds_profiles.xml, 3 s with Fast DDS's default).",
        0.0, 60.0)
    lost_team_wait_s: float = param_field(
        0.0, "Lockstep: wall seconds to wait, when every robot that has not finished is lost, "
        "for one to come back before ending the mission (0: end at once; run_team.sh "
        "--respawn gives 60, the time to restart them).", 0.0, 1e6)
    max_sim_time_s: float = param_field(
        0.0, "Stop stepping after this simulation time [s] (0: no limit besides "
        "run.max_steps).", 0.0, 1e9)
    wait_for_evaluator: bool = param_field(
        False, "Before the first step, also wait until an evaluator listens to the ground "
        "truth and to every robot's team updates.")
    wait_for_recorder: bool = param_field(
        False, "Before the first step, also wait until the recorder (em-record) subscribes "
        "to every topic the world publishes.")


@dataclass(frozen=True)
class RobotNodeSettings:
    """em-robot (node name ``em_robot``)."""

    run_id: int = run_id_field()
    robot_id: int = param_field(0, "Id of this robot (0-based).", 0, 25)
    barrier_timeout_s: float = param_field(
        10.0, "Lockstep: wall seconds to wait for teammates' updates named by the world's "
        "barrier before going on without them.", 0.01, 1e6)
    request_period_s: float = param_field(
        0.5, "Wall seconds between two requests for missing team updates.", 0.01, 1e3)
    resend_interval_s: float = param_field(
        0.5, "Wall seconds between two re-sends of team updates to the same requester "
        "(requests in between are merged into one pending range).", 0.0, 1e3)
    world_lost_timeout_s: float = param_field(
        120.0, "Wall seconds to wait, logging, for a world that left the ROS graph after "
        "the run started before the robot exits (exit code 4).", 1.0, 1e6)
    rejoin_settle_s: float = param_field(
        1.0, "After a restart: wall seconds to listen for teammates' copies of this robot's "
        "earlier stream before resuming.", 0.0, 1e3)
    rejoin_timeout_s: float = param_field(
        20.0, "After a restart: wall seconds after which the robot resumes with what it "
        "recovered of its stream, even if records are missing.", 0.1, 1e6)
    state_dir: str = param_field(
        "", "Folder of this robot's stream journal (robot_<id>.journal): every record of its "
        "team-update stream is appended there, and a restarted process reads its stream "
        "back from it when no teammate holds it (empty: no journal; run_team.sh gives "
        "<run folder>/state).")
    wait_for_recorder: bool = param_field(
        False, "Before its first step, wait until the recorder (em-record) subscribes to "
        "every topic this robot publishes (run_team.sh --record sets it), so that the "
        "recording holds every message from the first step: volatile topics keep nothing "
        "for a late subscriber.")
    recorder_wait_s: float = param_field(
        5.0, "Wall seconds to wait for the recorder before the first step is answered "
        "anyway (with a warning); keep it below the world's robot_timeout_s.", 0.0, 1e6)


@dataclass(frozen=True)
class EvaluatorNodeSettings:
    """em-evaluator (node name ``em_evaluator``)."""

    run_id: int = run_id_field()
    summary_path: str = param_field("summary.json", "Where the run summary JSON is written.")
    map_png_path: str = param_field(
        "", "Where the final map PNG is written (empty: next to the summary, <stem>_map.png).")
    metrics_interval_s: float = param_field(
        2.0, "Simulation seconds between two evaluations of the team metrics.", 0.001, 1e6)
    progress_interval_s: float = param_field(
        20.0, "Simulation seconds between two progress lines in the log.", 0.001, 1e9)
    max_sim_time_s: float = param_field(
        0.0, "End the run at this simulation time [s] (0: no limit besides run.max_steps); "
        "give the world the same value.", 0.0, 1e9)
    estimate_wait_s: float = param_field(
        30.0, "Wall seconds an evaluation waits for the estimates of the latest keyframe of "
        "every robot that is not lost before it goes on with older ones (a loaded or flooded "
        "evaluator can take seconds to reach them; going on early changes that evaluation); "
        "a robot waited for in vain is not waited for again until it publishes.", 0.0, 1e6)
    silence_timeout_s: float = param_field(
        120.0, "End the run (exit code 3) when no ground truth arrived for this many wall "
        "seconds; a world that leaves the ROS graph is logged at once.", 0.1, 1e6)
    liveliness_grace_s: float = param_field(
        4.0, "Wall seconds a robot's liveliness must stay lost before the robot counts as "
        "lost.", 0.0, 1e6)


#: Node name -> its settings table.
NODE_SETTINGS: dict[str, type] = {"em_world": WorldNodeSettings, "em_robot": RobotNodeSettings,
                                  "em_evaluator": EvaluatorNodeSettings}


def checked_settings(settings_type: type, values: dict[str, Any]) -> Any:
    """The settings of ``settings_type`` with ``values`` applied after the type and range
    checks of ``core.params`` (integers accepted for floats); ``ValueError`` names the
    setting, and for an unknown name the closest valid one."""
    return replace_checked(settings_type(), values)

