"""What the outside observer keeps to count the robots' data association at the end of a
run (``association_stats``), from what the world and the robots publish: truth side only.

When the sonar is not the paper's ideal one, the observer (``EvaluatorSession``, in
em-evaluator and in em-sim) takes:

* the truth of every robot's scan at each keyframe step (``sonar_truth``: the readings and
  where each came from, a landmark id or ``sensors.CLUTTER``; em-world publishes it on
  /world/sonar_truth/robot_i, which no robot reads);
* the landmark readings of every keyframe in each robot's team stream (``team_update``),
  named by the team graph's landmark ids as every robot's ``TeamSlam`` names them, the
  late readings of earlier keyframes with the keyframe that carried them;
* the teammates' landmarks each robot tied to its own and the step it did
  (``correspondences``; /robot_i/landmark_correspondences).

``counts`` rebuilds what each robot's graph held when it answered the run's last step ``e``
(the step before the final evaluation, whose estimates that evaluation read) and counts it
as em-sim's robots' own graphs would be counted: robot i's keyframes in its graph are those
of the path it published last (the final evaluation's); a teammate's, those of the
teammate's path made before step e (the lockstep delivers a record made at step s before step
s + 1); the correspondences, those tied up to step e. Over links that are not perfect a
record may reach a teammate later than that: the teammate's landmarks a correspondence names
are then judged by readings the robot may not have held yet (only the correspondences' counts
can differ, and only if that changes which landmark most of a teammate's readings came from).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from em_exploration_ros.core.evaluation.association_stats import (GraphReading,
                                                                  association_summary,
                                                                  robot_association)
from em_exploration_ros.core.records.readings import LandmarkReading
from em_exploration_ros.core.records.team_data import TeamUpdate
from em_exploration_ros.core.slam.team_slam import graph_landmark_id


class AssociationRecord:
    """The observer's evidence of a team of ``num_robots`` (see module docstring);
    ``shared_landmark_ids``: the sonar names landmarks (``sensors.landmark_ids``), so the
    graph ids are the world's."""

    def __init__(self, num_robots: int, keyframe_interval_steps: int,
                 shared_landmark_ids: bool) -> None:
        self.num_robots = num_robots
        self.interval = keyframe_interval_steps
        self._shared = shared_landmark_ids
        #: (robot, step) -> (the scan's readings, the source of each): the world's truth.
        self.scans: dict[tuple[int, int], tuple[tuple[LandmarkReading, ...],
                                                tuple[int, ...]]] = {}
        #: robot -> keyframe index -> the landmark readings it adds to the graph (the
        #: keyframe index each is of: its own or, for a late reading, an earlier one; graph
        #: id, bearing, range).
        self._keyframes: list[dict[int, tuple[tuple[int, int, float, float], ...]]] = [
            {} for _ in range(num_robots)]
        #: robot -> (own landmark id, teammate's landmark id) -> the step it was tied at.
        self._ties: list[dict[tuple[int, int], int]] = [{} for _ in range(num_robots)]

    def has_scan(self, robot: int, step: int) -> bool:
        """Whether the truth of robot ``robot``'s scan at ``step`` is in."""
        return (robot, step) in self.scans

    def sonar_truth(self, robot: int, step: int, readings: tuple[LandmarkReading, ...],
                    sources: tuple[int, ...]) -> None:
        """The truth of robot ``robot``'s scan at keyframe step ``step`` (the first copy
        counts)."""
        self.scans.setdefault((robot, step), (tuple(readings), tuple(sources)))

    def team_update(self, update: TeamUpdate) -> None:
        """A record of a robot's stream, in sequence order: its keyframes' readings."""
        robot = update.robot_id
        for keyframe in update.keyframes:
            readings = [(keyframe.index, reading) for reading in keyframe.landmarks]
            readings.extend((late.keyframe_index, late.reading)
                            for late in keyframe.late_landmarks)
            self._keyframes[robot].setdefault(keyframe.index, tuple(
                (index, graph_landmark_id(robot, reading.landmark_id, self._shared),
                 reading.bearing_rad, reading.range_m) for index, reading in readings))

    def correspondences(self, robot: int, step: int, pairs: Iterable[tuple[int, int]]
                        ) -> None:
        """Landmark pairs (own id, teammate's id) robot ``robot`` tied while answering
        ``step`` (a pair tied again, by a restarted process, keeps its first step)."""
        for pair in pairs:
            self._ties[robot].setdefault((int(pair[0]), int(pair[1])), step)

    def missing_scans(self, end_step: int) -> list[tuple[int, int]]:
        """(robot, step) of the keyframe scans up to ``end_step`` whose truth is not in."""
        return [(robot, step) for step in range(0, end_step + 1, self.interval)
                for robot in range(self.num_robots) if (robot, step) not in self.scans]

    def counts(self, end_step: int, paths: Mapping[int, Iterable[int]]) -> dict[str, Any]:
        """The summary's ``association`` as of each robot's answer to ``end_step``, with
        ``paths``: each robot's keyframe indices in the path it published last (the final
        evaluation's; a robot without one holds no keyframe)."""
        indices = {robot: sorted(int(i) for i in path) for robot, path in paths.items()}
        return association_summary(
            robot_association(robot, self._graph_readings(robot, end_step, indices),
                              indices.get(robot, []),
                              [pair for pair, step in self._ties[robot].items()
                               if step <= end_step],
                              self.scans, self.interval)
            for robot in range(self.num_robots))

    def _graph_readings(self, robot: int, end_step: int,
                        indices: Mapping[int, list[int]]) -> list[GraphReading]:
        """The landmark readings robot ``robot``'s graph held after answering ``end_step``:
        those of its own keyframes in its path and of its teammates' made before it."""
        readings: list[GraphReading] = []
        for owner in range(self.num_robots):
            keyframes = self._keyframes[owner]
            for index in indices.get(owner, []):
                if owner != robot and index * self.interval >= end_step:
                    continue
                readings.extend((owner, of_index, landmark, bearing, range_m)
                                for of_index, landmark, bearing, range_m
                                in keyframes.get(index, ()))
        return readings
