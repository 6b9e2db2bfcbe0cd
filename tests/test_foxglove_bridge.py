"""em-foxglove: a WebSocket client sees a running world and robot through the bridge.

A world node and one robot (small map) run as separate processes with the bridge (port 0:
any free port). A client speaking the Foxglove WebSocket protocol (the ``websockets``
package) connects, collects the advertised channels, subscribes to /tf_static and /tf and
decodes what arrives with rclpy: the static world -> map transform (sent to the late client
from the bridge's store of latched messages) and the robot's live map -> odom -> base_link
chain. All processes are bounded in time and stopped.
"""
from __future__ import annotations

import json
import re
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

from rclpy.serialization import deserialize_message
from tf2_msgs.msg import TFMessage
from websockets.sync.client import connect

from em_exploration_ros.tools.foxglove_bridge import viewer_qos
from em_exploration_ros.bag_format.qos_yaml import QosProfile
from ros_process import REPO_ROOT, ProcessSet, loaded_modules, ros_args, wait_until

PARAMS = {"world.num_robots": 1, "world.width_m": 30.0, "world.height_m": 30.0,
          "world.num_landmarks": 3, "planner.name": "CE", "run.seed": 1}
STARTUP_S = 40.0
RECEIVE_S = 40.0
#: Channels a viewer of this team needs, all advertised by the bridge.
EXPECTED_TOPICS = {"/tf", "/tf_static", "/world/markers", "/mission/anchor_pose",
                   "/robot_0/virtual_map", "/robot_0/estimated_path", "/robot_0/markers"}
SUBPROTOCOL = "foxglove.sdk.v1"  # the subprotocol of the foxglove-sdk server
#: Binary frames of the protocol: a message on a subscribed channel (opcode, subscription
#: id, log time [ns], then the CDR bytes) and the server time (opcode, time [ns]).
MESSAGE, TIME = 1, 2
MESSAGE_DATA = struct.Struct("<BIQ")


def test_viewer_qos_never_holds_back_a_publisher() -> None:
    # Discovery reports a remote writer's history as unknown.
    latched = QosProfile(history="unknown", depth=0, durability="transient_local")
    stream = QosProfile(history="unknown", depth=0)
    assert viewer_qos((latched, latched)) == QosProfile(depth=100, durability="transient_local")
    assert viewer_qos((stream,)).reliability == "best_effort"
    assert viewer_qos((latched, stream)) == QosProfile(depth=100, reliability="best_effort")


def test_no_node_imports_the_bridge() -> None:
    loaded = loaded_modules("em_exploration_ros.nodes.world_node",
                            "em_exploration_ros.nodes.robot_node",
                            "em_exploration_ros.nodes.evaluator_node")
    assert not [name for name in loaded if name.startswith("foxglove")]


def _receive_until(socket, channels: dict[str, dict], done, timeout_s: float,
                   on_binary=None, state=None) -> None:
    """Read frames into ``channels`` (advertised, by topic) until ``done()`` or timeout."""
    deadline = time.monotonic() + timeout_s
    while not done():
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError(f"timed out; advertised so far: {sorted(channels)}; "
                               f"received: {state() if state else '-'}")
        try:
            frame = socket.recv(timeout=min(remaining, 1.0))
        except TimeoutError:
            continue
        if isinstance(frame, str):
            message = json.loads(frame)
            if message.get("op") == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        elif on_binary is not None:
            on_binary(frame)


def test_client_sees_the_team_live(tmp_path: Path) -> None:
    with ProcessSet() as processes:
        bridge = processes.start_module(
            "em_exploration_ros.tools.foxglove_bridge",
            ["--port", "0", *ros_args({"use_sim_time": True})], tmp_path / "bridge.log")
        # Real time (5x): in lockstep this one-robot mission is over in about a second,
        # before the client has subscribed to anything.
        world = processes.start_module(
            "em_exploration_ros.nodes.world_node",
            ros_args({**PARAMS, "clock_mode": "realtime", "realtime_factor": 5.0}),
            tmp_path / "world.log")
        processes.start_module(
            "em_exploration_ros.nodes.robot_node",
            ros_args({**PARAMS, "robot_id": 0, "use_sim_time": True}, "/robot_0"),
            tmp_path / "robot.log")
        bridge.wait_for_output("serving ws://", STARTUP_S)
        port = int(re.search(r"serving ws://127\.0\.0\.1:(\d+)", bridge.output()).group(1))
        world.wait_for_output("stepping", STARTUP_S)

        channels: dict[str, dict] = {}
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                     open_timeout=20) as socket:
            assert socket.subprotocol == SUBPROTOCOL
            _receive_until(socket, channels, lambda: EXPECTED_TOPICS <= set(channels),
                           STARTUP_S)
            for topic in EXPECTED_TOPICS:
                assert channels[topic]["encoding"] == "cdr"
                assert channels[topic]["schemaEncoding"] == "ros2msg"
            assert channels["/tf"]["schemaName"] == "tf2_msgs/msg/TFMessage"
            assert "geometry_msgs/TransformStamped[] transforms" in channels["/tf"]["schema"]

            subscriptions = {1: "/tf_static", 2: "/tf"}
            socket.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sid, "channelId": channels[topic]["id"]}
                for sid, topic in subscriptions.items()]}))
            edges: dict[str, set[tuple[str, str]]] = {"/tf_static": set(), "/tf": set()}
            server_times: list[int] = []

            def on_binary(frame: bytes) -> None:
                if frame[0] == TIME:
                    server_times.append(struct.unpack_from("<Q", frame, 1)[0])
                    return
                opcode, subscription, _log_time = MESSAGE_DATA.unpack_from(frame)
                if opcode == MESSAGE and subscription in subscriptions:
                    message = deserialize_message(frame[MESSAGE_DATA.size:], TFMessage)
                    edges[subscriptions[subscription]].update(
                        (t.header.frame_id, t.child_frame_id) for t in message.transforms)

            chain = {("map", "robot_0/odom"), ("robot_0/odom", "robot_0/base_link"),
                     ("world", "robot_0/base_link_truth")}
            _receive_until(socket, channels,
                           lambda: ("world", "map") in edges["/tf_static"]
                           and chain <= edges["/tf"] and server_times, RECEIVE_S, on_binary,
                           lambda: (edges, server_times[-1:]))
        assert server_times == sorted(server_times)  # the simulation clock, moving forward
        wait_until(lambda: "serving /tf [" in bridge.output(), 5.0, "the bridge's log")
        assert "Traceback" not in bridge.output()


def test_a_taken_port_is_refused_in_one_line(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "em_exploration_ros.tools.foxglove_bridge", "--port",
             str(port)], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert f"cannot serve on 127.0.0.1:{port}" in result.stderr
    assert "Traceback" not in result.stderr
