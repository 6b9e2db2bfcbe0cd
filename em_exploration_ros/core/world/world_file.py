"""World files: a site of one's own (map size, landmarks, start poses) as YAML, checked.

A world file (``em-sim --world FILE``, ``em-bench planners --world FILE``,
``run_team.sh --world FILE``, the ``world.file`` parameter of every node) replaces the
world a seed generates; ``em-sim --save-world FILE`` writes the one a seed generates
(``world_yaml``), so it can be edited and run again. Format (world frame, metres and radians)::

    width_m: 120.0           # the map is [0, width_m] x [0, height_m]
    height_m: 70.0
    landmarks:               # x [m], y [m], radius [m]; ids 0..M-1 in this order
      - [20.0, 15.0, 1.0]
    starts:                  # x [m], y [m], yaw [rad]; robot i starts at row i
      - [6.0, 6.0, 0.0]

The file is read as untrusted input (``core.untrusted_files``, ``core.untrusted_yaml``:
bounded size, no duplicate key, hostile aliases cost nothing) and refused with one line
naming the problem (``WorldFileError``) if it is malformed (a missing or unknown key, a
wrong type, NaN or inf, more than ``MAX_LANDMARKS`` landmarks) or inconsistent with the
run's parameters (``world_problem``): a landmark outside the map, landmarks of different
radii (the robots' local planner knows one radius, ``world.landmark_radius_m``), fewer
starts than robots, a start outside the map or in a landmark's collision disc, two starts
whose robot bodies overlap, or a robot that starts out of sonar range of every robot
listed before it (the world generator's rule: each robot senses a teammate at its start,
so the readings chain every robot to robot 0, whose launch pose anchors the map).

The world a file gives sets the parameters it determines (``params_for_world``): the map
size, the number of landmarks and their radius, and (unless given) the number of robots,
one per start. A run from a saved world is the seeded run it came from, given the same
seed (the seed still draws the sensor noise).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from em_exploration_ros.core.geometry import wrap_angle
from em_exploration_ros.core.params import ExplorationParams, WorldParams, closest_name_hint
from em_exploration_ros.core.untrusted_files import FileTooLarge, read_regular_file
from em_exploration_ros.core.untrusted_yaml import load_yaml, shown_value
from em_exploration_ros.core.world.world import (World, collides, generate_world,
                                                 run_seed_sequences)

#: Largest world file read [bytes]: 1000 landmarks take about 40 kB.
MAX_FILE_BYTES = 1 << 20
_WORLD_FIELDS = {f.name: f for f in dataclasses.fields(WorldParams)}
#: Most landmarks and start poses a file may list (``world.num_landmarks``, ``num_robots``).
MAX_LANDMARKS = int(_WORLD_FIELDS["num_landmarks"].metadata["high"])
MAX_STARTS = int(_WORLD_FIELDS["num_robots"].metadata["high"])
KEYS = ("width_m", "height_m", "landmarks", "starts")


class WorldFileError(ValueError):
    """A world file that cannot be read, is malformed, or does not fit the run."""


def read_world_file(path: str | Path) -> World:
    """The world of the file ``path`` with every start it lists, checked on its own (format,
    types, finite numbers, landmarks inside the map and of one radius); ``WorldFileError``
    naming the file and the problem otherwise. The robot radius is a placeholder (0) that
    ``world_for_params`` sets from the parameters."""
    what = f"world file {path}"
    try:
        data = read_regular_file(path, MAX_FILE_BYTES)
    except FileTooLarge as error:
        raise WorldFileError(f"{what} is too large ({error.size} bytes, at most "
                             f"{MAX_FILE_BYTES})") from None
    except (OSError, ValueError) as error:
        reason = error.strerror if isinstance(error, OSError) and error.strerror else error
        raise WorldFileError(f"{what}: cannot read it ({reason})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise WorldFileError(f"{what} is not UTF-8 text") from None
    return world_from_data(load_yaml(text, what, WorldFileError), what)


def world_from_data(data: Any, what: str = "world file") -> World:
    """The world of a parsed world file ``data`` (see the module docstring), checked on its
    own; ``WorldFileError`` starting with ``what`` otherwise."""
    if not isinstance(data, dict):
        raise WorldFileError(f"{what} must be a mapping with the keys {', '.join(KEYS)}, got "
                             f"{shown_value(data)}")
    for key in data:
        if key not in KEYS:
            hint = closest_name_hint(key, KEYS) if isinstance(key, str) else ""
            raise WorldFileError(f"{what}: unknown key {shown_value(key)}{hint}; known: "
                                 f"{', '.join(KEYS)}")
    missing = [key for key in KEYS if key not in data]
    if missing:
        raise WorldFileError(f"{what} lacks {', '.join(missing)}")
    size = [_number(data[key], f"{what}: {key}", _WORLD_FIELDS[key]) for key in KEYS[:2]]
    landmarks = _rows(data["landmarks"], f"{what}: landmarks", MAX_LANDMARKS, 0,
                      "x [m], y [m], radius [m]")
    starts = _rows(data["starts"], f"{what}: starts", MAX_STARTS, 1, "x [m], y [m], yaw [rad]")
    radius_field = _WORLD_FIELDS["landmark_radius_m"]
    for index, (x, y, radius) in enumerate(landmarks):
        if not (0.0 <= x <= size[0] and 0.0 <= y <= size[1]):
            raise WorldFileError(f"{what}: landmark {index} at ({x:g}, {y:g}) m is outside "
                                 f"the {size[0]:g} x {size[1]:g} m map")
        _number(radius, f"{what}: landmark {index}'s radius", radius_field)
        if radius != landmarks[0][2]:
            raise WorldFileError(
                f"{what}: landmark {index}'s radius {radius:g} m differs from landmark 0's "
                f"{landmarks[0][2]:g} m (one radius for all: the robots' local planner knows "
                "one, world.landmark_radius_m)")
    poses = np.array(starts, dtype=float).reshape(-1, 3)
    outside = (poses[:, 2] <= -math.pi) | (poses[:, 2] > math.pi)
    poses[outside, 2] = wrap_angle(poses[outside, 2])
    radius = landmarks[0][2] if landmarks else float(radius_field.default)
    return _world(size[0], size[1], np.array(landmarks, dtype=float).reshape(-1, 3)[:, :2],
                  radius, 0.0, poses)


def _world(width_m: float, height_m: float, landmarks: np.ndarray, landmark_radius_m: float,
           robot_radius_m: float, start_poses: np.ndarray) -> World:
    """A ``World`` of read-only copies (landmark ids ``0..M-1``)."""
    arrays = {"landmarks": np.array(landmarks, dtype=float),
              "landmark_ids": np.arange(len(landmarks), dtype=np.int64),
              "start_poses": np.array(start_poses, dtype=float)}
    for array in arrays.values():
        array.setflags(write=False)
    return World(width_m=float(width_m), height_m=float(height_m),
                 landmark_radius_m=float(landmark_radius_m), robot_radius_m=float(robot_radius_m),
                 **arrays)


def _number(value: Any, what: str, f: dataclasses.Field | None = None) -> float:
    """``value`` as a finite float (in the range of the parameter field ``f``, if given)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        hint = ""
        if isinstance(value, str) and len(value) < 40:
            try:
                float(value)
                hint = " (YAML reads an exponent without a dot as text: write 1.0e-05)"
            except ValueError:
                pass
        raise WorldFileError(f"{what} must be a number, got {shown_value(value)}{hint}")
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise WorldFileError(f"{what} must be finite, got {shown_value(value)}")
    if f is not None:
        low, high = f.metadata["low"], f.metadata["high"]
        if not low <= number <= high:
            raise WorldFileError(f"{what} = {number:g} is outside [{low:g}, {high:g}]")
    return number


def _rows(value: Any, what: str, most: int, fewest: int, columns: str) -> list[list[float]]:
    """``value`` as a list of at least ``fewest`` and at most ``most`` rows of three finite
    numbers (``columns`` names them). The length is checked before any row is read, and
    each row's type before its items, so a hostile alias structure costs nothing."""
    if not isinstance(value, list):
        raise WorldFileError(f"{what} must be a list of [{columns}], got {shown_value(value)}")
    if not fewest <= len(value) <= most:
        raise WorldFileError(f"{what} lists {len(value)} entries; between {fewest} and {most} "
                             "are allowed")
    rows = []
    for index, row in enumerate(value):
        if not isinstance(row, list) or len(row) != 3:
            raise WorldFileError(f"{what}: entry {index} must be [{columns}], got "
                                 f"{shown_value(row)}")
        rows.append([_number(item, f"{what}: entry {index}") for item in row])
    return rows


def world_problem(world: World, params: ExplorationParams) -> str | None:
    """Why the run of ``params`` cannot start from ``world`` (its first
    ``params.world.num_robots`` starts), or None. See the module docstring."""
    wp, sonar_range = params.world, params.sensors.sonar_max_range_m
    if world.num_robots < wp.num_robots:
        return f"it lists {world.num_robots} starts for {wp.num_robots} robots"
    starts = world.start_poses[:wp.num_robots, :2]
    probe = dataclasses.replace(world, robot_radius_m=wp.robot_radius_m)
    for robot, xy in enumerate(starts):
        if bool(collides(probe, xy)):
            return (f"robot {robot} starts at ({xy[0]:g}, {xy[1]:g}) m, outside the map or "
                    f"closer than {wp.robot_radius_m:g} + {world.landmark_radius_m:g} m "
                    "(robot and landmark radii) to a landmark")
        if robot == 0:
            continue
        distance = np.linalg.norm(starts[:robot] - xy, axis=1)
        closest = int(np.argmin(distance))
        if distance[closest] < 2.0 * wp.robot_radius_m:
            return (f"robots {closest} and {robot} start {distance[closest]:g} m apart, closer "
                    f"than two robot radii ({2.0 * wp.robot_radius_m:g} m)")
        if distance[closest] >= sonar_range:
            return (f"robot {robot} starts {distance[closest]:g} m from robot {closest}, the "
                    f"nearest robot listed before it, not within the sonar range "
                    f"{sonar_range:g} m (each robot must sense one listed before it at the "
                    "start, so the readings chain it to robot 0)")
    return None


def params_for_world(params: ExplorationParams, world: World, path: str | Path,
                     num_robots: int | None = None) -> ExplorationParams:
    """``params`` for a run from the world file ``path`` holding ``world``: the map size,
    the number of landmarks and their radius from the file, ``num_robots`` robots (default:
    one per start) and ``world.file`` the file's absolute path; ``WorldFileError`` if the
    world does not fit them (``world_problem``) or ``ValueError`` for a parameter the
    checks of ``core.params`` refuse (a cell size too large for the map)."""
    changes: dict[str, Any] = {
        "width_m": world.width_m, "height_m": world.height_m,
        "num_landmarks": world.num_landmarks,
        "num_robots": world.num_robots if num_robots is None else num_robots,
        "file": str(Path(path).expanduser().absolute())}
    if world.num_landmarks:  # (a world without landmarks keeps the parameters' radius)
        changes["landmark_radius_m"] = world.landmark_radius_m
    resolved = params.replace(world=changes)
    problem = world_problem(world, resolved)
    if problem:
        raise WorldFileError(f"world file {path}: {problem}")
    return resolved


def world_for_params(params: ExplorationParams) -> World:
    """The world of a run: read from ``params.world.file`` when it is set (``WorldFileError``
    if it cannot be read or does not match ``params``: map size, landmarks and their radius
    as ``params_for_world`` set them, and every check of ``world_problem``), generated from
    ``params.run.seed`` otherwise (``ValueError`` if the constraints cannot be met)."""
    wp = params.world
    if not wp.file:
        return generate_world(wp, params.sensors, run_seed_sequences(params.run.seed)[0])
    world = read_world_file(wp.file)
    given = (world.width_m, world.height_m, world.num_landmarks)
    if world.num_landmarks == 0:
        world = dataclasses.replace(world, landmark_radius_m=wp.landmark_radius_m)
    expected = (wp.width_m, wp.height_m, wp.num_landmarks)
    if given != expected or world.landmark_radius_m != wp.landmark_radius_m:
        raise WorldFileError(
            f"world file {wp.file} holds a {given[0]:g} x {given[1]:g} m map with "
            f"{given[2]} landmarks of radius {world.landmark_radius_m:g} m, but the parameters "
            f"say {expected[0]:g} x {expected[1]:g} m, {expected[2]} of radius "
            f"{wp.landmark_radius_m:g} m (leave world.width_m, height_m, num_landmarks and "
            "landmark_radius_m to the file)")
    problem = world_problem(world, params)
    if problem:
        raise WorldFileError(f"world file {wp.file}: {problem}")
    return dataclasses.replace(world, robot_radius_m=float(wp.robot_radius_m),
                               start_poses=world.start_poses[:wp.num_robots])


def world_yaml(world: World, comment: str = "") -> str:
    """``world`` as the text of a world file (``comment`` lines first, as YAML comments);
    every number is written so that it reads back to the same float."""
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [f"width_m: {_float_text(world.width_m)}",
              f"height_m: {_float_text(world.height_m)}",
              "landmarks:  # x [m], y [m], radius [m]" + ("" if world.num_landmarks else " []")]
    lines += [f"  - [{_float_text(x)}, {_float_text(y)}, {_float_text(world.landmark_radius_m)}]"
              for x, y in world.landmarks]
    lines.append("starts:  # x [m], y [m], yaw [rad]; one per robot")
    lines += [f"  - [{', '.join(_float_text(v) for v in pose)}]" for pose in world.start_poses]
    return "\n".join(lines) + "\n"


def _float_text(value: float) -> str:
    """The shortest text of a finite float that YAML 1.1 reads back as that float (its
    float pattern needs a dot: ``1e-05`` would be a string, ``1.0e-05`` is the number)."""
    text = repr(float(value))
    if "e" in text and "." not in text:
        text = text.replace("e", ".0e")
    return text

