"""Artificial potential field (APF) local planner and the goal-reached rule.

The robot moves ``speed_mps * time_step_s`` forward every step along its heading and can
only choose how much to turn (at most ``max_turn_per_step_rad``). The controller steers
toward the direction of a virtual force in the map frame (in the style of the improved APF
of Fan et al. 2020):

* attraction: a unit vector toward the target times ``apf_attractive_gain`` (conic
  potential, so the pull does not grow with distance);
* repulsion from every landmark whose *surface* distance
  ``rho = |p - l| - (landmark_radius + robot_radius + safety_margin)`` is below
  ``apf_influence_m``: ``k_rep (1/rho - 1/rho0) / rho^2`` away from the landmark, scaled by
  ``min(1, (d_goal / rho0)^2)`` so that a target next to a landmark stays reachable (the
  "goal non-reachable with obstacle nearby" fix);
* a tangential force of the same magnitude along the landmark's surface, on the side that
  leads toward the target (ties, e.g. a target straight behind the landmark, go to the side
  the robot already heads to, then to the left). It removes the local minimum where
  attraction and repulsion are collinear and keeps the robot circling the landmark on one
  side instead of oscillating.

A safety filter then checks the turn before it is issued: a candidate turn is safe when,
after it, the robot can still keep at least ``landmark_radius + robot_radius +
safety_margin`` (or, when already closer, its current distance) from every landmark by
continuing with a constant left, zero or right turn at the maximum rate for half a turn.
The safe candidate closest to the APF turn is issued; if none is safe, the candidate with
the largest such clearance. The APF alone can cut close to a landmark when the goal
scaling weakens repulsion near a target next to it; the filter keeps it out.

Poses are ``(x [m], y [m], theta [rad])`` in the map frame; landmark positions ``(M, 2)``.
"""
from __future__ import annotations

import numpy as np

from em_exploration_ros.core.geometry import wrap_angle
from em_exploration_ros.core.params import MotionParams
from em_exploration_ros.core.world.world import step_pose

#: Smallest surface distance used in the repulsion formula [m] (keeps it finite).
_MIN_RHO_M = 0.05
#: Weight of the current heading when choosing the side of the tangential force.
_HEADING_TIE_WEIGHT = 1e-3
#: Number of evenly spaced candidate turns checked by the safety filter (plus the APF turn).
_CANDIDATE_TURNS = 31


class ApfController:
    """APF steering toward a target among circular landmarks (see the module docstring)."""

    def __init__(self, motion_params: MotionParams, landmark_radius_m: float,
                 robot_radius_m: float) -> None:
        """Args: motion parameters, landmark and robot collision radii [m]."""
        self.params = motion_params
        self.keep_out_m = (float(landmark_radius_m) + float(robot_radius_m)
                           + motion_params.safety_margin_m)

    def force(self, pose: np.ndarray, target: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """Total virtual force (2,) in the map frame at ``pose`` (3,) toward ``target`` (2,) [m]
        among ``landmarks`` (M, 2) [m] (unitless, only its direction is used)."""
        pose = np.asarray(pose, dtype=float)
        position = pose[:2]
        to_goal = np.asarray(target, dtype=float)[:2] - position
        goal_distance = float(np.linalg.norm(to_goal))
        goal_direction = to_goal / max(goal_distance, 1e-9)
        total = self.params.apf_attractive_gain * goal_direction

        landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 2)
        away = position - landmarks
        distance = np.linalg.norm(away, axis=1)
        rho0 = self.params.apf_influence_m
        rho = distance - self.keep_out_m
        active = rho < rho0
        if not np.any(active) or rho0 <= 0.0:
            return total
        normal = away[active] / np.maximum(distance[active], 1e-9)[:, None]
        rho = np.maximum(rho[active], _MIN_RHO_M)
        goal_scale = min(1.0, (goal_distance / rho0) ** 2)
        magnitude = (self.params.apf_repulsive_gain * (1.0 / rho - 1.0 / rho0) / rho ** 2
                     * goal_scale)
        tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
        heading = np.array([np.cos(pose[2]), np.sin(pose[2])])
        side = np.where(tangent @ (goal_direction + _HEADING_TIE_WEIGHT * heading) >= 0.0,
                        1.0, -1.0)
        return total + magnitude @ (normal + side[:, None] * tangent)

    def command(self, pose: np.ndarray, target: np.ndarray, landmarks: np.ndarray) -> float:
        """Heading change [rad] for the next step, clipped to ``±max_turn_per_step_rad``.

        Args:
            pose: (3,) current map-frame pose.
            target: (2,) map-frame target position [m].
            landmarks: (M, 2) known (estimated) landmark positions [m].
        """
        pose = np.asarray(pose, dtype=float)
        landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 2)
        force = self.force(pose, target, landmarks)
        limit = self.params.max_turn_per_step_rad
        apf_turn = float(np.clip(wrap_angle(np.arctan2(force[1], force[0]) - pose[2]),
                                 -limit, limit))
        candidates = np.concatenate([[apf_turn], np.linspace(-limit, limit, _CANDIDATE_TURNS)])
        clearance = self._rollout_clearance(pose, candidates, landmarks)
        if clearance is None:
            return apf_turn
        current = float(np.min(np.linalg.norm(landmarks - pose[:2], axis=1)))
        safe = clearance >= min(self.keep_out_m, current) - 1e-9
        if not np.any(safe):
            return float(candidates[np.argmax(clearance)])
        deviation = np.where(safe, np.abs(candidates - apf_turn), np.inf)
        return float(candidates[np.argmin(deviation)])

    def _rollout_clearance(self, pose: np.ndarray, turns: np.ndarray,
                           landmarks: np.ndarray) -> np.ndarray | None:
        """For each candidate turn (U,), the smallest landmark distance [m] along the best of
        three constant-turn continuations (left, straight, right at the maximum rate, for
        half a turn); None when no landmark is close enough to matter."""
        step_m = self.params.speed_mps * self.params.time_step_s
        limit = self.params.max_turn_per_step_rad
        horizon = int(np.ceil(np.pi / limit)) if limit > 0.0 else 1
        reach = self.keep_out_m + step_m * (horizon + 1)
        near = landmarks[np.linalg.norm(landmarks - pose[:2], axis=1) < reach]
        if len(near) == 0:
            return None
        first = step_pose(np.broadcast_to(pose, (len(turns), 3)), turns, step_m, self.params)
        rates = np.array([-limit, 0.0, limit])
        steps = np.arange(1, horizon + 1)
        headings = first[:, None, None, 2] + rates[None, :, None] * steps[None, None, :]
        path = first[:, None, None, :2] + step_m * np.cumsum(
            np.stack([np.cos(headings), np.sin(headings)], axis=-1), axis=2)
        path = np.concatenate([np.broadcast_to(first[:, None, None, :2], (len(turns), 3, 1, 2)),
                               path], axis=2)
        distance = np.linalg.norm(path[..., None, :] - near, axis=-1)
        return distance.min(axis=(2, 3)).max(axis=1)

    def reached(self, pose: np.ndarray, target: np.ndarray) -> bool:
        """True when the pose (3,) lies within ``goal_tolerance_m`` of the target (2,) [m]."""
        offset = np.asarray(pose, dtype=float)[:2] - np.asarray(target, dtype=float)[:2]
        return bool(np.linalg.norm(offset) <= self.params.goal_tolerance_m)
