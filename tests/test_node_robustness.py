"""Node processes against bad parameters and a vanishing world (issue 11, points 8 and 9).

- A parameter file with an integer where a float is expected is taken; a wrong type, an
  out-of-range value or a misspelt name ends the node at once with exit code 2, one
  fatal line naming the parameter (and the closest valid name), no traceback.
- Settings read once are read-only: setting them on a running node is refused.
- A robot started on its own whose world leaves the ROS graph says so and exits (code 4)
  after world_lost_timeout_s; one that sees the world come back goes on.
- A robot the evaluator never saw alive (stopped before its liveliness reached the
  evaluator) is reported lost after the liveliness grace, not silently left out.
- A robot stopped until the world went on without it (and the sensor data of the steps it
  missed is gone) resumes at the world's step when it runs again.
- Ctrl-C raises nothing inside a node's callbacks (where it once broke a message being
  taken and ended the world with exit code 1): it shuts ROS down and the node wraps up.
"""
from __future__ import annotations

import json
import signal
import textwrap
import time

import pytest
import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from em_exploration_msgs.msg import MotionCommand, SonarScan, TeamUpdate, WorldStatus
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from ros_process import NodeProcess, loaded_modules, ros_args
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header

from em_exploration_ros.nodes.qos import GROUND_TRUTH_QOS, LATCHED_QOS, SENSOR_QOS, TEAM_QOS

WORLD = "em_exploration_ros.nodes.world_node"
ROBOT = "em_exploration_ros.nodes.robot_node"
EVALUATOR = "em_exploration_ros.nodes.evaluator_node"
ONE_ROBOT = {"world.num_robots": 1, "world.width_m": 30.0, "world.height_m": 30.0,
             "world.num_landmarks": 2}
START_S = 30.0  # process start-up on a loaded machine


def write_params(tmp_path, text: str):
    path = tmp_path / "params.yaml"
    path.write_text(text)
    return path


def test_integers_are_taken_where_floats_are_expected(tmp_path):
    params = write_params(tmp_path, "/**:\n  ros__parameters:\n    world:\n      width_m: 60\n"
                          "      height_m: 60\n      num_robots: 1\n"
                          "/em_world:\n  ros__parameters:\n    robot_timeout_s: 5\n")
    with NodeProcess.start_module(WORLD, ros_args(params_file=params),
                                  log_path=tmp_path / "world.log") as world:
        world.wait_for_output("world ready", START_S)
        assert "60 m x 60 m" in world.output()


@pytest.mark.parametrize("text, message", [
    ("/em_world:\n  ros__parameters:\n    robot_timeout_s: abc\n",
     "parameter robot_timeout_s: WorldNodeSettings.robot_timeout_s must be a number"),
    ("/em_world:\n  ros__parameters:\n    robot_timout_s: 3.0\n",
     "unknown parameter 'robot_timout_s' (did you mean 'robot_timeout_s'?)"),
    ("/**:\n  ros__parameters:\n    world.num_robots: 0\n", "outside [1, 26]"),
    ("/**:\n  ros__parameters:\n    planner.name: EM_9\n", "must be one of"),
    ("/**:\n  ros__parameters:\n    links.loss_probability: 1.0\n", "outside [0.0, 0.99]"),
])
def test_bad_parameters_end_the_node_with_exit_code_2_and_no_traceback(tmp_path, text, message):
    params = write_params(tmp_path, text)
    world = NodeProcess.start_module(WORLD, ros_args(params_file=params),
                                     log_path=tmp_path / "world.log")
    with world:
        code = world.wait(START_S)
    output = world.output()
    assert code == 2, output
    assert "cannot start" in output and message in output, output
    assert "Traceback" not in output, output


def test_settings_read_once_are_read_only(tmp_path):
    args = ros_args(params=dict(ONE_ROBOT, robot_id=0), namespace="/robot_0")
    with NodeProcess.start_module(ROBOT, args, log_path=tmp_path / "robot.log") as robot:
        robot.wait_for_output("ready", START_S)
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("param_setter", context=context)
        try:
            client = node.create_client(SetParameters, "/robot_0/em_robot/set_parameters")
            assert client.wait_for_service(timeout_sec=START_S)
            request = SetParameters.Request(parameters=[
                Parameter(name, value=-1.0).to_parameter_msg()
                for name in ("barrier_timeout_s", "request_period_s", "world.width_m")])
            future = client.call_async(request)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            executor.spin_until_future_complete(future, timeout_sec=START_S)
            results = future.result().results
        finally:
            node.destroy_node()
            rclpy.try_shutdown(context=context)
        assert [r.successful for r in results] == [False, False, False]
        assert all("read-only" in r.reason for r in results), [r.reason for r in results]


def test_a_robot_whose_world_leaves_says_so_and_exits(tmp_path):
    world = NodeProcess.start_module(WORLD, ros_args(params=ONE_ROBOT),
                                     log_path=tmp_path / "world.log")
    robot = NodeProcess.start_module(
        ROBOT, ros_args(params=dict(ONE_ROBOT, robot_id=0, world_lost_timeout_s=3.0),
                        namespace="/robot_0"), log_path=tmp_path / "robot.log")
    with world, robot:
        world.wait_for_output("stepping", START_S)  # the robot is connected
        # ... and has heard the world (its latched anchor): a robot that never saw a world
        # only waits for one, so a world gone before its first message reached the robot
        # made this test fail now and then
        robot.wait_for_output("map anchored", START_S)
        world.signal_group(signal.SIGINT)  # a clean exit leaves the graph at once
        assert world.wait(START_S) == 0
        # the graph forgets the world's endpoints a moment later; slower on a loaded machine
        robot.wait_for_output("the world left the ROS graph", 2 * START_S)
        assert robot.wait(START_S) == 4
    assert "the world has been gone for 3 s; exiting (code 4)" in robot.output()


def test_a_robot_never_seen_alive_is_reported_lost(tmp_path):
    """Robot 1 of 2 never starts: the world starts with robot 0 alone after
    startup_timeout_s (it once treated robot 0 as missing too, since robot 1 did not listen
    to its team updates, and stepped over at once); the evaluator, which never saw robot 1's
    liveliness, reports it lost after the grace, and the run ends at its time limit."""
    team = dict(ONE_ROBOT, **{"world.num_robots": 2})
    summary_path = tmp_path / "summary.json"
    world = NodeProcess.start_module(WORLD, ros_args(params=dict(
        team, startup_timeout_s=3.0, wait_for_evaluator=True, max_sim_time_s=30.0)),
        log_path=tmp_path / "world.log")
    evaluator = NodeProcess.start_module(EVALUATOR, ros_args(params=dict(
        team, summary_path=str(summary_path), max_sim_time_s=30.0, use_sim_time=True)),
        log_path=tmp_path / "evaluator.log")
    robot = NodeProcess.start_module(ROBOT, ros_args(params=dict(team, robot_id=0),
                                                     namespace="/robot_0"),
                                     log_path=tmp_path / "robot.log")
    with world, evaluator, robot:
        assert evaluator.wait(4 * START_S) == 0, evaluator.output()[-3000:]
    # the line run_team.sh --respawn restarts a robot on (a process wedged at its start)
    assert "robot 1 lost: not connected after 3 s (treated as stopped)" in world.output()
    log = evaluator.output()
    assert "robot 1 lost: no liveliness for 4 s (never seen alive)" in log, log
    assert "robot 0 lost" not in log, log
    summary = json.loads(summary_path.read_text())
    assert summary["stop_reason"].startswith("final step 150"), summary["stop_reason"]
    robot_0, robot_1 = summary["robots"]
    assert [change["status"] for change in robot_1["status_changes"]] == ["lost"]
    assert robot_1["downtime_wall_s"] > 0.0 and robot_1["distance_m"] == 0.0
    assert robot_0["status_changes"] == [] and robot_0["distance_m"] > 1.0


def test_a_robot_the_world_went_on_without_resumes_at_the_worlds_step(tmp_path):
    """Robot 1 is stopped (SIGSTOP: wedged, or starved of CPU) 500 steps into the run until
    the world gives it up and runs on with robot 0 for hundreds of steps; its sensor topics
    keep only the last 50 messages, so the data of the steps it missed is gone. Continued,
    it used to wait for the next of those steps for good (or drop the newest as too far
    ahead); it now resumes at the world's step, which takes it back into the lockstep."""
    team = {"world.num_robots": 2, "world.width_m": 100.0, "world.height_m": 100.0,
            "world.num_landmarks": 4, "planner.name": "NEAREST"}
    world = NodeProcess.start_module(WORLD, ros_args(params=dict(
        team, robot_timeout_s=3.0, liveliness_grace_s=1.0, max_sim_time_s=600.0)),
        log_path=tmp_path / "world.log")
    robots = [NodeProcess.start_module(ROBOT, ros_args(params=dict(team, robot_id=robot),
                                                       namespace=f"/robot_{robot}"),
                                       log_path=tmp_path / f"robot_{robot}.log")
              for robot in range(2)]
    with world, robots[0], robots[1]:
        world.wait_for_output("robot 1: liveliness asserted", START_S)
        # Robot 1 answered steps 0-499 (once, stopped before its first step, it was taken
        # for a restarted process when continued, and rejoined through that path instead).
        world.wait_for_output("step 500 (t = 100 s)", START_S)
        robots[1].signal_group(signal.SIGSTOP)
        assert "robot 1 lost" not in world.output()
        world.wait_for_output("robot 1 lost", START_S)
        world.wait_for_output("step 1000 (t = 200 s)", START_S)  # far past 50 steps on
        assert "robot 1 rejoined" not in world.output()
        robots[1].signal_group(signal.SIGCONT)
        world.wait_for_output("robot 1 rejoined at step", START_S)
        # Stopped in the middle of a step, it answers that step first; the world takes it
        # back and re-sends its open step (with its /clock) until the robot skips to it.
        robots[1].wait_for_output("the world went on without this robot: resuming at step",
                                  START_S)
    assert "more than 1000 steps ahead" not in robots[1].output()


def test_a_forged_world_status_does_not_end_a_paused_run(tmp_path):
    """While the world waits for a stopped robot, a second publisher on /world/status says
    that the world stepped over at the current step: the evaluator does not trust it (the
    world is not the status's sole publisher) and the run goes on."""
    # A map the team does not finish before robot 1 is stopped (on 30 m x 30 m it once
    # finished 1.7 s into the run, before the evaluator had seen robot 0's liveliness).
    team = dict(ONE_ROBOT, **{"world.num_robots": 2, "world.width_m": 100.0,
                              "world.height_m": 100.0})
    world = NodeProcess.start_module(WORLD, ros_args(params=dict(
        team, wait_for_evaluator=True, robot_timeout_s=120.0, liveliness_grace_s=120.0)),
        log_path=tmp_path / "world.log")
    evaluator = NodeProcess.start_module(EVALUATOR, ros_args(params=dict(
        team, summary_path=str(tmp_path / "summary.json"), use_sim_time=True)),
        log_path=tmp_path / "evaluator.log")
    robots = [NodeProcess.start_module(ROBOT, ros_args(params=dict(team, robot_id=robot),
                                                       namespace=f"/robot_{robot}"),
                                       log_path=tmp_path / f"robot_{robot}.log")
              for robot in range(2)]
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("forger", context=context)
    try:
        with world, evaluator, robots[0], robots[1]:
            for robot in range(2):
                evaluator.wait_for_output(f"robot {robot}: liveliness asserted", START_S)
            robots[1].signal_group(signal.SIGSTOP)  # the world waits for it from now on
            truth = []
            node.create_subscription(Odometry, "/world/ground_truth/robot_0",
                                     truth.append, GROUND_TRUTH_QOS)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            deadline = time.monotonic() + START_S
            while True:  # until the world has published no new step for a second
                heard = len(truth)
                spin_for(executor, 1.0)
                if truth and len(truth) == heard:
                    break
                assert time.monotonic() < deadline, "the world did not wait for robot 1"
            assert "stepping over" not in world.output()  # it waits, it has not ended
            last = truth[-1]
            step = round(stamp_s(last) / 0.2)
            status = node.create_publisher(WorldStatus, "/world/status", LATCHED_QOS)
            status.publish(WorldStatus(header=Header(stamp=last.header.stamp, frame_id="world"),
                                       step=step, stepping_over=True, reason="forged"))
            evaluator.wait_for_output("not trusted", 4 * START_S)
            assert evaluator.running()
            robots[1].signal_group(signal.SIGCONT)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    log = evaluator.output()
    assert f"the world stepped over at step {step} (forged)" in log
    assert "done (the world stepped over" not in log, log


def test_a_negative_clock_ends_neither_the_recorder_nor_the_viewer_bridge(tmp_path):
    """em-record and em-foxglove follow /clock (use_sim_time) like the team's nodes: a
    /clock before 1970 (rclpy's own time source raises on it) is dropped with a warning,
    and both go on and stop cleanly; the recording keeps what was on the wire."""
    sim_time = ros_args({"use_sim_time": True})
    recorder = NodeProcess.start_module(
        "em_exploration_ros.tools.record", ["-o", str(tmp_path / "bag"), "--topics", "/clock",
                                            *sim_time], log_path=tmp_path / "record.log")
    bridge = NodeProcess.start_module("em_exploration_ros.tools.foxglove_bridge",
                                      ["--port", "0", *sim_time],
                                      log_path=tmp_path / "bridge.log")
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("hostile_clock", context=context)
    try:
        with recorder, bridge:
            clock = node.create_publisher(Clock, "/clock", 10)
            recorder.wait_for_output("recording /clock", START_S)
            bridge.wait_for_output("serving ws://", START_S)
            deadline = time.monotonic() + START_S
            while not all("clock is negative" in p.output() for p in (recorder, bridge)):
                assert time.monotonic() < deadline, "the negative clock was not dropped"
                clock.publish(Clock(clock=TimeMsg(sec=-5)))
                time.sleep(0.1)
            clock.publish(Clock(clock=TimeMsg(sec=7)))
            time.sleep(1.0)
            assert recorder.running() and bridge.running()
            assert recorder.stop() == 0 and bridge.stop() == 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    for process in (recorder, bridge):
        assert "Traceback" not in process.output(), process.output()
    assert (tmp_path / "bag" / "metadata.yaml").is_file()


def test_a_robot_never_seen_alive_is_not_waited_for_the_robot_timeout(tmp_path):
    """Robot 1 is a stand-in that listens to its sensors and has a command publisher, but
    never answers and offers no liveliness (like a robot that died before the middleware
    reported it): the world gives it up a lease plus liveliness_grace_s into the run, not
    after robot_timeout_s (60 s here; 30 s by default, one robot after another)."""
    team = dict(ONE_ROBOT, **{"world.num_robots": 2})
    # startup_timeout_s: long enough for the world to discover this process's participant
    # even when Fast DDS's first announcements are missed (it announces again after 1 s with
    # config/fastdds_profiles.xml, 3 s by default; at a 3 s timeout and 3 s announcements,
    # about one run in ten treated the stand-in as never started, and it was not given up as
    # a silent robot). The world starts as soon as both robots are connected.
    world = NodeProcess.start_module(WORLD, ros_args(params=dict(
        team, startup_timeout_s=10.0, robot_timeout_s=60.0, liveliness_grace_s=4.0)),
        log_path=tmp_path / "world.log")
    robot = NodeProcess.start_module(ROBOT, ros_args(params=dict(team, robot_id=0),
                                                     namespace="/robot_0"),
                                     log_path=tmp_path / "robot_0.log")
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("stand_in", context=context)
    try:
        node.create_subscription(SonarScan, "/robot_1/sonar", lambda _m: None, SENSOR_QOS)
        node.create_subscription(Odometry, "/robot_1/odom", lambda _m: None, SENSOR_QOS)
        node.create_publisher(MotionCommand, "/robot_1/motion_command", SENSOR_QOS)
        # Like a teammate, so that robot 0 counts as connected and the world starts at once.
        node.create_subscription(TeamUpdate, "/robot_0/team/updates", lambda _m: None,
                                 TEAM_QOS)
        with world, robot:
            world.wait_for_output("stepping (lockstep)", START_S)
            started = time.monotonic()
            world.wait_for_output("robot 1 lost: no answer to step 0 in time (liveliness lost)",
                                  START_S)
            given_up_after_s = time.monotonic() - started
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    output = world.output()
    assert "robot 1: no liveliness seen 3 s into the run; given 4 s to answer" in output
    assert "robot 0 lost" not in output, output
    assert given_up_after_s < 20.0  # about 3 + 4 s; robot_timeout_s would be 60 s


def bad_odometry(frame_id: str, child_frame_id: str) -> list[Odometry | bytes]:
    """Odometry a robot's dead reckoning or ground truth must never be taken from: another
    child frame, a NaN position, a stamp off the 0.2 s step grid, and truncated bytes."""
    def message(child: str = child_frame_id, x: float = 1.0, nanosec: int = 0) -> Odometry:
        odometry = Odometry()
        odometry.header.stamp.sec, odometry.header.stamp.nanosec = 1, nanosec
        odometry.header.frame_id, odometry.child_frame_id = frame_id, child
        odometry.pose.pose.position.x, odometry.pose.pose.orientation.w = x, 1.0
        return odometry
    return [message(child="robot_9/base_link"), message(x=float("nan")),
            message(nanosec=100_000_000), serialize_message(message())[:40]]


def test_odometry_the_fast_reader_does_not_take_is_checked_and_dropped_with_its_reason(tmp_path):
    """The robot's dead reckoning and the evaluator's ground truth are read in one struct
    when they are in the world's own form (nodes/odometry_cdr.py); anything else goes
    through the message checks and is dropped with their reasons."""
    robot = NodeProcess.start_module(ROBOT, ros_args(params=dict(ONE_ROBOT, robot_id=0),
                                                     namespace="/robot_0"),
                                     log_path=tmp_path / "robot.log")
    evaluator = NodeProcess.start_module(EVALUATOR, ros_args(params=dict(
        ONE_ROBOT, summary_path=str(tmp_path / "summary.json"), use_sim_time=True)),
        log_path=tmp_path / "evaluator.log")
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("odometry_forger", context=context)
    reasons = ("child_frame_id 'robot_9/base_link' is not 'robot_0/base_link'",
               "a number is not finite (nan)", "malformed Odometry")
    try:
        with robot, evaluator:
            odom = node.create_publisher(Odometry, "/robot_0/odom", SENSOR_QOS)
            truth = node.create_publisher(Odometry, "/world/ground_truth/robot_0",
                                          GROUND_TRUTH_QOS)
            deadline = time.monotonic() + START_S
            while odom.get_subscription_count() < 1 or truth.get_subscription_count() < 1:
                assert time.monotonic() < deadline, "the robot or the evaluator never listened"
                time.sleep(0.1)
            for _ in range(20):  # best-effort sensor QoS: send more than once
                for message in bad_odometry("robot_0/odom", "robot_0/base_link"):
                    odom.publish(message)
                for message in bad_odometry("world", "robot_0/base_link"):
                    truth.publish(message)
                time.sleep(0.1)
            for process, topic in ((robot, "/robot_0/odom"),
                                   (evaluator, "/world/ground_truth/robot_0")):
                for reason in reasons:
                    process.wait_for_output(f"dropped a message on {topic}: " + reason,
                                            START_S)
            robot.wait_for_output("dropped a message on /robot_0/odom: stamp 1.1", START_S)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def spin_for(executor: SingleThreadedExecutor, seconds: float) -> None:
    """Spin ``executor`` for ``seconds`` wall seconds."""
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        executor.spin_once(timeout_sec=left)


def stamp_s(message: Odometry) -> float:
    """The message's header stamp [s]."""
    return message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec


# A node that sends itself SIGINT from a callback, then keeps running Python code in that
# callback (building messages, as rclpy's conversion of a taken message does) for 0.5 s.
SELF_INTERRUPTING_NODE = textwrap.dedent("""
    import os, signal, sys, time
    from rclpy.node import Node
    from std_msgs.msg import String
    from em_exploration_ros.nodes.node_main import run_node

    class SelfInterrupting(Node):
        def __init__(self):
            super().__init__("self_interrupting")
            self.ticks = 0
            self.create_timer(0.05, self.tick)

        def tick(self):
            self.ticks += 1
            if self.ticks != 3:
                return
            os.kill(os.getpid(), signal.SIGINT)
            try:
                deadline = time.monotonic() + 0.5
                while time.monotonic() < deadline:
                    String(data="message")
            except KeyboardInterrupt:
                self.get_logger().error("KeyboardInterrupt inside a callback")
                raise
            self.get_logger().info("callback ended undisturbed")

    def wrap_up(node):
        node.get_logger().info(f"wrapped up after {node.ticks} ticks")
        return 0

    sys.exit(run_node(SelfInterrupting, "self_interrupting", wrap_up=wrap_up))
""")


def test_ctrl_c_shuts_ros_down_without_raising_inside_a_callback(tmp_path):
    code, output = NodeProcess.run_script(SELF_INTERRUPTING_NODE, tmp_path / "node.log",
                                          START_S)
    assert code == 0, output
    assert "KeyboardInterrupt" not in output and "Traceback" not in output, output
    assert "callback ended undisturbed" in output, output
    assert "wrapped up after" in output, output
    # The wrap-up's log line is not also offered to /rosout, whose publisher the signal's
    # shutdown invalidated (rcl then printed this error after it, at the end of every node
    # log; a line logged by a callback still running at the signal may still get it).
    after_wrap_up = output.split("wrapped up after", 1)[1]
    assert "Failed to publish log message to rosout" not in after_wrap_up, output


def test_a_robot_process_loads_neither_the_relay_nor_the_simulator_runner_nor_plotting():
    """A robot node imports what a robot runs: not the world's link relay, em-sim's team
    runner with its evaluation, or matplotlib (0.76 s of CPU at every (re)start, before)."""
    loaded = loaded_modules("em_exploration_ros.nodes.robot_node")
    assert not loaded & {"em_exploration_ros.nodes.team_relay",
                         "em_exploration_ros.core.sessions.team_runner",
                         "em_exploration_ros.core.evaluation.evaluator", "matplotlib"}


def test_the_evaluator_process_loads_plotting_only_when_it_draws_its_pictures():
    """The evaluator draws its pictures at the run's end; at start-up, which the world waits
    for, matplotlib was 0.4 s of its 1.2 s of imports."""
    loaded = loaded_modules("em_exploration_ros.nodes.evaluator_node")
    assert "em_exploration_ros.nodes.evaluator_outputs" in loaded
    assert not [name for name in loaded if name.split(".")[0] == "matplotlib"
                or name.endswith(("map_render", "run_timeline"))]


def test_nodes_drop_what_another_run_publishes_with_a_line_naming_it(tmp_path):
    """A world and a robot of run 7 are given run 42's command and scan (two missions on
    one domain, issue 40 point 1): each drops them with the throttled line naming both
    runs, and the robot's command of another run does not reach the world's barrier."""
    run = dict(ONE_ROBOT, run_id=7)
    world = NodeProcess.start_module(WORLD, ros_args(params=run),
                                     log_path=tmp_path / "world.log")
    robot = NodeProcess.start_module(ROBOT, ros_args(params=dict(run, robot_id=0),
                                                     namespace="/robot_0"),
                                     log_path=tmp_path / "robot.log")
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("other_run", context=context)
    line = "of run 42, not of this node's run 7 (another run on the domain)"
    try:
        with world, robot:
            commands = node.create_publisher(MotionCommand, "/robot_0/motion_command",
                                             SENSOR_QOS)
            scans = node.create_publisher(SonarScan, "/robot_0/sonar", SENSOR_QOS)
            header = Header(frame_id="robot_0/base_link")
            deadline = time.monotonic() + 2 * START_S
            while not (line in world.output() and line in robot.output()):
                assert time.monotonic() < deadline, (world.output(), robot.output())
                commands.publish(MotionCommand(header=header, run_id=42, step=462))
                scans.publish(SonarScan(header=header, run_id=42, step=3))
                time.sleep(0.2)
            assert world.running() and robot.running()
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert (f"dropped a message on /robot_0/motion_command: {line}" in world.output())
    assert f"dropped a message on /robot_0/sonar: {line}" in robot.output()
    assert "ignored a future command" not in world.output()
