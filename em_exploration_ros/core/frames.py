"""The transforms of the system's REP-105 frame tree, as planar poses (no ROS).

The tree a viewer (RViz, Foxglove) assembles from /tf and /tf_static::

    world ──► map ──► robot_<i>/odom ──► robot_<i>/base_link      (estimate chain, robot i)
      └──► robot_<i>/base_link_truth                              (ground truth, world node)

- ``world -> map`` (static): where the team's SLAM frame lies in the simulator's frame. The
  mission gives robot 0's launch pose in the map frame (the anchor); the simulator knows the
  same pose in the world frame, so ``map`` in ``world`` is ``anchor_in_world ⊕ anchor_in_map⁻¹``
  (the identity in this simulation, where the anchor is the true start pose).
- ``map -> robot_<i>/odom``: robot i's SLAM correction of its dead reckoning,
  ``base_in_map ⊕ base_in_odom⁻¹`` for the same instant; it changes when the estimate does.
- ``robot_<i>/odom -> robot_<i>/base_link``: robot i's dead reckoning.
- ``world -> robot_<i>/base_link_truth``: robot i's true pose.

A pose is ``(x [m], y [m], theta [rad])`` of a child frame in its parent frame, so it is
also the transform that maps child coordinates into parent coordinates.
"""
from __future__ import annotations

from numpy.typing import ArrayLike

from em_exploration_ros.core.geometry import FloatArray, compose, inverse


def map_in_world(anchor_in_world: ArrayLike, anchor_in_map: ArrayLike) -> FloatArray:
    """Pose (3,) of the ``map`` frame in ``world``, from one pose known in both frames: the
    mission anchor (robot 0's launch pose) in ``world`` and in ``map``."""
    return compose(anchor_in_world, inverse(anchor_in_map))


def odom_in_map(base_in_map: ArrayLike, base_in_odom: ArrayLike) -> FloatArray:
    """Pose (3,) of a robot's ``odom`` frame in ``map``: its estimated pose in ``map`` and its
    dead-reckoning pose in ``odom``, both of the same instant."""
    return compose(base_in_map, inverse(base_in_odom))
