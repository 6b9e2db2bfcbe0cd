"""Team metrics as in the paper, from ground truth and the robots' published estimates.

The evaluator sees what an outside observer of a run sees: the simulator's true poses
(stamped) and landmark positions, and each robot's estimate of its own keyframe
trajectory (stamped) and of the landmarks it knows. It never feeds anything back to a
robot. Metrics:

- localization RMSE [m]: position error of every robot's optimized keyframe trajectory
  (each robot's own estimate of itself), pooled over robots;
- landmark RMSE [m]: position error of every landmark each robot estimates, pooled;
- explored ratio: fraction of explored cells of the inter-robot virtual map built from
  all robots' estimated trajectories and landmarks;
- distance [m]: true path length travelled by all robots.

The map frame coincides with the world frame in simulation (robot 0 is anchored at its
launch pose), so no alignment is needed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from em_exploration_ros.core.evaluation.metrics import (landmark_rmse, localization_rmse,
                                                        nearest_landmark_rmse)
from em_exploration_ros.core.params import ExplorationParams, WorldParams
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid
from em_exploration_ros.core.world.world import World

#: Stamps are matched on this resolution [ns] (sim time is a multiple of the step).
_STAMP_RESOLUTION_NS = 1000


def stamp_key(stamp_s: float) -> int:
    """Integer key of a simulation time [s], robust to float round-off."""
    return int(round(stamp_s * 1e9 / _STAMP_RESOLUTION_NS))


def stamp_keys(stamps_s: ArrayLike) -> NDArray[np.int64]:
    """:func:`stamp_key` of many finite simulation times [s] (any shape) at once: the same
    arithmetic, rounding half to even as Python's ``round`` does."""
    return np.rint(np.asarray(stamps_s, dtype=float) * 1e9 / _STAMP_RESOLUTION_NS).astype(np.int64)


class _TruePoses:
    """One robot's true poses (world frame) by stamp key, stored as growing arrays so that a
    whole estimated trajectory is matched in one lookup; a stamp recorded again replaces
    its pose."""

    def __init__(self) -> None:
        self._row: dict[int, int] = {}
        self._keys = np.zeros(64, dtype=np.int64)
        self._poses = np.zeros((64, 3))
        self._sorted: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None

    def put(self, key: int, pose: np.ndarray) -> None:
        row = self._row.get(key)
        if row is None:
            row = len(self._row)
            if row == len(self._keys):
                self._keys = np.concatenate([self._keys, np.zeros_like(self._keys)])
                self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
            self._row[key] = row
            self._keys[row] = key
            self._sorted = None
        self._poses[row] = pose

    def _order(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Rows in key order and the keys in that order."""
        if self._sorted is None:
            keys = self._keys[:len(self._row)]
            order = np.argsort(keys, kind="stable")
            self._sorted = (order, keys[order])
        return self._sorted

    def match(self, keys: NDArray[np.int64]) -> tuple[NDArray[np.bool_], np.ndarray]:
        """Which of ``keys`` (K,) have a true pose, and those poses (in ``keys`` order)."""
        order, sorted_keys = self._order()
        if not len(sorted_keys):
            return np.zeros(len(keys), dtype=bool), np.zeros((0, 3))
        position = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
        found = sorted_keys[position] == keys
        return found, self._poses[order[position[found]]]

    def in_time_order(self) -> np.ndarray:
        """Every recorded pose (N, 3), by stamp."""
        return self._poses[self._order()[0]].copy()


def landmark_truth(world_params: WorldParams, landmark_ids: np.ndarray,
                   positions: np.ndarray, radius_m: float) -> World:
    """The part of a ``World`` an evaluator needs, from published true landmarks.

    ``landmark_ids`` (M,) and ``positions`` (M, 2) [m, world frame]; the start poses,
    which evaluation never uses, are left empty. For evaluators that receive the truth
    (e.g. /world/landmarks) instead of regenerating the world from the seed.
    """
    return World(width_m=world_params.width_m, height_m=world_params.height_m,
                 landmarks=np.asarray(positions, dtype=float).reshape(-1, 2),
                 landmark_ids=np.asarray(landmark_ids, dtype=np.int64).reshape(-1),
                 landmark_radius_m=float(radius_m), robot_radius_m=world_params.robot_radius_m,
                 start_poses=np.zeros((0, 3)))


@dataclass(frozen=True)
class TeamMetrics:
    """Metrics of the team at one simulation time ``stamp_s`` [s]: team and per-robot true
    distance [m], explored ratio, robot localization and landmark RMSE [m], and, when the
    watcher knows them, each robot's position uncertainty [m] (``pose_sigma_m``)."""

    stamp_s: float
    distance_m: float
    explored_ratio: float
    loc_rmse_m: float
    landmark_rmse_m: float
    robot_distances_m: tuple[float, ...] = ()
    robot_pose_sigma_m: tuple[float, ...] = ()


def pose_sigma_m(covariance: np.ndarray) -> float:
    """Position uncertainty [m] of a pose covariance (3, 3) (x, y [m], theta [rad]; body or
    map frame): the square root of the trace of its position block, as the paper's."""
    covariance = np.asarray(covariance, dtype=float)
    return float(np.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0)))


class TeamEvaluator:
    """Accumulates ground truth and computes ``TeamMetrics`` from robots' estimates."""

    def __init__(self, world: World, params: ExplorationParams) -> None:
        self.world = world
        self.params = params
        self._grid = OccupancyGrid(world.width_m, world.height_m, params.map,
                                   params.sensors.sonar_max_range_m)
        #: Landmark estimates carry world ids (else each is scored at the nearest landmark).
        self._named_landmarks = params.sensors.landmark_ids
        n = params.world.num_robots
        self._truth = [_TruePoses() for _ in range(n)]
        self._last_true_xy: list[np.ndarray | None] = [None] * n
        self._distance = np.zeros(n)

    @property
    def num_robots(self) -> int:
        """Robots of the run (``world.num_robots``; a world read from published landmarks
        has no start poses to count them by)."""
        return len(self._truth)

    @property
    def robot_distances_m(self) -> np.ndarray:
        """True distance travelled by each robot so far [m]."""
        return self._distance.copy()

    @property
    def grid(self) -> OccupancyGrid:
        """The team virtual map of the last ``evaluate`` (read it, do not change it)."""
        return self._grid

    def true_trajectory(self, robot_id: int) -> np.ndarray:
        """A robot's recorded true poses (K, 3) in time order (world frame)."""
        return self._truth[robot_id].in_time_order()

    def record_truth(self, robot_id: int, stamp_s: float, pose: np.ndarray) -> None:
        """Store a robot's true pose (world frame) at a simulation time [s]."""
        pose = np.asarray(pose, dtype=float)
        self._truth[robot_id].put(stamp_key(stamp_s), pose)
        previous = self._last_true_xy[robot_id]
        if previous is not None:
            self._distance[robot_id] += float(np.linalg.norm(pose[:2] - previous))
        self._last_true_xy[robot_id] = pose[:2].copy()

    def evaluate(self, stamp_s: float,
                 trajectories: dict[int, tuple[np.ndarray, np.ndarray]],
                 landmark_estimates: dict[int, dict[int, np.ndarray]],
                 latest_pose_covariances: dict[int, np.ndarray] | None = None) -> TeamMetrics:
        """Metrics from each robot's own trajectory estimate and landmark estimates.

        Args:
            stamp_s: simulation time of the evaluation [s].
            trajectories: ``{robot: (stamps_s (K,), poses (K, 3))}``, map frame.
            landmark_estimates: ``{robot: {landmark_id: position (2,)}}``, map frame.
            latest_pose_covariances: ``{robot: (3, 3)}`` marginal covariance of each robot's
                latest keyframe in its own estimate, when the watcher knows it; gives
                ``robot_pose_sigma_m`` (NaN for a robot left out; empty when None).
        """
        estimated, true = [np.zeros((0, 3))], [np.zeros((0, 3))]
        for robot, (stamps, poses) in trajectories.items():
            found, truth = self._truth[robot].match(stamp_keys(stamps).reshape(-1))
            estimated.append(np.asarray(poses, dtype=float).reshape(-1, 3)[found])
            true.append(truth)
        estimated_poses, true_poses = np.concatenate(estimated), np.concatenate(true)
        loc_rmse = (localization_rmse(estimated_poses, true_poses)
                    if len(estimated_poses) else math.nan)
        pooled_errors = []
        for estimates in landmark_estimates.values():
            value = (landmark_rmse(estimates, self.world) if self._named_landmarks
                     else nearest_landmark_rmse(list(estimates.values()), self.world))
            if math.isfinite(value):
                pooled_errors.append((value ** 2, len(estimates)))
        total = sum(count for _, count in pooled_errors)
        landmark_error = (math.sqrt(sum(sq * count for sq, count in pooled_errors) / total)
                          if total else math.nan)
        all_poses = [np.asarray(poses).reshape(-1, 3) for _, poses in trajectories.values()]
        all_landmarks = [np.asarray(list(est.values())).reshape(-1, 2)
                         for est in landmark_estimates.values()]
        self._grid.rebuild(np.concatenate(all_poses) if all_poses else np.zeros((0, 3)),
                           np.concatenate(all_landmarks) if all_landmarks else np.zeros((0, 2)))
        sigmas = () if latest_pose_covariances is None else tuple(
            pose_sigma_m(latest_pose_covariances[r]) if r in latest_pose_covariances
            else math.nan for r in range(self.num_robots))
        return TeamMetrics(stamp_s, float(self._distance.sum()), self._grid.explored_ratio(),
                           loc_rmse, landmark_error, tuple(float(d) for d in self._distance),
                           sigmas)
