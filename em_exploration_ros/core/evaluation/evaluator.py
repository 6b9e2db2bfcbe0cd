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

from em_exploration_ros.core.evaluation.metrics import landmark_rmse, localization_rmse
from em_exploration_ros.core.virtual_map.occupancy import OccupancyGrid
from em_exploration_ros.core.params import ExplorationParams, WorldParams
from em_exploration_ros.core.sim.world import World

#: Stamps are matched on this resolution [ns] (sim time is a multiple of the step).
_STAMP_RESOLUTION_NS = 1000


def stamp_key(stamp_s: float) -> int:
    """Integer key of a simulation time [s], robust to float round-off."""
    return int(round(stamp_s * 1e9 / _STAMP_RESOLUTION_NS))


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
    distance [m], explored ratio, robot localization and landmark RMSE [m]."""

    stamp_s: float
    distance_m: float
    explored_ratio: float
    loc_rmse_m: float
    landmark_rmse_m: float
    robot_distances_m: tuple[float, ...] = ()


class TeamEvaluator:
    """Accumulates ground truth and computes ``TeamMetrics`` from robots' estimates."""

    def __init__(self, world: World, params: ExplorationParams) -> None:
        self.world = world
        self._grid = OccupancyGrid(world.width_m, world.height_m, params.map,
                                   params.sensors.sonar_max_range_m)
        n = params.world.num_robots
        self._truth: list[dict[int, np.ndarray]] = [{} for _ in range(n)]
        self._last_true_xy: list[np.ndarray | None] = [None] * n
        self._distance = np.zeros(n)

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
        truth = self._truth[robot_id]
        return np.array([truth[key] for key in sorted(truth)]).reshape(-1, 3)

    def record_truth(self, robot_id: int, stamp_s: float, pose: np.ndarray) -> None:
        """Store a robot's true pose (world frame) at a simulation time [s]."""
        pose = np.asarray(pose, dtype=float)
        self._truth[robot_id][stamp_key(stamp_s)] = pose
        previous = self._last_true_xy[robot_id]
        if previous is not None:
            self._distance[robot_id] += float(np.linalg.norm(pose[:2] - previous))
        self._last_true_xy[robot_id] = pose[:2].copy()

    def evaluate(self, stamp_s: float,
                 trajectories: dict[int, tuple[np.ndarray, np.ndarray]],
                 landmark_estimates: dict[int, dict[int, np.ndarray]]) -> TeamMetrics:
        """Metrics from each robot's own trajectory estimate and landmark estimates.

        Args:
            stamp_s: simulation time of the evaluation [s].
            trajectories: ``{robot: (stamps_s (K,), poses (K, 3))}``, map frame.
            landmark_estimates: ``{robot: {landmark_id: position (2,)}}``, map frame.
        """
        estimated, true = [], []
        for robot, (stamps, poses) in trajectories.items():
            truth = self._truth[robot]
            for stamp, pose in zip(np.asarray(stamps, dtype=float), np.asarray(poses)):
                key = stamp_key(float(stamp))
                if key in truth:
                    estimated.append(pose)
                    true.append(truth[key])
        loc_rmse = (localization_rmse(np.array(estimated), np.array(true))
                    if estimated else math.nan)
        pooled_errors = []
        for estimates in landmark_estimates.values():
            value = landmark_rmse(estimates, self.world)
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
        return TeamMetrics(stamp_s, float(self._distance.sum()), self._grid.explored_ratio(),
                           loc_rmse, landmark_error, tuple(float(d) for d in self._distance))
