"""One robot's landmarks when sonar detections carry no identity (``sensors.landmark_ids``
false): its own detections paired with its own landmarks, and which of its
teammates' landmarks are its own.

Each robot numbers its own landmarks (0, 1, ...), and its keyframes carry those numbers to
the teammates; ``TeamSlam`` keeps robot r's landmark n as ``owned_landmark_id(r, n)``.
Nothing here sees a world landmark id: only the robot's detections, its keyframes, the
teammates' keyframes and the estimates of its own graph.

Frames and units: the ``map`` frame; poses ``(x [m], y [m], theta [rad])`` with covariances
of additive coordinate errors; detections (bearing [rad, body frame], range [m]).
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from em_exploration_ros.core.geometry import compose, compose_jacobians
from em_exploration_ros.core.params import SensorParams
from em_exploration_ros.core.records.readings import (KeyframeMeasurements, LandmarkReading,
                                                      LateReading)
from em_exploration_ros.core.slam.association import (RobotMotion, ScanCompatibility,
                                                      ScanPrediction, TentativeTracks,
                                                      detection_points, jcbb,
                                                      maximum_consistent_set,
                                                      offsets_within_gate,
                                                      pairwise_consistency,
                                                      point_pose_jacobian,
                                                      predict_measurements)
from em_exploration_ros.core.slam.team_slam import (OWNED_LANDMARK_STRIDE, TeamSlam,
                                                    body_to_map_covariance, landmark_owner,
                                                    owned_landmark_id)

#: Landmarks up to this far [m] beyond the sonar's range of the predicted pose are
#: candidates of a scan (the prediction's error).
CANDIDATE_MARGIN_M = 2.0
#: A teammate's landmark is a candidate correspondence of an own landmark only within this
#: distance [m] of it: loose, as two robots' maps may be offset by their drift (the gate
#: and pairwise consistency then judge); distinct landmarks of the world lie
#: ``world.landmark_min_separation_m`` (10 m) apart.
CORRESPONDENCE_RADIUS_M = 3.0
#: A landmark last seen at most this many keyframes before the previous one is gated on
#: the odometry since (relative), an older one on the marginals from iSAM2.
RECENT_KEYFRAMES = 10
#: Fewest correspondences with one teammate, consistent with each other, before any is
#: accepted: one alone has nothing to be checked against.
FIRST_CORRESPONDENCES = 2


@dataclasses.dataclass(frozen=True)
class _Sighting:
    """One detection held in a tentative track: the own keyframe that saw it, its reading,
    and the own landmark (graph id) it was paired with while that landmark waited for its
    track (a landmark gated on the marginals), else None."""

    index: int
    reading: LandmarkReading
    landmark: int | None


class OwnLandmarks:
    """Data association of one robot without landmark identities.

    :meth:`associate` turns a keyframe of unidentified detections into one whose readings
    name the robot's own landmarks: the detections of a scan are paired with the own
    landmarks near the predicted pose by JCBB, the others go to tentative tracks, and a
    track seen in ``track_confirm_hits`` of the last ``track_window_keyframes`` keyframes
    becomes a new landmark, its earlier sightings named too (the keyframe's
    ``late_landmarks``: without them a landmark's first sightings were lost, and recall
    stayed near 0.71); detections paired with nothing are left out.
    :meth:`match_teammates` finds teammates' landmarks that are own ones and ties them in
    the graph, accepting a correspondence only when it is consistent with the others it
    holds with that teammate (pairwise consistency maximization).

    Uncertainty is relative where it can be: the estimates of iSAM2 place the previous
    keyframe and the landmarks; the prediction's pose covariance is the odometry since the
    previous keyframe (shared by every detection of the scan, which JCBB uses). A landmark
    seen within the last ``RECENT_KEYFRAMES`` keyframes has the odometry covariance from
    the keyframe that last saw it to the previous one, moved to the landmark, plus the
    sonar's noise; an older one its marginal plus the previous pose's, moved to the
    landmark (the map-frame marginals from iSAM2, which hold what the team's graph did to
    both since). The marginals hold the drift from the mission's start, common to pose and
    landmarks (about 0.3 m after 250 steps): as gates of every landmark and track they let
    clutter in where the landmark was missed. Tentative tracks live in the robot's
    dead-reckoned odometry frame, where what the graph does to the map does not move them:
    a track's gate holds the odometry's errors since its last sighting (``RobotMotion``).

    Such a wide gate still has to judge the loop closures, so a detection paired with a
    landmark gated on the marginals is not named at once: it goes to the tentative tracks
    with that landmark, and names it only once its track was seen in
    ``loop_closure_confirm_hits`` of the window's keyframes (then with its earlier
    sightings, as late readings; a track paired with several landmarks names the one paired
    most often). One clutter point inside such a gate, where the landmark was missed, bent
    a robot's map by 1.7 m under the Cauchy loss: the pose, held only by the odometry since
    the landmark was last seen, gave way to it.
    """

    def __init__(self, slam: TeamSlam, sensor_params: SensorParams) -> None:
        self._slam = slam
        self._robot = slam.robot_id
        params = slam.slam_params
        self._probability = params.association_gate_probability
        self._floor = params.covariance_floor_sigma ** 2
        self._window = params.track_window_keyframes
        self._loop_closure_hits = params.loop_closure_confirm_hits
        self._tracks = TentativeTracks(params.track_confirm_hits, self._window,
                                       self._probability)
        self._reach_m = sensor_params.sonar_max_range_m + CANDIDATE_MARGIN_M
        self._next_own = 0
        #: Own keyframe index -> (odometry delta (3,), covariance (3, 3)) from the previous.
        self._motion: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        #: Own keyframe index -> its pose (3,) in the dead-reckoned odometry frame, where
        #: the tentative tracks are (their gates then hold the odometry's errors alone).
        self._dead_reckoned: dict[int, np.ndarray] = {}
        #: Own landmark (graph id) -> the latest own keyframe index that saw it.
        self._last_seen: dict[int, int] = {}
        #: Accepted correspondences with each teammate: (own id, teammate's id).
        self._held: dict[int, list[tuple[int, int]]] = {}
        #: Landmarks in the graph at the last :meth:`match_teammates` that looked.
        self._landmarks_matched = 0

    @property
    def num_tentative(self) -> int:
        """Tentative tracks held."""
        return len(self._tracks)

    def associate(self, keyframe: KeyframeMeasurements) -> KeyframeMeasurements:
        """``keyframe`` (this robot's, detections unidentified) with its landmark readings
        named by own landmark numbers; detections of no landmark (yet) are left out, and all
        of them while the robot cannot predict its pose (not yet tied to the map)."""
        self._record_motion(keyframe)
        prediction = self._predicted_pose(keyframe)
        if prediction is None or not keyframe.landmarks:
            return dataclasses.replace(keyframe, landmarks=())
        previous, pose, pose_covariance = prediction
        readings = keyframe.landmarks
        measurements = np.array([[r.bearing_rad, r.range_m] for r in readings])
        noise = np.array([np.diag([r.bearing_variance + self._floor,
                                   r.range_variance + self._floor]) for r in readings])
        ids, points, covariances, old = self._own_landmarks_near(previous, pose, keyframe,
                                                                 noise[0])
        pairing = jcbb(ScanCompatibility(ScanPrediction(pose, pose_covariance, points,
                                                        covariances), measurements, noise),
                       self._probability)
        # A pairing with a landmark gated on the marginals waits for its track (class doc).
        waiting = {d: int(ids[row]) for d, row in enumerate(pairing)
                   if row is not None and old[row]}
        tracked = [d for d, row in enumerate(pairing) if row is None or d in waiting]
        odometry_pose = self._dead_reckoned[keyframe.index]
        # Tracks last seen at one keyframe share the motion since it: computed once.
        motion_since = functools.cache(lambda since: self._relative_covariance(
            since, keyframe.index, odometry_pose[2]))
        track_points, track_covariances = detection_points(
            odometry_pose, np.zeros((3, 3)), measurements[tracked], noise[tracked])
        confirmed = dict(zip(tracked, self._tracks.observe(
            keyframe.index, track_points, track_covariances,
            [_Sighting(keyframe.index, readings[d], waiting.get(d)) for d in tracked],
            [self._loop_closure_hits if d in waiting else self._tracks.confirm_hits
             for d in tracked],
            RobotMotion(odometry_pose, motion_since))))
        paired = {d: int(ids[row]) for d, row in enumerate(pairing)
                  if row is not None and d not in waiting}
        # One scan sees a landmark once: a track does not name one another reading names.
        taken = set(paired.values())
        named, late = [], []
        for d, reading in enumerate(readings):
            if d in paired:
                landmark = paired[d]
            elif confirmed[d] is not None:
                landmark = self._confirmed_landmark(
                    [*confirmed[d], _Sighting(keyframe.index, reading, waiting.get(d))], taken)
                taken.add(landmark)
            else:
                continue
            self._last_seen[landmark] = keyframe.index
            number = landmark % OWNED_LANDMARK_STRIDE
            named.append(dataclasses.replace(reading, landmark_id=number))
            late.extend(LateReading(earlier.index,
                                    dataclasses.replace(earlier.reading, landmark_id=number))
                        for earlier in confirmed.get(d) or ())
        return dataclasses.replace(keyframe, landmarks=tuple(named), late_landmarks=tuple(late))

    def _record_motion(self, keyframe: KeyframeMeasurements) -> None:
        """Keep the keyframe's odometry and its dead-reckoned pose (the odometry composed
        since the first keyframe this association saw, or since the chain broke: a restart),
        for the last ``max(RECENT_KEYFRAMES, track_window_keyframes)`` keyframes."""
        before = self._dead_reckoned.get(keyframe.previous_index)
        if keyframe.is_first or before is None:
            self._dead_reckoned[keyframe.index] = np.zeros(3)
        else:
            delta = np.asarray(keyframe.odom_delta, dtype=float)
            self._motion[keyframe.index] = (delta, np.asarray(keyframe.odom_covariance,
                                                              dtype=float))
            self._dead_reckoned[keyframe.index] = compose(before, delta)
        kept = keyframe.index - max(RECENT_KEYFRAMES, self._window)
        for history in (self._motion, self._dead_reckoned):
            for index in [index for index in history if index < kept]:
                del history[index]

    def _confirmed_landmark(self, sightings: list[_Sighting], taken: set[int]) -> int:
        """The landmark (graph id) a confirmed track stands for: the own landmark its
        sightings were paired with most often (the earliest such on a tie) of those not in
        ``taken`` (named by another reading of the same keyframe), else a new one."""
        paired = [sighting.landmark for sighting in sightings
                  if sighting.landmark is not None and sighting.landmark not in taken]
        if paired:
            return max(dict.fromkeys(paired), key=paired.count)
        return owned_landmark_id(self._robot, self._new_own_number())

    def _new_own_number(self) -> int:
        """The next own landmark number: after every own landmark of the graph too (a
        restarted robot's recovered stream holds its earlier ones)."""
        in_graph = [landmark_id % OWNED_LANDMARK_STRIDE + 1
                    for landmark_id in self._slam.landmark_estimates()
                    if landmark_owner(landmark_id) == self._robot]
        number = max([self._next_own, *in_graph])
        self._next_own = number + 1
        return number

    def _predicted_pose(self, keyframe: KeyframeMeasurements
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The previous keyframe's estimate (3,), this keyframe's pose (3,) predicted from
        it by the odometry, and the covariance (3, 3) of that odometry (map frame); None
        while the previous keyframe is not in the graph (or this is the first one)."""
        if keyframe.is_first or self._slam.latest_index(self._robot) != keyframe.previous_index:
            return None
        previous = self._slam.pose(self._robot, keyframe.previous_index)
        _, j_delta = compose_jacobians(previous, keyframe.odom_delta)
        covariance = j_delta @ np.asarray(keyframe.odom_covariance) @ j_delta.T
        return previous, compose(previous, keyframe.odom_delta), covariance

    def _relative_covariance(self, since: int, until: int, until_heading: float
                             ) -> np.ndarray:
        """Covariance (3, 3) of the motion from own keyframe ``since`` to ``until`` (first
        order, from the recorded odometry in between), as additive map-frame errors of
        ``until``'s pose given ``since``'s: the odometry's errors are in the body frame of
        ``since``, which is rotated from the map by ``until_heading`` [rad] less the
        motion's turn."""
        delta, covariance = np.zeros(3), np.zeros((3, 3))
        for index in range(max(since, 0) + 1, until + 1):
            step = self._motion.get(index)
            if step is None:
                continue
            j_accumulated, j_step = compose_jacobians(delta, step[0])
            covariance = j_accumulated @ covariance @ j_accumulated.T + \
                j_step @ step[1] @ j_step.T
            delta = compose(delta, step[0])
        return body_to_map_covariance(np.array([0.0, 0.0, until_heading - delta[2]]),
                                      covariance)

    def _own_landmarks_near(self, previous: np.ndarray, pose: np.ndarray,
                            keyframe: KeyframeMeasurements, noise: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ids (L,), points (L, 2), covariances (L, 2, 2) and whether each is gated on the
        marginals (L,) bool, of this robot's own landmarks within the sonar's range (plus a
        margin) of ``pose``: a recent one's covariance is the motion's from the keyframe
        that last saw it to ``previous``, moved to the landmark, plus the sonar's ``noise``
        (2, 2) there; an older one's the marginals' (class docstring), as is one this
        association has not named (a restarted robot's, from its journal: gated on the
        sonar's noise alone, as if seen just before, a re-seen one was made anew)."""
        near = [(landmark_id, point) for landmark_id, point
                in self._slam.landmark_estimates().items()
                if landmark_owner(landmark_id) == self._robot
                and np.hypot(*(point - pose[:2])) <= self._reach_m]
        ids = np.array([landmark_id for landmark_id, _ in near], dtype=np.int64)
        points = np.array([point for _, point in near], dtype=float).reshape(-1, 2)
        covariances = np.zeros((len(near), 2, 2))
        old = np.zeros(len(near), dtype=bool)
        for row, (landmark_id, point) in enumerate(near):
            moved = point_pose_jacobian(previous, point)
            last_seen = self._last_seen.get(landmark_id)
            if last_seen is not None and keyframe.previous_index - last_seen <= RECENT_KEYFRAMES:
                motion = self._relative_covariance(last_seen, keyframe.previous_index,
                                                   previous[2])
                measured = predict_measurements(previous, point[None])[0]
                point_part = detection_points(previous, np.zeros((3, 3)), measured,
                                              noise[None])[1][0]
            else:
                old[row] = True
                motion = body_to_map_covariance(previous, self._slam.pose_covariance(
                    self._robot, keyframe.previous_index))
                point_part = self._slam.landmark_covariance(int(landmark_id))
            covariances[row] = moved @ motion @ moved.T + point_part
        return ids, points, covariances, old

    def match_teammates(self) -> list[tuple[int, int]]:
        """Find teammates' landmarks that are this robot's own and tie them in the graph
        (``TeamSlam.add_landmark_correspondences``); returns the pairs (own id, teammate's
        id) accepted now.

        A candidate pairs a teammate's landmark with the nearest own landmark, each the
        other's nearest, neither tied yet, within ``CORRESPONDENCE_RADIUS_M``. Both
        landmarks are in this robot's graph, so the covariance of their offset, and of the
        offsets of any two candidates, comes from the graph's joint marginals (the drift
        between the two maps that the graph holds shows in them, and a drift common to two
        correspondences cancels): a candidate whose offset is outside the gate under its
        own covariance is left out (``offsets_within_gate``); two correspondences are
        consistent when their offsets agree (``pairwise_consistency``). With each teammate,
        the candidates consistent with every correspondence it holds, and the largest set of
        them consistent with each other, are accepted (at least ``FIRST_CORRESPONDENCES``
        when it holds none). It looks again only once the graph holds more landmarks than
        when it last looked.

        Marginals taken as independent (before) let wrong correspondences through: Victoria
        Park's robots (em-bench dataset, 3 robots, its first 2000 poses) accepted 13 wrong of 66,
        each tying trees 7-15 m apart in maps offset by their drift, consistent in pairs
        under marginals of metres; with the joint covariances 8 of 72."""
        estimates = self._slam.landmark_estimates()
        if len(estimates) == self._landmarks_matched:
            return []
        self._landmarks_matched = len(estimates)
        by_owner: dict[int, dict[int, np.ndarray]] = {}
        for landmark_id, point in estimates.items():
            owner = landmark_owner(landmark_id)
            if owner is not None:
                by_owner.setdefault(owner, {})[landmark_id] = point
        own = by_owner.pop(self._robot, {})
        accepted: list[tuple[int, int]] = []
        for teammate, theirs in sorted(by_owner.items()):
            held = self._held.setdefault(teammate, [])
            candidates = self._candidates(own, theirs, held)
            if not candidates:
                continue
            pairs = held + candidates
            offsets, covariance = self._offsets(pairs, estimates)
            consistent = pairwise_consistency(offsets, covariance, self._probability)
            within = offsets_within_gate(offsets, covariance, self._probability)
            eligible = [i for i in range(len(pairs)) if i < len(held) or within[i]]
            chosen = [eligible[k] for k in maximum_consistent_set(
                consistent[np.ix_(eligible, eligible)], range(len(held)))]
            new = [pairs[i] for i in chosen if i >= len(held)]
            if not held and len(new) < FIRST_CORRESPONDENCES:
                continue
            held.extend(new)
            accepted.extend(new)
        self._slam.add_landmark_correspondences(accepted)
        return accepted

    def _offsets(self, pairs: list[tuple[int, int]], estimates: dict[int, np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Offsets ``a - b`` ``(N, 2)`` [m] of the correspondences ``pairs`` and their joint
        covariance ``(2N, 2N)`` [m^2], from the joint marginals of every landmark in them."""
        landmarks = list(dict.fromkeys(landmark for pair in pairs for landmark in pair))
        column = {landmark: 2 * k for k, landmark in enumerate(landmarks)}
        selector = np.zeros((2 * len(pairs), 2 * len(landmarks)))
        for row, (a, b) in enumerate(pairs):
            selector[2 * row:2 * row + 2, column[a]:column[a] + 2] += np.eye(2)
            selector[2 * row:2 * row + 2, column[b]:column[b] + 2] -= np.eye(2)
        joint = self._slam.landmarks_joint_covariance(landmarks)
        offsets = np.array([estimates[a] - estimates[b] for a, b in pairs])
        return offsets, selector @ joint @ selector.T

    def _candidates(self, own: dict[int, np.ndarray], theirs: dict[int, np.ndarray],
                    held: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """Mutually nearest pairs (own id, teammate's id), untied, within the radius."""
        tied_own = {a for a, _ in held}
        tied_theirs = {b for _, b in held}
        free_own = {i: p for i, p in own.items() if i not in tied_own}
        free_theirs = {i: p for i, p in theirs.items() if i not in tied_theirs}
        if not free_own or not free_theirs:
            return []
        own_ids, own_points = list(free_own), np.array(list(free_own.values()))
        their_ids, their_points = list(free_theirs), np.array(list(free_theirs.values()))
        distances = np.linalg.norm(own_points[:, None] - their_points[None], axis=2)
        candidates = []
        for j, their_id in enumerate(their_ids):
            i = int(np.argmin(distances[:, j]))
            if distances[i, j] <= CORRESPONDENCE_RADIUS_M and int(np.argmin(distances[i])) == j:
                candidates.append((own_ids[i], their_id))
        return candidates
