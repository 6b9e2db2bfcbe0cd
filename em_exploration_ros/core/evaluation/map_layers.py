"""What a picture of a team's final map shows, as plain data (no drawing library).

The layers, in the mission rectangle ``[0, width] x [0, height]`` (the map frame, which is
the world frame in simulation), metres:

- the explored area of the team virtual map (explored cells);
- true landmarks (with their radius) and each robot's landmark estimates;
- each robot's true trajectory and estimated keyframe trajectory;
- the targets each robot chose, with their frontier type (exploration, revisiting,
  rendezvous);
- the team virtual map's uncertainty: one ellipse per observed cell, from every robot's
  estimated keyframes and their marginal covariances (``team_uncertainty``; the observer's
  are each keyframe's as the robot published it when that keyframe was its newest, see
  ``keyframe_covariances``), or each robot's own as it published it
  (``uncertainty_ellipses``, read from a recording), and each robot's last frontier
  candidates;
- requested rendezvous and whether the robots met;
- the targets each robot gave up.

:mod:`map_render` draws them; the simulation and the evaluator fill them in without
loading matplotlib.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator
from em_exploration_ros.core.evaluation.rendezvous_stats import RendezvousOutcome
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, TargetEntry
from em_exploration_ros.core.params import MapParams, SensorParams
from em_exploration_ros.core.virtual_map.cell_uncertainty import cell_covariances_from_poses
from em_exploration_ros.core.virtual_map.ellipses import UncertaintyEllipses, covariance_ellipses
from em_exploration_ros.core.virtual_map.occupancy import GridGeometry



@dataclass(frozen=True)
class TeamMapLayers:
    """What the picture shows (see the module docstring); robots are keyed by id.

    ``explored``: (rows, cols) boolean mask of the virtual map, row 0 at y = 0, cells of
    ``cell_size_m``; trajectories: (K, 3) poses (x [m], y [m], theta [rad]), true ones in
    time order from the robot's start; landmark positions: (M, 2) [m]; ``team_uncertainty``:
    the team virtual map's ellipses (None when the poses' covariances were not known).
    """

    width_m: float
    height_m: float
    cell_size_m: float
    explored: np.ndarray
    true_landmarks: np.ndarray
    landmark_radius_m: float
    true_paths: Mapping[int, np.ndarray] = field(default_factory=dict)
    estimated_paths: Mapping[int, np.ndarray] = field(default_factory=dict)
    estimated_landmarks: Mapping[int, np.ndarray] = field(default_factory=dict)
    targets: Mapping[int, Sequence[TargetEntry]] = field(default_factory=dict)
    uncertainty_ellipses: Mapping[int, UncertaintyEllipses] = field(default_factory=dict)
    frontiers: Mapping[int, Sequence[TargetEntry]] = field(default_factory=dict)
    rendezvous: Sequence[RendezvousOutcome] = ()
    given_up: Mapping[int, Sequence[GivenUpEntry]] = field(default_factory=dict)
    team_uncertainty: UncertaintyEllipses | None = None
    title: str = ""


def team_virtual_map(geometry: GridGeometry, poses: Mapping[int, np.ndarray],
                     covariances: Mapping[int, np.ndarray], sensors: SensorParams,
                     map_params: MapParams) -> UncertaintyEllipses:
    """The team virtual map's ellipses (one per observed cell) from each robot's estimated
    keyframe poses (K, 3) and their marginal covariances (K, 3, 3) (map frame), fused over
    all robots as one robot fuses its team's (``cell_covariances_from_poses``); a keyframe
    whose covariance is not finite (not known) is left out."""
    robots = sorted(set(poses) & set(covariances))
    stacked = np.concatenate([np.asarray(poses[r], dtype=float).reshape(-1, 3) for r in robots]
                             or [np.zeros((0, 3))])
    stacked_cov = np.concatenate([np.asarray(covariances[r], dtype=float).reshape(-1, 3, 3)
                                  for r in robots] or [np.zeros((0, 3, 3))])
    known = np.isfinite(stacked_cov).all(axis=(1, 2))
    stacked, stacked_cov = stacked[known], stacked_cov[known]
    cells, observed = cell_covariances_from_poses(geometry, stacked, stacked_cov, sensors,
                                                  map_params)
    centres = geometry.cell_centers().reshape(-1, 2)[observed.ravel()]
    return covariance_ellipses(centres, cells.reshape(-1, 2, 2)[observed.ravel()])


def fused_ellipses(ellipses: Mapping[int, UncertaintyEllipses]) -> UncertaintyEllipses:
    """One ellipse per cell centre out of several robots' virtual maps: the smallest (by
    area), i.e. what the best-informed robot knows of the cell."""
    shapes = [e for _, e in sorted(ellipses.items()) if e.count]
    if not shapes:
        return UncertaintyEllipses(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    centres = np.concatenate([e.centres for e in shapes])
    axes = np.concatenate([e.axes for e in shapes])
    angles = np.concatenate([e.angles for e in shapes])
    order = np.lexsort((np.prod(axes, axis=1), centres[:, 1], centres[:, 0]))
    key = np.round(centres[order], 6)
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(key[1:] != key[:-1], axis=1)
    keep = order[first]
    return UncertaintyEllipses(centres[keep], axes[keep], angles[keep])


def evaluation_layers(evaluator: TeamEvaluator, estimated_paths: Mapping[int, np.ndarray],
                      estimated_landmarks: Mapping[int, np.ndarray],
                      targets: Mapping[int, Sequence[TargetEntry]],
                      rendezvous: Sequence[RendezvousOutcome], title: str, *,
                      given_up: Mapping[int, Sequence[GivenUpEntry]] | None = None,
                      pose_covariances: Mapping[int, np.ndarray] | None = None
                      ) -> TeamMapLayers:
    """The map of a run watched by ``evaluator``: its world's truth (every robot's true path
    as recorded) and explored area, with the robots' estimated paths (K, 3) and landmarks
    (M, 2), chosen targets, requested rendezvous and, when given, the targets given up and
    the marginal covariances (K, 3, 3) (map frame) of the estimated paths' poses (NaN where
    not known), from which the team virtual map's uncertainty is drawn."""
    world = evaluator.world
    team_uncertainty = None
    if pose_covariances:
        params = evaluator.params
        team_uncertainty = team_virtual_map(evaluator.grid.geometry, estimated_paths,
                                            pose_covariances, params.sensors, params.map)
    return TeamMapLayers(
        width_m=world.width_m, height_m=world.height_m,
        cell_size_m=evaluator.grid.geometry.cell_size_m,
        explored=evaluator.grid.explored_mask(), true_landmarks=world.landmarks,
        landmark_radius_m=world.landmark_radius_m,
        true_paths={r: evaluator.true_trajectory(r) for r in range(evaluator.num_robots)},
        estimated_paths=dict(estimated_paths), estimated_landmarks=dict(estimated_landmarks),
        targets=dict(targets), rendezvous=tuple(rendezvous),
        given_up={r: list(g) for r, g in (given_up or {}).items()},
        team_uncertainty=team_uncertainty, title=title)
