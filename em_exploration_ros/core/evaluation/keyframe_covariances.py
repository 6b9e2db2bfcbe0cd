"""The pose uncertainty each robot published: one marginal covariance per keyframe.

At every keyframe step a robot publishes its latest keyframe's pose with its marginal
covariance (``/robot_i/estimated_pose``, geometry_msgs/PoseWithCovarianceStamped in the
map frame, stamped with the keyframe's time); em-sim hands its observer the same values.
The observer keeps each keyframe's covariance as the robot last published it, i.e. as the
robot knew it when that keyframe was its newest (a later loop closure or meeting, which
shrinks it, is not published again: a robot marginalizes one pose per keyframe, not its
whole trajectory). From them:

- the latest covariance of each robot as of a time: its position uncertainty over time
  (the timeline's ``robot_pose_sigma_m``);
- the covariance of each keyframe of a robot's estimated path: the team virtual map's
  uncertainty in the final map (``map_layers.team_virtual_map``), each cell's ellipse as the
  team knew it when the cell was seen.

Covariances are (3, 3) over (x [m], y [m], theta [rad]), map frame.
"""
from __future__ import annotations

import bisect

import numpy as np

from em_exploration_ros.core.evaluation.evaluator import stamp_key, stamp_keys


class KeyframeCovariances:
    """Each robot's published keyframe covariances, by the keyframe's stamp (module
    docstring). Stamps of a robot come in time order (the caller drops older ones); one
    published again replaces the earlier."""

    def __init__(self) -> None:
        self._keys: dict[int, list[int]] = {}
        self._covariances: dict[int, list[np.ndarray]] = {}

    @property
    def published(self) -> bool:
        """Whether any robot published a keyframe covariance."""
        return bool(self._keys)

    def newest_key(self, robot: int) -> int | None:
        """Stamp key of the robot's newest keyframe covariance (None before the first)."""
        keys = self._keys.get(robot)
        return keys[-1] if keys else None

    def add(self, robot: int, stamp_s: float, covariance: np.ndarray) -> None:
        """Keep the covariance (3, 3) of the robot's keyframe of time ``stamp_s`` [s], not
        older than its newest."""
        keys = self._keys.setdefault(robot, [])
        covariances = self._covariances.setdefault(robot, [])
        key = stamp_key(stamp_s)
        if keys and keys[-1] == key:
            covariances[-1] = np.asarray(covariance, dtype=float).reshape(3, 3)
            return
        keys.append(key)
        covariances.append(np.asarray(covariance, dtype=float).reshape(3, 3))

    def latest_as_of(self, stamp_s: float) -> dict[int, np.ndarray] | None:
        """Each robot's newest covariance stamped at or before ``stamp_s`` [s] (robots
        without one left out); None while no robot published any."""
        if not self.published:
            return None
        limit = stamp_key(stamp_s)
        latest = {}
        for robot, keys in sorted(self._keys.items()):
            row = bisect.bisect_right(keys, limit) - 1
            if row >= 0:
                latest[robot] = self._covariances[robot][row]
        return latest

    def along(self, robot: int, stamps_s: np.ndarray) -> np.ndarray:
        """The covariances (K, 3, 3) of the robot's keyframes of times ``stamps_s`` (K,) [s]
        (a path's), NaN where none was published."""
        stamps = stamp_keys(stamps_s).reshape(-1)
        found = np.full((len(stamps), 3, 3), np.nan)
        keys = np.array(self._keys.get(robot, ()), dtype=np.int64)
        if not len(keys):
            return found
        rows = np.minimum(np.searchsorted(keys, stamps), len(keys) - 1)
        hit = keys[rows] == stamps
        if hit.any():
            found[hit] = np.array(self._covariances[robot])[rows[hit]]
        return found
