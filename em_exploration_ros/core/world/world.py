"""Seeded simulated environment: point landmarks, start poses, kinematics and collisions.

Everything is in the ``world`` frame: the rectangle ``[0, width_m] x [0, height_m]``,
metres and radians, poses ``(x, y, theta)`` with theta in (-pi, pi].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.geometry import wrap_angle
from em_exploration_ros.core.params import MotionParams, SensorParams, WorldParams

FloatArray = NDArray[np.float64]

#: Whole layouts (start poses, or landmarks) tried before generation gives up.
_MAX_LAYOUT_ATTEMPTS = 100
#: Random candidates drawn at once for one start position or one landmark.
_CANDIDATES_PER_DRAW = 256

#: Index of each stream derived from a run seed by :func:`run_seed_sequences`.
WORLD_STREAM, SENSOR_STREAM = 0, 1


def derive_seed_sequence(parent: np.random.SeedSequence, *indices: int) -> np.random.SeedSequence:
    """The child of ``parent`` at ``indices``, independent of every other index path.

    Equivalent to ``parent.spawn`` but addressed by index and without changing
    ``parent``, so the same child can be rebuilt anywhere (world node, em-sim).
    """
    return np.random.SeedSequence(entropy=parent.entropy,
                                  spawn_key=tuple(parent.spawn_key) + tuple(indices),
                                  pool_size=parent.pool_size)


def run_seed_sequences(seed: int) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
    """Split one run seed into the world-layout sequence and the sensor-noise sequence."""
    root = np.random.SeedSequence(seed)
    return derive_seed_sequence(root, WORLD_STREAM), derive_seed_sequence(root, SENSOR_STREAM)


@dataclass(frozen=True, eq=False)
class World:
    """A generated environment (world frame, metres, radians); arrays are read-only.

    ``landmarks`` are the ``(M, 2)`` landmark centres, ``landmark_ids`` their ``(M,)``
    unique integer ids, ``start_poses`` the ``(N, 3)`` robots' start poses.
    """

    width_m: float
    height_m: float
    landmarks: FloatArray
    landmark_ids: NDArray[np.int64]
    landmark_radius_m: float
    robot_radius_m: float
    start_poses: FloatArray

    @property
    def num_robots(self) -> int:
        """Number of robots (rows of ``start_poses``)."""
        return int(self.start_poses.shape[0])

    @property
    def num_landmarks(self) -> int:
        """Number of landmarks."""
        return int(self.landmarks.shape[0])


def _read_only(array: ArrayLike, dtype: type) -> NDArray:
    """A read-only copy of ``array``."""
    out = np.array(array, dtype=dtype)
    out.setflags(write=False)
    return out


def _pick_candidate(rng: np.random.Generator, low: FloatArray, high: FloatArray,
                    placed: FloatArray, min_dist: float, max_dist: float, near_count: int,
                    keep_out: FloatArray, keep_out_dist: float) -> FloatArray | None:
    """First of a batch of uniform candidates in the box ``[low, high]`` that lies at least
    ``min_dist`` from every ``placed`` point, at most ``max_dist`` from the last
    ``near_count`` of them and at least ``keep_out_dist`` from every ``keep_out`` point;
    None if no candidate of the batch qualifies.

    Once more points are placed than ``near_count`` (a team past its first group), the
    candidates are drawn in the part of the box within ``max_dist`` (per axis) of the last
    point, where every admissible candidate lies; before, in the whole box (which keeps
    the layouts of teams up to one group as they always were)."""
    if 0 < near_count < len(placed):
        low = np.maximum(low, placed[-1] - max_dist)
        high = np.minimum(high, placed[-1] + max_dist)
    candidates = rng.uniform(low, high, size=(_CANDIDATES_PER_DRAW, 2))
    ok = np.ones(_CANDIDATES_PER_DRAW, dtype=bool)
    if placed.size:
        dist = np.linalg.norm(candidates[:, None, :] - placed[None, :, :], axis=-1)
        ok &= np.all(dist >= min_dist, axis=1)
        ok &= np.all(dist[:, len(placed) - min(near_count, len(placed)):] <= max_dist, axis=1)
    if keep_out.size:
        dist = np.linalg.norm(candidates[:, None, :] - keep_out[None, :, :], axis=-1)
        ok &= np.all(dist >= keep_out_dist, axis=1)
    index = np.flatnonzero(ok)
    return candidates[index[0]] if index.size else None


def _place_points(rng: np.random.Generator, count: int, low: FloatArray, high: FloatArray,
                  min_dist: float, max_dist: float, near_count: int, keep_out: FloatArray,
                  keep_out_dist: float) -> FloatArray | None:
    """``count`` points placed one after the other by :func:`_pick_candidate`, restarting
    the whole layout when one point cannot be placed; None after the attempt budget."""
    for _ in range(_MAX_LAYOUT_ATTEMPTS):
        placed = np.empty((0, 2))
        for _ in range(count):
            point = _pick_candidate(rng, low, high, placed, min_dist, max_dist, near_count,
                                    keep_out, keep_out_dist)
            if point is None:
                break
            placed = np.vstack([placed, point])
        else:
            return placed
    return None


def _packing_bound(low: FloatArray, high: FloatArray, separation: float) -> float:
    """Upper bound on how many points ``separation`` apart fit in the box ``[low, high]``
    (Oler's inequality for a convex region: 2/sqrt(3) A/d^2 + P/(2d) + 1)."""
    if separation <= 0.0:
        return np.inf
    sides = high - low
    area, perimeter = float(np.prod(sides)), 2.0 * float(np.sum(sides))
    return 2.0 / np.sqrt(3.0) * area / separation ** 2 + perimeter / (2.0 * separation) + 1.0


def start_region(world_params: WorldParams) -> tuple[FloatArray, FloatArray]:
    """Corners ``low``, ``high`` (2,) [m] of the start region of the team: the
    ``start_region_*_fraction`` box for up to ``start_group_robots`` robots; for a larger
    team its sides grow by ``sqrt(num_robots / start_group_robots)`` (area in proportion to
    the team) about the same centre, clipped to the map."""
    wp = world_params
    size = np.array([wp.width_m, wp.height_m])
    low = size * np.array([wp.start_region_x_fraction[0], wp.start_region_y_fraction[0]])
    high = size * np.array([wp.start_region_x_fraction[1], wp.start_region_y_fraction[1]])
    if wp.num_robots <= wp.start_group_robots:
        return low, high
    centre, half = 0.5 * (low + high), 0.5 * (high - low)
    half = half * np.sqrt(wp.num_robots / wp.start_group_robots)
    return np.maximum(centre - half, 0.0), np.minimum(centre + half, size)


def _check_box(name: str, low: FloatArray, high: FloatArray) -> None:
    """Raise ValueError if the sampling box is empty."""
    if np.any(low > high):
        raise ValueError(f"{name} region is empty: low {low.tolist()} > high {high.tolist()}")


def generate_world(world_params: WorldParams, sensor_params: SensorParams,
                   seed_sequence: np.random.SeedSequence) -> World:
    """A random environment drawn from ``seed_sequence`` (same sequence, same world).

    Robots start in the middle-left start region (:func:`start_region`) with random
    headings, placed one after the other: every pair of start positions is at least
    ``start_min_separation_m`` apart, and each robot is at most ``start_max_separation_m``
    (and strictly less than the sonar range) from each of the ``start_group_robots - 1``
    robots placed before it, so it senses them: in a team of up to ``start_group_robots``
    every robot senses every other, in a larger one the readings chain every robot to
    robot 0 (whose launch pose anchors the map). Landmarks are uniform in the map shrunk by
    ``landmark_edge_margin_m``, at least ``landmark_min_separation_m`` apart and
    ``landmark_clearance_from_start_m`` from every start position; their ids are
    ``0..M-1``.

    Raises:
        ValueError: if the constraints cannot be met (checked up front where possible,
            otherwise after a bounded number of random layouts).
    """
    wp = world_params
    rng = np.random.default_rng(seed_sequence)
    size = np.array([wp.width_m, wp.height_m])
    start_low, start_high = start_region(wp)
    _check_box("start", start_low, start_high)
    if np.any(start_low < 0.0) or np.any(start_high > size):
        raise ValueError("start region must lie inside the map (fractions within [0, 1])")
    # Largest admissible separation: below the sonar range, so all robots see each other.
    max_separation = min(wp.start_max_separation_m,
                         float(np.nextafter(sensor_params.sonar_max_range_m, 0.0)))
    if wp.num_robots > 1 and wp.start_min_separation_m > max_separation:
        raise ValueError(
            f"start_min_separation_m={wp.start_min_separation_m} exceeds the admissible maximum "
            f"{max_separation} (start_max_separation_m, strictly below sonar_max_range_m="
            f"{sensor_params.sonar_max_range_m})")
    starts = _place_points(rng, wp.num_robots, start_low, start_high,
                           wp.start_min_separation_m, max_separation,
                           wp.start_group_robots - 1, np.empty((0, 2)), 0.0)
    if starts is None:
        raise ValueError(
            f"cannot place {wp.num_robots} robots in the start region {start_low.tolist()}-"
            f"{start_high.tolist()} m with pairwise separation in "
            f"[{wp.start_min_separation_m}, {max_separation}] m (the maximum to the "
            f"{wp.start_group_robots - 1} robots placed before) after "
            f"{_MAX_LAYOUT_ATTEMPTS} attempts")
    headings = wrap_angle(rng.uniform(-np.pi, np.pi, size=wp.num_robots))

    landmark_low = np.full(2, wp.landmark_edge_margin_m)
    landmark_high = size - wp.landmark_edge_margin_m
    _check_box("landmark", landmark_low, landmark_high)
    if wp.num_landmarks > _packing_bound(landmark_low, landmark_high,
                                         wp.landmark_min_separation_m):
        raise ValueError(
            f"{wp.num_landmarks} landmarks cannot be {wp.landmark_min_separation_m} m apart in "
            f"a {wp.width_m} x {wp.height_m} m map with edge margin {wp.landmark_edge_margin_m} m")
    landmarks = _place_points(rng, wp.num_landmarks, landmark_low, landmark_high,
                              wp.landmark_min_separation_m, np.inf, 0, starts,
                              wp.landmark_clearance_from_start_m)
    if landmarks is None:
        raise ValueError(
            f"cannot place {wp.num_landmarks} landmarks {wp.landmark_min_separation_m} m apart "
            f"in a {wp.width_m} x {wp.height_m} m map (edge margin {wp.landmark_edge_margin_m} m, "
            f"clearance {wp.landmark_clearance_from_start_m} m from the starts) after "
            f"{_MAX_LAYOUT_ATTEMPTS} attempts")
    return World(
        width_m=float(wp.width_m),
        height_m=float(wp.height_m),
        landmarks=_read_only(landmarks, float),
        landmark_ids=_read_only(np.arange(wp.num_landmarks), np.int64),
        landmark_radius_m=float(wp.landmark_radius_m),
        robot_radius_m=float(wp.robot_radius_m),
        start_poses=_read_only(np.column_stack([starts, headings]), float),
    )


def step_pose(pose: ArrayLike, turn_rad: ArrayLike, forward_m: ArrayLike,
              motion_params: MotionParams) -> FloatArray:
    """Pose ``(..., 3)`` after one action: turn, then move along the new heading.

    The turn is clipped to ``±max_turn_per_step_rad``; the forward distance [m] is clipped
    to ``[0, speed_mps * time_step_s]`` (constant speed, no reversing; 0 stops the robot).
    Broadcasts over leading dimensions; no collision check (see :func:`advance_robot`).
    """
    pose = np.asarray(pose, dtype=float)
    max_turn = motion_params.max_turn_per_step_rad
    turn = np.clip(np.asarray(turn_rad, dtype=float), -max_turn, max_turn)
    forward = np.clip(np.asarray(forward_m, dtype=float), 0.0,
                      motion_params.speed_mps * motion_params.time_step_s)
    heading = wrap_angle(pose[..., 2] + turn)
    return np.stack([pose[..., 0] + forward * np.cos(heading),
                     pose[..., 1] + forward * np.sin(heading),
                     heading], axis=-1)


def collides(world: World, xy: ArrayLike) -> NDArray[np.bool_]:
    """Whether robot centres ``(..., 2)`` [m] are outside the map or closer than
    ``robot_radius_m + landmark_radius_m`` to a landmark centre; shape ``(...)``."""
    xy = np.asarray(xy, dtype=float)
    outside = ((xy[..., 0] < 0.0) | (xy[..., 0] > world.width_m)
               | (xy[..., 1] < 0.0) | (xy[..., 1] > world.height_m))
    if world.num_landmarks == 0:
        return outside
    dist = np.linalg.norm(xy[..., None, :] - world.landmarks, axis=-1)
    return outside | np.any(dist < world.robot_radius_m + world.landmark_radius_m, axis=-1)


def advance_robot(world: World, pose: ArrayLike, turn_rad: float, forward_m: float,
                  motion_params: MotionParams) -> tuple[FloatArray, bool]:
    """True pose ``(3,)`` after one action and whether translation was blocked.

    Applies :func:`step_pose`; if the resulting position collides, the robot keeps its
    position and only turns (``blocked=True``).
    """
    pose = np.asarray(pose, dtype=float)
    moved = step_pose(pose, turn_rad, forward_m, motion_params)
    if bool(collides(world, moved[:2])):
        return np.array([pose[0], pose[1], moved[2]]), True
    return moved, False
