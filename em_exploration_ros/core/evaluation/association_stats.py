"""How well the robots associated their sonar detections, against ground truth. Truth
side only: the world's record of where each detection came from never reaches a robot.

A robot's graph holds landmark readings (``TeamSlam.landmark_readings``: its own keyframes'
and its teammates'); each is one detection of the world's scan at that keyframe's step,
found again by its bearing and range (the keyframe carries them rounded to float32). A
graph landmark stands for the true landmark most of its readings came from (clutter, when
most came from none). Per robot, over the readings of its own keyframes in its own graph:

* ``correct``: readings of the true landmark their graph landmark stands for;
* ``wrong``: any other reading (another landmark's, or clutter kept as a landmark's);
* ``missed``: detections of a true landmark at a keyframe in the graph left out of it
  (unpaired, or still a tentative track);
* ``spurious_landmarks``: own landmarks that stand for clutter, or for a true landmark an
  earlier own landmark already stands for;
* ``correspondences_correct`` / ``_wrong``: the teammates' landmarks it tied to its own
  (``TeamSlam.landmark_correspondences``) that stand for the same true landmark, or not.

``precision`` is ``correct / (correct + wrong)`` and ``recall`` is ``correct / (detections of
true landmarks at its keyframes in the graph)``, each 1 when there is nothing to count. The
team's counts are the robots' sums; its precision counts each correspondence as one more
association (correct or wrong).
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from em_exploration_ros.core.records.readings import LandmarkReading
from em_exploration_ros.core.slam.team_slam import TeamSlam
from em_exploration_ros.core.world.sensors import CLUTTER

#: A graph reading is the scan's detection with the same bearing and range up to the
#: float32 rounding of the team stream (relative 1e-6; these tolerances are 10 times more).
BEARING_TOLERANCE_RAD = 1e-5
RANGE_TOLERANCE_M = 1e-4

#: (robot, step) -> (the scan's readings, the source of each: a landmark id or CLUTTER).
KeyframeScans = Mapping[tuple[int, int], tuple[tuple[LandmarkReading, ...], tuple[int, ...]]]
#: A graph's landmark reading: (robot, keyframe index, landmark id, bearing [rad], range [m]).
GraphReading = tuple[int, int, int, float, float]


@dataclass(frozen=True)
class AssociationCounts:
    """Association outcomes of one robot (or the team); see the module docstring."""

    correct: int = 0
    wrong: int = 0
    missed: int = 0
    true_detections: int = 0
    spurious_landmarks: int = 0
    correspondences_correct: int = 0
    correspondences_wrong: int = 0

    @property
    def precision(self) -> float:
        """Share of the associations made that are right, in [0, 1]."""
        made = self.correct + self.wrong + self.correspondences_correct \
            + self.correspondences_wrong
        return (self.correct + self.correspondences_correct) / made if made else 1.0

    @property
    def recall(self) -> float:
        """Share of the detections of true landmarks that the graph holds rightly, [0, 1]."""
        return self.correct / self.true_detections if self.true_detections else 1.0

    def __add__(self, other: AssociationCounts) -> AssociationCounts:
        return AssociationCounts(**{name: value + getattr(other, name)
                                    for name, value in asdict(self).items()})

    def to_dict(self) -> dict[str, Any]:
        """The counts with ``precision`` and ``recall``."""
        return {"precision": self.precision, "recall": self.recall, **asdict(self)}


def _source(scans: KeyframeScans, robot: int, step: int, bearing: float,
            range_m: float) -> int | None:
    """The source of the detection of robot ``robot``'s scan at ``step`` with this bearing
    and range, None if the scan holds none (not a detection of that scan)."""
    scan = scans.get((robot, step))
    if scan is None or not scan[0]:
        return None
    readings, sources = scan
    bearings = np.array([r.bearing_rad for r in readings])
    ranges = np.array([r.range_m for r in readings])
    close = np.flatnonzero((np.abs(bearings - bearing) <= BEARING_TOLERANCE_RAD)
                           & (np.abs(ranges - range_m) <= RANGE_TOLERANCE_M))
    return int(sources[close[0]]) if len(close) else None


def landmark_sources(readings: Iterable[GraphReading], scans: KeyframeScans,
                     keyframe_interval_steps: int) -> tuple[dict[int, int], list[int | None]]:
    """What each graph landmark stands for (``{landmark id: true id or CLUTTER}``, by the
    majority of its readings, the lowest id on a tie) and the source of each reading."""
    readings = list(readings)
    sources = [_source(scans, robot, index * keyframe_interval_steps, bearing, range_m)
               for robot, index, _, bearing, range_m in readings]
    votes: dict[int, Counter] = {}
    for (_, _, landmark, _, _), source in zip(readings, sources):
        if source is not None:
            votes.setdefault(landmark, Counter())[source] += 1
    stands_for = {landmark: min(counter.items(), key=lambda item: (-item[1], item[0]))[0]
                  for landmark, counter in votes.items()}
    return stands_for, sources


def robot_association(robot_id: int, readings: Iterable[GraphReading],
                      keyframe_indices: Iterable[int],
                      correspondences: Iterable[tuple[int, int]], scans: KeyframeScans,
                      keyframe_interval_steps: int) -> AssociationCounts:
    """Robot ``robot_id``'s counts from its own graph: its ``readings`` (every landmark
    reading the graph holds), the indices of its own keyframes in the graph, the
    correspondences it accepted, and the world's ``scans``."""
    readings, correspondences = list(readings), list(correspondences)
    stands_for, sources = landmark_sources(readings, scans, keyframe_interval_steps)
    correct = wrong = 0
    held: dict[int, set[int]] = {}
    first_landmark: dict[int, int] = {}
    spurious: set[int] = set()
    for (robot, index, landmark, _, _), source in zip(readings, sources):
        if robot != robot_id:
            continue
        if source is not None and source != CLUTTER and source == stands_for.get(landmark):
            correct += 1
            held.setdefault(index, set()).add(source)
        else:
            wrong += 1
        meaning = stands_for.get(landmark)
        if meaning is not None and landmark not in spurious:
            if meaning == CLUTTER or first_landmark.setdefault(meaning, landmark) != landmark:
                spurious.add(landmark)
    true_detections = missed = 0
    for index in keyframe_indices:
        scan = scans.get((robot_id, index * keyframe_interval_steps))
        if scan is None:
            continue
        for source in scan[1]:
            if source != CLUTTER:
                true_detections += 1
                missed += source not in held.get(index, set())
    right = sum(1 for a, b in correspondences
                if stands_for.get(a) is not None and stands_for.get(a) == stands_for.get(b)
                and stands_for.get(a) != CLUTTER)
    return AssociationCounts(correct, wrong, missed, true_detections, len(spurious), right,
                             len(correspondences) - right)


def team_association(slams: Sequence[TeamSlam], scans: KeyframeScans,
                     keyframe_interval_steps: int) -> dict[str, Any]:
    """:func:`association_summary` of a team from each robot's own graph (em-sim)."""
    return association_summary(
        robot_association(slam.robot_id, slam.landmark_readings(),
                          slam.trajectory(slam.robot_id)[0], slam.landmark_correspondences,
                          scans, keyframe_interval_steps) for slam in slams)


def association_summary(robots: Iterable[AssociationCounts]) -> dict[str, Any]:
    """The summary's ``association``: the team's counts, precision and recall, and each
    robot's (``robots``, by id)."""
    robots = list(robots)
    team = sum(robots, AssociationCounts())
    return {**team.to_dict(), "robots": [counts.to_dict() for counts in robots]}


def association_line(data: Mapping[str, Any]) -> str:
    """One line of a summary's ``association``, e.g. ``association: precision 0.998, recall
    0.912; 1210 correct, 2 wrong, 117 missed, 0 spurious landmarks; correspondences 12
    correct, 0 wrong``."""
    return (f"association: precision {data['precision']:.3f}, recall {data['recall']:.3f}; "
            f"{data['correct']} correct, {data['wrong']} wrong, {data['missed']} missed, "
            f"{data['spurious_landmarks']} spurious landmarks; correspondences "
            f"{data['correspondences_correct']} correct, {data['correspondences_wrong']} wrong")
