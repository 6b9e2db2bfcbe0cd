"""Robot-to-robot detections screened by pairwise consistency before they enter a team graph.

A robot's detection of a teammate (``TeammateReading`` at one of its keyframes: the
teammate's pose at the same keyframe index, in the observer's body frame) is an inter-robot
loop closure. A wrong one (a misidentified vehicle, a multipath return) would bend every
teammate's graph that holds it, as a wrong landmark correspondence would. Without landmark
identities (field sensing) :class:`RobotDetectionScreen` keeps detections back until they
agree with others of the same two robots, the pairwise consistency test DRACo-SLAM and
Swarm-SLAM apply to inter-robot loop closures (Mangelson et al. 2018):

* Two detections of robots ``a < b``, ``z_i`` at keyframe index ``i`` and ``z_j`` at ``j``
  (each the pose of b's keyframe in a's, whichever robot observed), are consistent when the
  loop ``z_i ⊕ B = A ⊕ z_j`` closes within the chi-square gate (3 degrees of freedom), with
  ``A`` and ``B`` each robot's odometry from ``i`` to ``j`` (``detections_agree``). Two
  robots in sonar range see each other at the same keyframe, and those two detections test
  each other with no odometry between them.
* A detection is accepted once it agrees with at least one, and at least half, of the other
  detections of its two robots within ``window`` keyframes of it (those accepted already
  and those waiting). Accepted detections are not judged again, and they do not have to
  agree with each other: over a few keyframes with a sharp turn the odometry's stated
  covariance is tighter than its errors, so a true detection can disagree with one made 5
  keyframes before (a largest mutually consistent set then left out true detections that
  agreed with every recent one). A gross error agrees with none.
* A detection at either robot's first keyframe is accepted as it comes: it is the robot's
  start in the team frame (its launch pose), and nothing else places it.
* A waiting detection not accepted once both robots are ``window`` keyframes past it is left
  out, and the screen says why.

Poses are ``(x [m], y [m], theta [rad])``; covariances are of additive coordinate errors
(the convention of :mod:`geometry`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from em_exploration_ros.core.geometry import (compose, compose_jacobians, inverse,
                                              inverse_jacobian, wrap_angle)
from em_exploration_ros.core.records.readings import KeyframeId, TeammateReading
from em_exploration_ros.core.slam.association import chi2_quantile

#: The most accepted detections of one pair of robots a screening compares a waiting one
#: with (the latest ones): two robots in range add two per keyframe, 22 within 5 either side.
MAX_HELD_PER_PAIR = 24

#: A robot's odometry from one keyframe index to a later one: ``(delta (3,), covariance
#: (3, 3))`` in the body frame of the earlier keyframe, or None when its graph does not hold
#: the chain of keyframes between them. Arguments: robot, from index, to index.
MotionLookup = Callable[[int, int, int], "tuple[np.ndarray, np.ndarray] | None"]


@dataclass(frozen=True, eq=False)
class RobotDetection:
    """One robot's detection of a teammate: ``reading`` made at keyframe ``observer``.
    Two detections are equal only when they are the same object (a robot may, in a forged
    record, detect one teammate twice at one keyframe)."""

    observer: KeyframeId
    reading: TeammateReading

    @property
    def index(self) -> int:
        """The keyframe index of both the observer's and the observed robot's keyframe."""
        return self.observer[1]

    @property
    def robots(self) -> tuple[int, int]:
        """The two robots, lower id first."""
        return (min(self.observer[0], self.reading.robot_id),
                max(self.observer[0], self.reading.robot_id))

    def lower_to_higher(self) -> tuple[np.ndarray, np.ndarray]:
        """The higher-id robot's pose in the lower-id robot's body frame at this index, and
        its covariance: the reading itself, or its inverse when the higher-id robot
        observed."""
        pose = np.asarray(self.reading.relative_pose, dtype=float)
        covariance = np.asarray(self.reading.covariance, dtype=float)
        if self.observer[0] < self.reading.robot_id:
            return pose, covariance
        jacobian = inverse_jacobian(pose)
        return inverse(pose), jacobian @ covariance @ jacobian.T


def detections_agree(first: RobotDetection, second: RobotDetection, lower_motion: tuple,
                     higher_motion: tuple, gate: float, floor_variance: float = 0.0) -> bool:
    """Whether two detections of the same two robots close their loop within ``gate`` (a
    squared Mahalanobis distance, 3 degrees of freedom): ``z_1 ⊕ B`` against ``A ⊕ z_2``,
    with ``A`` (``lower_motion``) and ``B`` (``higher_motion``) each robot's odometry
    ``(delta, covariance)`` from ``first``'s keyframe index to ``second``'s; the loop's
    covariance gets ``floor_variance`` on its diagonal (the graph's floor, so that readings
    stated exact still give a test)."""
    z_1, cov_1 = first.lower_to_higher()
    z_2, cov_2 = second.lower_to_higher()
    (a_delta, a_cov), (b_delta, b_cov) = lower_motion, higher_motion
    j_z1, j_b = compose_jacobians(z_1, b_delta)
    via_first = compose(z_1, b_delta)
    cov_via_first = j_z1 @ cov_1 @ j_z1.T + j_b @ b_cov @ j_b.T
    j_a, j_z2 = compose_jacobians(a_delta, z_2)
    via_second = compose(a_delta, z_2)
    cov_via_second = j_a @ a_cov @ j_a.T + j_z2 @ cov_2 @ j_z2.T
    # The loop's error: the first path's end in the second path's end frame.
    j_inverse, j_end = compose_jacobians(inverse(via_second), via_first)
    j_second = j_inverse @ inverse_jacobian(via_second)
    error = compose(inverse(via_second), via_first)
    error[2] = wrap_angle(error[2])
    covariance = (j_second @ cov_via_second @ j_second.T + j_end @ cov_via_first @ j_end.T
                  + floor_variance * np.eye(3))
    try:
        return float(error @ np.linalg.solve(covariance, error)) <= gate
    except np.linalg.LinAlgError:  # readings stated exact with no floor: nothing to test by
        return False


@dataclass(frozen=True)
class LeftOut:
    """A detection the screen gave up on, and why."""

    detection: RobotDetection
    reason: str


class RobotDetectionScreen:
    """Robot-to-robot detections waiting for consistent company (module docstring).

    Bounded: waiting detections leave once both robots are ``window`` keyframes past them,
    and of the accepted ones each pair keeps the latest :data:`MAX_HELD_PER_PAIR`."""

    def __init__(self, window: int, gate_probability: float, floor_variance: float) -> None:
        self.window = window
        self._gate = chi2_quantile(3, gate_probability)
        self._floor = floor_variance
        self._waiting: dict[tuple[int, int], list[RobotDetection]] = {}
        self._held: dict[tuple[int, int], list[RobotDetection]] = {}

    @property
    def num_waiting(self) -> int:
        """Detections waiting for a decision."""
        return sum(len(waiting) for waiting in self._waiting.values())

    def offer(self, detection: RobotDetection) -> None:
        """A detection whose two keyframes are both in the graph, to be screened."""
        self._waiting.setdefault(detection.robots, []).append(detection)

    def accept_unscreened(self, detection: RobotDetection) -> None:
        """A detection accepted without a test (at a robot's first keyframe), held for
        testing the later ones."""
        self._hold(detection.robots, [detection])

    def screen(self, motion: MotionLookup, newest_index: Callable[[int], int]
               ) -> tuple[list[RobotDetection], list[LeftOut]]:
        """Decide what can be decided: the detections accepted now, and those left out.
        ``motion`` gives a robot's odometry between two of its keyframe indices (None when
        its graph lacks the chain); ``newest_index(robot)`` its latest keyframe index in the
        graph."""
        accepted: list[RobotDetection] = []
        left_out: list[LeftOut] = []
        for robots in sorted(self._waiting):
            waiting = self._waiting.pop(robots)
            lowest = min(detection.index for detection in waiting)
            held = [detection for detection in self._held.get(robots, [])
                    if detection.index >= lowest - self.window][-MAX_HELD_PER_PAIR:]
            pool = held + waiting
            consistent = self._consistency(pool, len(held), motion)
            indices = np.array([detection.index for detection in pool])
            now, undecided = [], []
            for k, detection in enumerate(waiting, start=len(held)):
                near = np.abs(indices - detection.index) <= self.window
                near[k] = False
                agreeing, others = int(np.count_nonzero(consistent[k, near])), int(near.sum())
                if agreeing >= 1 and 2 * agreeing >= others:
                    now.append(detection)
                else:
                    undecided.append((detection, agreeing, others))
            accepted.extend(now)
            self._hold(robots, now)
            past = min(newest_index(robot) for robot in robots)
            for detection, agreeing, others in undecided:
                if past < detection.index + self.window:
                    self._waiting.setdefault(robots, []).append(detection)
                elif others:
                    left_out.append(LeftOut(detection, (
                        f"agrees with {agreeing} of the {others} other detections of these "
                        f"robots within {self.window} keyframes")))
                else:
                    left_out.append(LeftOut(detection, (
                        f"no other detection of these robots within {self.window} keyframes")))
        return accepted, left_out

    def _hold(self, robots: tuple[int, int], detections: list[RobotDetection]) -> None:
        held = self._held.setdefault(robots, [])
        held.extend(detections)
        held.sort(key=lambda detection: detection.index)
        del held[:-MAX_HELD_PER_PAIR]

    def _consistency(self, pool: list[RobotDetection], first_waiting: int,
                     motion: MotionLookup) -> np.ndarray:
        """``(N, N)`` bool: which detections of ``pool`` (one pair of robots) agree, for
        every pair with a waiting one (from ``first_waiting`` on; two accepted ones are not
        compared) within ``window`` keyframes of each other; a pair whose odometry the graph
        does not hold does not agree."""
        count = len(pool)
        consistent = np.eye(count, dtype=bool)
        lower, higher = pool[0].robots
        motions: dict[tuple[int, int, int], tuple | None] = {}

        def between_indices(robot: int, since: int, until: int) -> tuple | None:
            key = (robot, since, until)
            if key not in motions:
                motions[key] = motion(robot, since, until)
            return motions[key]

        for i in range(count):
            for j in range(max(i + 1, first_waiting), count):
                first, second = sorted((pool[i], pool[j]), key=lambda d: d.index)
                if second.index - first.index > self.window:
                    continue
                lower_motion = between_indices(lower, first.index, second.index)
                higher_motion = between_indices(higher, first.index, second.index)
                if lower_motion is None or higher_motion is None:
                    continue
                consistent[i, j] = consistent[j, i] = detections_agree(
                    first, second, lower_motion, higher_motion, self._gate, self._floor)
        return consistent
