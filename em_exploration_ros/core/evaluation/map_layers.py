"""What a picture of a team's final map shows, as plain data (no drawing library).

The layers, in the mission rectangle ``[0, width] x [0, height]`` (the map frame, which is
the world frame in simulation), metres:

- the explored area of the team virtual map (explored cells);
- true landmarks (with their radius) and each robot's landmark estimates;
- each robot's true trajectory and estimated keyframe trajectory;
- the targets each robot chose, with their frontier type (exploration, revisiting,
  rendezvous);
- each robot's virtual-map uncertainty ellipses and its last frontier candidates;
- requested rendezvous and whether the robots met.

:mod:`map_render` draws them; the simulation and the evaluator fill them in without
loading matplotlib.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator
from em_exploration_ros.core.evaluation.rendezvous_stats import RendezvousOutcome
from em_exploration_ros.core.evaluation.summary import TargetEntry


@dataclass(frozen=True)
class UncertaintyEllipses:
    """Virtual-map cell uncertainty ellipses: ``centres`` (K, 2) [m]; ``axes`` (K, 2) full
    lengths (major, minor) [m] at a stated sigma scale; ``angles`` (K,) [rad] of the major
    axis from map x."""

    centres: np.ndarray
    axes: np.ndarray
    angles: np.ndarray

    @property
    def count(self) -> int:
        """Number of ellipses."""
        return len(self.centres)


@dataclass(frozen=True)
class TeamMapLayers:
    """What the picture shows (see the module docstring); robots are keyed by id.

    ``explored``: (rows, cols) boolean mask of the virtual map, row 0 at y = 0, cells of
    ``cell_size_m``; trajectories: (K, 3) poses (x [m], y [m], theta [rad]); landmark
    positions: (M, 2) [m].
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
    title: str = ""


def evaluation_layers(evaluator: TeamEvaluator, estimated_paths: Mapping[int, np.ndarray],
                      estimated_landmarks: Mapping[int, np.ndarray],
                      targets: Mapping[int, Sequence[TargetEntry]],
                      rendezvous: Sequence[RendezvousOutcome], title: str) -> TeamMapLayers:
    """The final map of a run watched by ``evaluator``: its world's truth and explored
    area, with the robots' estimated paths (K, 3) and landmarks (M, 2), chosen targets and
    requested rendezvous."""
    world = evaluator.world
    return TeamMapLayers(
        width_m=world.width_m, height_m=world.height_m,
        cell_size_m=evaluator.grid.geometry.cell_size_m,
        explored=evaluator.grid.explored_mask(), true_landmarks=world.landmarks,
        landmark_radius_m=world.landmark_radius_m,
        true_paths={r: evaluator.true_trajectory(r) for r in range(len(world.start_poses))},
        estimated_paths=dict(estimated_paths), estimated_landmarks=dict(estimated_landmarks),
        targets=dict(targets), rendezvous=tuple(rendezvous), title=title)
