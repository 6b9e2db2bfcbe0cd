"""The ROS side of ``em-bag render``: the final team map of a recorded run, as a PNG, and
its animation (``--animate``: the map at up to ``MAX_FRAMES`` moments of the run).

One validating pass over the recording (``BagScanner``) keeps the last message of every
state topic and every message of the stream topics; only those are deserialized, with
``rclpy.serialization`` (no ROS graph, no ``rclpy.init``), and converted with
``nodes.conversions``. A type whose recorded schema is not the installed definition (a
recording made before a message changed, e.g. before TeamUpdate became compact) is
decoded with the schema the recording holds (mcap-ros2-support's dynamic decoder) and read
by field name. All positions are in the ``map`` frame, which is the ``world`` frame
in simulation, in metres.

What is read, per robot ``i`` (topics absent from the recording are simply left out):

- ``/robot_i/estimated_path`` (last): the robot's estimated keyframe trajectory;
- ``/robot_i/landmarks`` (last): its landmark estimates;
- ``/robot_i/virtual_map`` (last): its virtual map; a cell is explored when its occupancy
  lies outside [``MapParams.explored_free_below``, ``explored_occupied_above``] of the
  default parameters (the recording does not hold the run's parameters); the team's
  explored area is the union over robots;
- ``/robot_i/team/updates`` (all): the targets it chose, in decision order (resent updates
  are counted once), and the rendezvous events it sent, from which each requested
  rendezvous is judged met or not as of the last message (``rendezvous_outcomes``);
- ``/robot_i/markers`` (last): the virtual-map uncertainty ellipses as the robot drew them
  (namespace ``virtual_map_covariance``: 3-sigma flat cylinders, taken as they are, not
  recomputed) and the frontier candidates of its last decision by type
  (``frontiers_<type>`` sphere lists);
- ``/world/ground_truth/robot_i`` (all): its true trajectory;

and ``/world/landmarks`` (last) for the true landmarks and their radius, ``/world/markers``
(last) for the mission border. ``render_team_map`` draws the layers (the robots' ellipses
fused into one per cell, the smallest); the ellipses and frontiers are also returned apart
and summarized by ``describe``. Targets given up are not read (they travel in
``motion_command``).
"""
from __future__ import annotations

import bisect
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message
from visualization_msgs.msg import Marker

from em_exploration_ros.bag_format.bag_reader import BagError, BagScanner, ChannelInfo, SchemaInfo
from em_exploration_ros.bag_format.mcap_ros2_schema import same_layout
from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.map_render import drawable_layers, render_team_map
from em_exploration_ros.core.evaluation.rendezvous_stats import rendezvous_outcomes
from em_exploration_ros.core.evaluation.run_animation import render_animation
from em_exploration_ros.core.evaluation.summary import TARGET_TYPES, TargetEntry
from em_exploration_ros.core.params import MapParams
from em_exploration_ros.core.records.team_data import (FrontierType, InvalidTeamUpdate,
                                                       RendezvousEvent)
from em_exploration_ros.core.records.wire_model import nanoseconds_to_seconds
from em_exploration_ros.core.virtual_map.ellipses import UncertaintyEllipses
from em_exploration_ros.nodes.conversions import (landmark_positions_from_msg, odometry_pose,
                                                  path_from_msg, quaternion_to_yaw,
                                                  rendezvous_from_msg)
from em_exploration_ros.tools.bag_ros import MessageTypeError, message_type_support

#: Message type of each topic kind this module reads.
EXPECTED_TYPES = {
    "estimated_path": "nav_msgs/msg/Path",
    "landmarks": "em_exploration_msgs/msg/LandmarkArray",
    "virtual_map": "nav_msgs/msg/OccupancyGrid",
    "markers": "visualization_msgs/msg/MarkerArray",
    "team/updates": "em_exploration_msgs/msg/TeamUpdate",
    "ground_truth": "nav_msgs/msg/Odometry",
    "world_landmarks": "em_exploration_msgs/msg/LandmarkArray",
    "world_markers": "visualization_msgs/msg/MarkerArray",
}
_ROBOT_TOPIC = re.compile(r"^/robot_(\d+)/(estimated_path|landmarks|virtual_map|markers|"
                          r"team/updates)$")
_TRUTH_TOPIC = re.compile(r"^/world/ground_truth/robot_(\d+)$")
_WORLD_TOPICS = {"/world/landmarks": "world_landmarks", "/world/markers": "world_markers"}
#: Marker namespaces of nodes/visualization.py.
ELLIPSE_NAMESPACE = "virtual_map_covariance"
FRONTIER_NAMESPACES = {f"frontiers_{kind.name.lower()}": kind.name.lower()
                       for kind in FrontierType}
_WORLD_BORDER_NAMESPACE = "world"


@dataclass(frozen=True)
class RecordedTeamMap:
    """The final team map of a recording: the drawable layers plus what they cannot show.

    ``frontiers``: each robot's frontier candidates at its last decision (``type`` is one of
    ``TARGET_TYPES``); ``end_s``: log time [s] of the last message read (the recorder's
    clock: sim time when it ran with ``use_sim_time``); ``left_out``: recorded points left
    out of ``layers`` because they cannot be drawn (map_render.drawable_layers).
    """

    layers: TeamMapLayers
    ellipses: dict[int, UncertaintyEllipses] = field(default_factory=dict)
    frontiers: dict[int, list[TargetEntry]] = field(default_factory=dict)
    end_s: float = 0.0
    left_out: int = 0

    @property
    def robots(self) -> list[int]:
        """Ids of the robots with any recorded estimate."""
        layers = self.layers
        return sorted(set(layers.estimated_paths) | set(layers.estimated_landmarks)
                      | set(layers.targets) | set(self.ellipses) | set(self.frontiers))

    def describe(self) -> str:
        """A few lines for the user: what each robot's final state holds."""
        layers = self.layers
        lines = [f"{len(self.robots)} robots, {len(layers.true_landmarks)} true landmarks, "
                 f"{int(np.count_nonzero(layers.explored))} explored cells, "
                 f"last message at t = {self.end_s:.1f} s"]
        for robot in self.robots:
            path = layers.estimated_paths.get(robot, np.zeros((0, 3)))
            frontiers = self.frontiers.get(robot, [])
            counts = ", ".join(f"{kind} {sum(f.type == kind for f in frontiers)}"
                               for kind in TARGET_TYPES)
            ellipses = self.ellipses.get(robot)
            lines.append(
                f"robot {robot}: {len(path)} keyframes, "
                f"{len(layers.estimated_landmarks.get(robot, ()))} landmark estimates, "
                f"{len(layers.targets.get(robot, ()))} targets, "
                f"{0 if ellipses is None else ellipses.count} uncertainty ellipses, "
                f"last frontiers: {counts}")
        if self.left_out:
            lines.append(f"left out {self.left_out} points with non-finite or far-out "
                         "coordinates")
        return "\n".join(lines)


def _topic_kind(topic: str) -> tuple[int | None, str] | None:
    """(robot id or None, kind) of a topic this module reads, else None."""
    match = _ROBOT_TOPIC.match(topic)
    if match:
        return int(match.group(1)), match.group(2)
    match = _TRUTH_TOPIC.match(topic)
    if match:
        return int(match.group(1)), "ground_truth"
    kind = _WORLD_TOPICS.get(topic)
    return None if kind is None else (None, kind)


#: ``em-bag render --animate``: at most this many frames.
MAX_FRAMES = 60
#: Log time between the walk's snapshots at first [ns] (doubled whenever they are thinned).
FIRST_SNAPSHOT_INTERVAL_NS = 1_000_000_000

_Key = tuple[int | None, str]


@dataclass
class _Collected:
    """Raw CDR of the messages kept by the walk, keyed by (robot or None, kind): the last of
    each state topic, every message of each stream topic with its log time [ns], and, for an
    animation, snapshots of the last messages (log time [ns], ``last`` as it was then), at
    most ``max_snapshots`` evenly spread (thinned as ``run_animation.FrameRecorder`` does)."""

    last: dict[_Key, bytes] = field(default_factory=dict)
    streams: dict[_Key, list[bytes]] = field(default_factory=dict)
    stream_log_ns: dict[_Key, list[int]] = field(default_factory=dict)
    decoders: dict[str, Callable[[bytes], Any]] = field(default_factory=dict)
    last_log_ns: int = 0
    max_snapshots: int = 0
    snapshot_interval_ns: int = FIRST_SNAPSHOT_INTERVAL_NS
    snapshots: list[tuple[int, dict[_Key, bytes]]] = field(default_factory=list)
    decoded: dict[_Key, list[Any]] = field(default_factory=dict)

    def snapshot(self) -> None:
        """Keep the state as of now when the interval since the last snapshot has passed."""
        if self.snapshots and self.last_log_ns < self.snapshots[-1][0] + self.snapshot_interval_ns:
            return
        self.snapshots.append((self.last_log_ns, dict(self.last)))
        if len(self.snapshots) > self.max_snapshots:
            self.snapshots = self.snapshots[::2]
            self.snapshot_interval_ns *= 2


def _register_decoder(path: Path, channel: ChannelInfo, schema: SchemaInfo, kind: str,
                      decoders: dict[str, Callable[[bytes], Any]]) -> None:
    """Check a read topic's recorded type and file its decoder in ``decoders``: the installed
    message class when the recording's schema is the installed definition, else the
    recorded schema itself."""
    expected = EXPECTED_TYPES[kind]
    if schema.name != expected:
        raise BagError(f"{path}: topic {channel.topic} has type {schema.name}, expected {expected}")
    if expected in decoders:
        return
    recorded = schema.data.decode("utf-8", errors="replace")
    try:
        message_class, definition = message_type_support(expected)
    except MessageTypeError:
        message_class, definition = None, None
    if definition is not None and same_layout(recorded, schema.encoding, definition):
        decoders[expected] = lambda data: deserialize_message(data, message_class)
        return
    try:
        decoder = DecoderFactory().decoder_for("cdr", Schema(
            id=schema.id, name=schema.name, encoding=schema.encoding, data=schema.data))
    except Exception as error:  # the recorded schema text does not parse
        raise BagError(f"{path}: the recorded schema of {expected} cannot be used: "
                       f"{str(error).splitlines()[0] if str(error) else type(error).__name__}"
                       ) from None
    if decoder is None:
        raise BagError(f"{path}: {expected} is recorded with schema encoding "
                       f"{schema.encoding!r}, which cannot be decoded without the installed type")
    decoders[expected] = decoder


def _collect(path: Path, snapshots: int = 0) -> _Collected:
    """Walk the recording once (validating it) and keep the messages this module reads, and
    up to ``snapshots`` snapshots of the state topics."""
    scanner = BagScanner(path)
    collected = _Collected(max_snapshots=snapshots)
    kinds: dict[int, tuple[int | None, str] | None] = {}
    for channel, message in scanner.messages():
        if channel.id not in kinds:
            kinds[channel.id] = _topic_kind(channel.topic)
            if kinds[channel.id] is not None:
                _register_decoder(path, channel, scanner.info.schema_of(channel),
                                  kinds[channel.id][1], collected.decoders)
        key = kinds[channel.id]
        if key is None:
            continue
        collected.last_log_ns = max(collected.last_log_ns, message.log_time_ns)
        if key[1] in ("team/updates", "ground_truth"):
            collected.streams.setdefault(key, []).append(message.data)
            collected.stream_log_ns.setdefault(key, []).append(collected.last_log_ns)
        else:
            collected.last[key] = message.data
        if snapshots and key[0] is not None:
            collected.snapshot()
    return collected


def _stream(path: Path, collected: _Collected, key: _Key, until_ns: int) -> list[Any]:
    """The messages of a stream topic logged by ``until_ns``, decoded (once per walk)."""
    if key not in collected.decoded:
        collected.decoded[key] = [_decode(path, data, key[1], collected)
                                  for data in collected.streams.get(key, ())]
    count = bisect.bisect_right(collected.stream_log_ns.get(key, []), until_ns)
    return collected.decoded[key][:count]


def _decode(path: Path, data: bytes, kind: str, collected: _Collected) -> Any:
    try:
        return collected.decoders[EXPECTED_TYPES[kind]](data)
    except Exception as error:  # rclpy: RuntimeError; the dynamic decoder: any parse error
        raise BagError(f"{path}: a {EXPECTED_TYPES[kind]} message does not deserialize: "
                       f"{str(error).splitlines()[0]}") from None


def _explored(grid: Any, map_params: MapParams) -> np.ndarray:
    """Explored cells (rows, cols) of an OccupancyGrid message (see the module docstring)."""
    percent = np.asarray(grid.data, dtype=np.int16).reshape(grid.info.height, grid.info.width)
    known = percent >= 0
    return known & ((percent < 100.0 * map_params.explored_free_below)
                    | (percent > 100.0 * map_params.explored_occupied_above))


def _marker_arrays(markers: list[Marker]) -> tuple[UncertaintyEllipses, list[TargetEntry]]:
    """The ellipses and frontier candidates of one robot's MarkerArray."""
    cylinders = [m for m in markers if m.ns == ELLIPSE_NAMESPACE and m.action == Marker.ADD]
    centres = np.array([[m.pose.position.x, m.pose.position.y] for m in cylinders])
    axes = np.array([[m.scale.x, m.scale.y] for m in cylinders])
    angles = np.array([quaternion_to_yaw(m.pose.orientation) for m in cylinders])
    ellipses = UncertaintyEllipses(centres.reshape(-1, 2), axes.reshape(-1, 2),
                                   angles.reshape(-1))
    frontiers = [TargetEntry(float(p.x), float(p.y), FRONTIER_NAMESPACES[m.ns])
                 for m in markers if m.ns in FRONTIER_NAMESPACES and m.action == Marker.ADD
                 for p in m.points]
    return ellipses, frontiers


def _targets(path: Path, updates: list[Any]) -> list[TargetEntry]:
    """A robot's chosen targets in decision order, from its decoded team updates; a resent
    update counts once. Reads the fields every TargetRecord schema has had (decision_index,
    x, y, frontier_type)."""
    by_decision = {}
    for update in updates:
        for record in update.targets:
            try:
                kind = FrontierType(record.frontier_type)
            except ValueError:
                raise BagError(f"{path}: a target has the unknown frontier type "
                               f"{record.frontier_type}") from None
            by_decision[int(record.decision_index)] = TargetEntry(
                float(record.x), float(record.y), kind.name.lower())
    return [by_decision[index] for index in sorted(by_decision)]


def _rendezvous_events(path: Path, updates: list[Any]) -> list[RendezvousEvent]:
    """The rendezvous events of a robot's decoded team updates (a resent one repeats, which
    the judging allows)."""
    events = []
    for update in updates:
        for record in getattr(update, "rendezvous", ()):
            try:
                events.append(rendezvous_from_msg(record))
            except InvalidTeamUpdate as error:
                raise BagError(f"{path}: a team update holds {error}") from None
    return events


def _mission_size(world_markers: Any, grids: dict[int, Any],
                  points: list[np.ndarray]) -> tuple[float, float]:
    """Mission rectangle [m]: the world's border marker, else the virtual map's extent,
    else the extent of everything drawn."""
    if world_markers is not None:
        border = [m for m in world_markers.markers
                  if m.ns == _WORLD_BORDER_NAMESPACE and m.type == Marker.LINE_STRIP]
        if border and border[0].points:
            return (max(p.x for p in border[0].points), max(p.y for p in border[0].points))
    if grids:
        info = next(iter(grids.values())).info
        return info.width * info.resolution, info.height * info.resolution
    stacked = np.concatenate([p[:, :2] for p in points if len(p)] or [np.ones((1, 2))])
    return float(max(stacked[:, 0].max(), 1.0)), float(max(stacked[:, 1].max(), 1.0))


def read_team_map(path: str | Path, map_params: MapParams | None = None) -> RecordedTeamMap:
    """The final team map of the recording at ``path`` (see the module docstring).

    ``map_params`` gives the explored-cell thresholds (default: the paper's). Raises
    BagError if the file cannot be read (not MCAP, truncated, corrupt), a read topic has an
    unexpected type or does not deserialize, or the file holds no robot estimate topic.
    """
    path = Path(path)
    collected = _collect(path)
    return _team_map(path, collected, collected.last, collected.last_log_ns,
                     map_params or MapParams())


def read_team_frames(path: str | Path, max_frames: int = MAX_FRAMES,
                     map_params: MapParams | None = None) -> list[TeamMapLayers]:
    """The team map of the recording at ``path`` at up to ``max_frames`` moments evenly
    spread over its log time, the final map last (with its ellipses and frontiers; the
    other frames without, which would cost most of the decoding). Raises BagError as
    ``read_team_map``."""
    path = Path(path)
    map_params = map_params or MapParams()
    collected = _collect(path, max(max_frames - 1, 1))
    frames = [_team_map(path, collected, last, until_ns, map_params, markers=False).layers
              for until_ns, last in collected.snapshots if until_ns < collected.last_log_ns]
    return frames + [_team_map(path, collected, collected.last, collected.last_log_ns,
                               map_params).layers]


def _team_map(path: Path, collected: _Collected, last_messages: dict[_Key, bytes],
              until_ns: int, map_params: MapParams, markers: bool = True) -> RecordedTeamMap:
    """The team map as of log time ``until_ns`` [ns]: ``last_messages`` of the state
    topics, the streams' messages logged by then; the robots' markers read if ``markers``."""
    robots = sorted({robot for (robot, kind) in [*last_messages, *collected.streams]
                     if robot is not None and kind != "ground_truth"})
    if not robots:
        raise BagError(f"{path}: no robot topics (/robot_<i>/estimated_path, landmarks, "
                       "virtual_map, markers or team/updates) with messages in the file")

    def last(robot: int | None, kind: str) -> Any:
        data = last_messages.get((robot, kind))
        return None if data is None else _decode(path, data, kind, collected)

    paths, landmarks, grids, ellipses, frontiers, targets = {}, {}, {}, {}, {}, {}
    events: list[RendezvousEvent] = []
    for robot in robots:
        if (message := last(robot, "estimated_path")) is not None:
            paths[robot] = path_from_msg(message)[1]
        if (message := last(robot, "landmarks")) is not None:
            positions = landmark_positions_from_msg(message)
            landmarks[robot] = np.array([positions[k] for k in sorted(positions)]).reshape(-1, 2)
        if (message := last(robot, "virtual_map")) is not None:
            grids[robot] = message
        if markers and (message := last(robot, "markers")) is not None:
            ellipses[robot], frontiers[robot] = _marker_arrays(list(message.markers))
        if (robot, "team/updates") in collected.streams:
            updates = _stream(path, collected, (robot, "team/updates"), until_ns)
            targets[robot] = _targets(path, updates)
            events += _rendezvous_events(path, updates)
    true_paths = {robot: np.array([odometry_pose(message) for message in
                                   _stream(path, collected, (robot, kind), until_ns)]
                                  ).reshape(-1, 3)
                  for (robot, kind) in collected.streams if kind == "ground_truth"}
    world_landmarks = last(None, "world_landmarks")
    true_landmarks = np.zeros((0, 2)) if world_landmarks is None else np.array(
        [[lm.x, lm.y] for lm in world_landmarks.landmarks]).reshape(-1, 2)
    radius = 0.0 if world_landmarks is None else float(world_landmarks.radius)

    shapes = {(g.info.height, g.info.width, g.info.resolution) for g in grids.values()}
    if len(shapes) > 1:
        raise BagError(f"{path}: the robots' virtual maps differ in size: {sorted(shapes)}")
    if grids:
        explored = np.logical_or.reduce([_explored(g, map_params) for g in grids.values()])
        cell_size = float(next(iter(grids.values())).info.resolution)
    else:
        explored, cell_size = np.zeros((1, 1), dtype=bool), 1.0
    width, height = _mission_size(last(None, "world_markers"), grids,
                                  [*paths.values(), *true_paths.values(), true_landmarks])
    end_s = nanoseconds_to_seconds(until_ns)
    layers = TeamMapLayers(
        width_m=width, height_m=height, cell_size_m=cell_size, explored=explored,
        true_landmarks=true_landmarks, landmark_radius_m=radius, true_paths=true_paths,
        estimated_paths=paths, estimated_landmarks=landmarks, targets=targets,
        uncertainty_ellipses=ellipses, frontiers=frontiers,
        rendezvous=tuple(rendezvous_outcomes(events, np.nextafter(end_s, np.inf))),
        title=f"{path.name}: {len(robots)} robots, t = {end_s:.1f} s")
    try:
        layers, left_out = drawable_layers(layers)
    except ValueError as error:
        raise BagError(f"{path}: {error}") from None
    return RecordedTeamMap(layers, ellipses, frontiers, end_s, left_out)


def render_recording(path: str | Path, png: str | Path) -> RecordedTeamMap:
    """Read the final team map of the recording at ``path`` and draw it into ``png``."""
    team_map = read_team_map(path)
    render_team_map(team_map.layers, png)
    return team_map


def animate_recording(path: str | Path, animation: str | Path) -> int:
    """Draw the recording at ``path`` as an animation (``read_team_frames``) into
    ``animation`` (.gif, or .mp4 with ffmpeg); returns the number of frames."""
    frames = read_team_frames(path)
    render_animation(frames, animation)
    return len(frames)
