"""Landmarks without identities (issue 38, points 2 and 3): a robot pairs its own detections
(JCBB, tentative tracks) with landmark numbers of its own, ties teammates' landmarks to its
own only when pairwise consistent (PCM), and the truth side counts the outcome."""
import dataclasses
import itertools
import logging
from dataclasses import dataclass

import numpy as np
import pytest

from em_exploration_ros.core.evaluation.association_stats import (AssociationCounts,
                                                                  association_line,
                                                                  association_summary,
                                                                  robot_association,
                                                                  team_association)
from em_exploration_ros.core.params import ExplorationParams, SlamParams
from em_exploration_ros.core.records.readings import (UNIDENTIFIED, KeyframeMeasurements,
                                                      LandmarkReading, LateReading,
                                                      TeammateReading)
from em_exploration_ros.core.slam.association import (maximum_consistent_set,
                                                      offsets_within_gate,
                                                      pairwise_consistency)
from em_exploration_ros.core.slam.own_landmarks import OwnLandmarks
from em_exploration_ros.core.slam.team_slam import (OWNED_LANDMARK_STRIDE, KeyframeBuilder,
                                                    TeamSlam, landmark_owner,
                                                    owned_landmark_id)
from em_exploration_ros.core.world.sensors import CLUTTER, SensorSimulator
from em_exploration_ros.core.world.world import (advance_robot, generate_world,
                                                 run_seed_sequences)

SENSING = {"landmark_ids": False, "detection_probability": 0.8, "clutter_rate": 1.5}


def test_owned_landmark_ids_are_distinct_per_robot_and_fit_the_messages():
    assert owned_landmark_id(0, 0) == OWNED_LANDMARK_STRIDE
    assert landmark_owner(owned_landmark_id(25, 7)) == 25 and landmark_owner(19) is None
    assert owned_landmark_id(25, OWNED_LANDMARK_STRIDE - 1) < 2 ** 31 - 1
    with pytest.raises(ValueError):
        owned_landmark_id(0, OWNED_LANDMARK_STRIDE)


def _keyframe(robot, index, landmarks, teammates=(), previous=None, delta=(0.0, 0.0, 0.0)):
    return KeyframeMeasurements(
        robot_id=robot, index=index, stamp_s=float(index), is_first=previous is None,
        previous_index=-1 if previous is None else previous, odom_delta=np.array(delta),
        odom_covariance=np.eye(3) * 1e-6, landmarks=tuple(landmarks), teammates=teammates)


def test_the_graph_keeps_each_robot_s_landmarks_apart_until_tied():
    slam = TeamSlam(0, 2, SlamParams(), np.zeros(3), landmark_ids=False)
    seen = LandmarkReading(0, 5.0, 0.0, 1e-2, 1e-3)  # loose: the tie decides
    slam.add_keyframe(_keyframe(0, 0, [seen], [TeammateReading(
        1, np.array([0.0, 1.0, 0.0]), np.eye(3) * 1e-6)]))
    slam.add_keyframe(_keyframe(1, 0, [LandmarkReading(0, 5.3, -0.2, 1e-2, 1e-3)]))
    slam.update()
    own, theirs = owned_landmark_id(0, 0), owned_landmark_id(1, 0)
    estimates = slam.landmark_estimates()
    assert sorted(estimates) == [own, theirs]
    assert np.linalg.norm(estimates[own] - estimates[theirs]) > 0.05
    slam.add_landmark_correspondences([(own, theirs)])
    estimates = slam.landmark_estimates()
    assert np.linalg.norm(estimates[own] - estimates[theirs]) < 0.02
    assert slam.landmark_correspondences == [(own, theirs)]
    assert [r[:3] for r in slam.landmark_readings()] == [(0, 0, own), (1, 0, theirs)]


@pytest.mark.parametrize("cauchy_k, pull_range_m", [(0.0, (0.4, 1.0)), (4.0, (0.0, 0.05))])
def test_a_wrong_reading_pulls_an_associated_landmark_less_under_the_cauchy_loss(
        cauchy_k, pull_range_m):
    """Without identities a robot's own readings may be wrong: four keyframes read a
    landmark at (5, 0), a fifth one 3 m off is tied to it. Under a Gaussian loss the wrong
    reading drags the landmark about 0.57 m; under the Cauchy loss of ``landmark_cauchy_k``
    (4) a few centimetres."""
    params = SlamParams(landmark_cauchy_k=cauchy_k)
    slam = TeamSlam(0, 1, params, np.zeros(3), landmark_ids=False)
    for index in range(5):
        bearing, range_m = (0.0, 5.0) if index < 4 else (np.arctan2(3.0, 5.0), np.hypot(5, 3))
        slam.add_keyframe(_keyframe(0, index, [LandmarkReading(0, range_m, bearing, 1e-2, 1e-3)],
                                    previous=None if index == 0 else index - 1))
        slam.update()
    slam.converge()
    pull = np.linalg.norm(slam.landmark_estimates()[owned_landmark_id(0, 0)] - [5.0, 0.0])
    assert pull_range_m[0] <= pull <= pull_range_m[1]


def test_a_late_reading_of_a_keyframe_not_in_the_graph_is_left_out_with_a_warning(caplog):
    """Only a forged record names an earlier keyframe the graph does not hold (here 1, which
    the stream skipped): its reading is left out, and said so."""
    slam = TeamSlam(0, 1, SlamParams(), np.zeros(3), landmark_ids=False)
    slam.add_keyframe(_keyframe(0, 0, []))
    seen = LandmarkReading(0, 5.0, 0.0, 1e-4, 1e-5)
    slam.add_keyframe(dataclasses.replace(
        _keyframe(0, 2, [seen], previous=0),
        late_landmarks=(LateReading(1, seen), LateReading(0, seen))))
    with caplog.at_level(logging.WARNING):
        slam.update()
    assert [r[:3] for r in slam.landmark_readings()] == [(0, 2, owned_landmark_id(0, 0)),
                                                         (0, 0, owned_landmark_id(0, 0))]
    assert ("robot 0's keyframe 2: 1 late reading(s) of its keyframe(s) [1], which are not "
            "in the graph, left out") in caplog.text


@dataclass
class _Run:
    slams: list
    associators: list
    scans: dict
    interval: int
    num_landmarks: int


def _explore(seed: int, steps: int, sensing=SENSING) -> _Run:
    """A team driving circles, each robot associating its own detections and sharing its
    keyframes with every teammate at once; the truth of every keyframe scan kept aside."""
    params = ExplorationParams().replace(sensors=sensing)
    world_sequence, sensor_sequence = run_seed_sequences(seed)
    world = generate_world(params.world, params.sensors, world_sequence)
    sensors = SensorSimulator(world, params.sensors, params.motion, sensor_sequence)
    n = world.num_robots
    slams = [TeamSlam(r, n, params.slam, world.start_poses[0], landmark_ids=False)
             for r in range(n)]
    associators = [OwnLandmarks(slam, params.sensors) for slam in slams]
    builders = [KeyframeBuilder(r, params.slam, keep_unidentified=True) for r in range(n)]
    poses = np.array(world.start_poses, dtype=float)
    forward = params.motion.speed_mps * params.motion.time_step_s
    interval = params.slam.keyframe_interval_steps
    scans = {}
    for step in range(steps + 1):
        odometry = [None] * n
        if step > 0:
            previous = poses.copy()
            for r in range(n):
                poses[r], _ = advance_robot(world, previous[r], 0.015 if r % 2 else -0.015,
                                            forward, params.motion)
                odometry[r] = sensors.odometry(r, previous[r], poses[r])
        for r in range(n):
            sonar, mates = [], []
            if step % interval == 0:
                sonar, sources = sensors.sonar_scan(r, poses[r])
                scans[r, step] = (tuple(sonar), sources)
                mates = sensors.teammates(r, poses)
            keyframe = builders[r].add_step(step, step * 0.2, odometry[r], sonar, mates)
            if keyframe is None:
                continue
            keyframe = associators[r].associate(keyframe)
            for slam in slams:
                slam.add_keyframe(keyframe)
        if step % interval == 0:
            for r in range(n):
                slams[r].update()
                associators[r].match_teammates()
    return _Run(slams, associators, scans, interval, world.num_landmarks)


@pytest.fixture(scope="module")
def explored() -> _Run:
    return _explore(seed=3, steps=900)


def test_own_detections_are_associated_rightly_despite_misses_and_clutter(explored):
    summary = team_association(explored.slams, explored.scans, explored.interval)
    print(association_line(summary))
    assert summary["precision"] >= 0.99
    assert summary["recall"] >= 0.9  # a track's first sightings are named when it is confirmed
    assert summary["spurious_landmarks"] == 0
    for robot in summary["robots"]:
        assert robot["correct"] > 20
    assert summary["correspondences_correct"] >= 1 and summary["correspondences_wrong"] == 0


def test_a_new_landmark_carries_its_first_sightings_as_late_readings(explored):
    """Each own landmark's first readings in the graph are of the keyframes before it was
    confirmed (its track's sightings), attached when the keyframe that confirmed it came."""
    for slam in explored.slams:
        first_seen: dict[int, list[int]] = {}
        for robot, index, landmark, _, _ in slam.landmark_readings():
            if robot == slam.robot_id:
                first_seen.setdefault(landmark, []).append(index)
        assert first_seen
        for indices in first_seen.values():
            # the keyframe that confirmed the landmark added it first, then the track's
            # earlier sightings (at least confirm_hits - 1 = 2), all before it
            confirming = indices[0]
            assert len(indices) >= 3 and indices[1] < confirming and indices[2] < confirming


def test_every_readings_id_is_the_robot_s_own(explored):
    for slam in explored.slams:
        for robot, _, landmark, _, _ in slam.landmark_readings():
            assert landmark_owner(landmark) == robot


def test_an_unanchored_robot_leaves_its_detections_out():
    slam = TeamSlam(1, 2, SlamParams(), np.zeros(3), landmark_ids=False)
    associator = OwnLandmarks(slam, ExplorationParams().sensors)
    keyframe = _keyframe(1, 0, [LandmarkReading(UNIDENTIFIED, 3.0, 0.1, 1e-6, 1e-6)])
    assert associator.associate(keyframe).landmarks == ()


_LANDMARK = LandmarkReading(UNIDENTIFIED, 5.0, 0.0, 1e-4, 1e-5)  # at (5, 0) from the origin
_STILL, _DRIVING = np.eye(3) * 1e-8, np.diag([0.02, 0.02, 1e-6])
#: Keyframe 0 anchors; 1-3 map the landmark; 4-17 drive 14 m out and back along y (about
#: 0.5 m of drift per axis in the marginal at the end).
_MAP_AND_RETURN = ([((0.0, 0.0), _STILL, [])] + [((0.0, 0.0), _STILL, [_LANDMARK])] * 3
                   + [((0.0, 2.0), _DRIVING, [])] * 7 + [((0.0, -2.0), _DRIVING, [])] * 7)


def _reading_at(x: float, y: float) -> LandmarkReading:
    return LandmarkReading(UNIDENTIFIED, float(np.hypot(x, y)), float(np.arctan2(y, x)),
                           1e-4, 1e-5)


def _drive(slam, associator, plan, first_index=0, before=None):
    """Robot 0's keyframes from ``plan`` (odometry delta (x, y), its covariance, readings),
    each associated, added and updated; ``before(index)`` is called before each. Returns
    the associated keyframes."""
    named = []
    for index, (delta, covariance, readings) in enumerate(plan, start=first_index):
        if before is not None:
            before(index)
        keyframe = associator.associate(KeyframeMeasurements(
            robot_id=0, index=index, stamp_s=float(index), is_first=index == 0,
            previous_index=index - 1, odom_delta=np.array([*delta, 0.0]),
            odom_covariance=covariance, landmarks=tuple(readings), teammates=()))
        named.append(keyframe)
        slam.add_keyframe(keyframe)
        slam.update()
    return named


def test_a_loop_closure_waits_for_its_track_so_clutter_in_its_wide_gate_is_not_named():
    """A landmark not seen for more than ``RECENT_KEYFRAMES`` keyframes is gated on the
    marginals, wide after an excursion. A robot maps a landmark at (5, 0), drives 14 m out
    and back, waits where the landmark is missed, then sees a clutter point 1 m from it
    (inside that gate) and the landmark itself at the next three keyframes. The clutter
    point is never named; the landmark's re-sighting names the old landmark once its track
    was seen twice (``loop_closure_confirm_hits``), the first sighting as a late reading,
    and the third at once (the landmark is recent again); no new landmark is made."""
    slam = TeamSlam(0, 1, SlamParams(), np.zeros(3), landmark_ids=False)
    associator = OwnLandmarks(slam, ExplorationParams().sensors)
    mapped, gate = owned_landmark_id(0, 0), []

    def gate_at_the_clutter(index):
        if index == 24:
            gate.append(slam.landmark_covariance(mapped)
                        + slam.pose_covariance(0, index - 1)[:2, :2])

    plan = (_MAP_AND_RETURN + [((0.0, 0.0), _STILL, [])] * 6  # 18-23: the landmark missed
            + [((0.0, 0.0), _STILL, [_reading_at(5.8, 0.6)])]  # 24: clutter in the gate
            + [((0.0, 0.0), _STILL, [_LANDMARK])] * 3)         # 25-27: seen again
    named = _drive(slam, associator, plan, before=gate_at_the_clutter)
    assert [r.landmark_id for r in named[3].landmarks] == [0]
    offset = np.array([0.8, 0.6])
    assert offset @ np.linalg.solve(gate[0], offset) < 9.21  # inside the 0.99 gate
    assert all(named[i].landmarks == () for i in range(4, 26))
    assert [r.landmark_id for r in named[26].landmarks] == [0]
    assert [(late.keyframe_index, late.reading.landmark_id)
            for late in named[26].late_landmarks] == [(25, 0)]
    assert [r.landmark_id for r in named[27].landmarks] == [0]
    assert named[27].late_landmarks == ()
    assert list(slam.landmark_estimates()) == [mapped]
    assert [r[1] for r in slam.landmark_readings()] == [3, 1, 2, 26, 25, 27]


def test_a_track_does_not_name_a_landmark_another_reading_of_its_keyframe_names():
    """One scan sees a landmark once. After the excursion a point 1 m from the mapped
    landmark (inside its wide gate: paired with it, waiting) is seen at keyframe 24, the
    landmark itself at 25, both at 26 and 27. At 26 both tracks are confirmed, the point's
    with its first sighting paired with the landmark: the landmark's own track names it, and
    the point's a new landmark, not the same one again (before, keyframe 26 held two
    readings of landmark 0 from one pose, and the point's earlier one as a late reading of
    it; Victoria Park had two such keyframes in 3332). At 27 each is recent and paired at
    once."""
    slam = TeamSlam(0, 1, SlamParams(), np.zeros(3), landmark_ids=False)
    associator = OwnLandmarks(slam, ExplorationParams().sensors)
    point = _reading_at(5.8, 0.6)
    plan = (_MAP_AND_RETURN + [((0.0, 0.0), _STILL, [])] * 6  # 18-23: the landmark missed
            + [((0.0, 0.0), _STILL, [point]), ((0.0, 0.0), _STILL, [_LANDMARK])]  # 24, 25
            + [((0.0, 0.0), _STILL, [_LANDMARK, point])] * 2)                    # 26, 27
    named = _drive(slam, associator, plan)
    assert named[24].landmarks == named[25].landmarks == ()
    assert [r.landmark_id for r in named[26].landmarks] == [0, 1]
    assert [(late.keyframe_index, late.reading.landmark_id)
            for late in named[26].late_landmarks] == [(25, 0), (24, 1)]
    assert [r.landmark_id for r in named[27].landmarks] == [0, 1]
    assert sorted(slam.landmark_estimates()) == [owned_landmark_id(0, 0),
                                                 owned_landmark_id(0, 1)]


def test_a_restarted_robot_gates_the_landmarks_of_its_journal_on_the_marginals():
    """A restarted robot's association starts afresh over the graph its journal rebuilt:
    it does not know when it last saw a landmark. Gated as if seen just before (the
    sonar's noise alone), a landmark re-seen 0.5 m off after the excursion was made anew
    (a duplicate); gated on the marginals, it is the old one, named once its track was
    seen twice."""
    slam = TeamSlam(0, 1, SlamParams(), np.zeros(3), landmark_ids=False)
    _drive(slam, OwnLandmarks(slam, ExplorationParams().sensors), _MAP_AND_RETURN)
    restarted = OwnLandmarks(slam, ExplorationParams().sensors)
    named = _drive(slam, restarted, [((0.0, 0.0), _STILL, [_reading_at(5.4, 0.3)])] * 3,
                   first_index=len(_MAP_AND_RETURN))
    assert named[0].landmarks == ()
    assert [r.landmark_id for r in named[1].landmarks] == [0]
    assert [late.keyframe_index for late in named[1].late_landmarks] == [18]
    assert [r.landmark_id for r in named[2].landmarks] == [0]
    assert list(slam.landmark_estimates()) == [owned_landmark_id(0, 0)]


def test_a_recent_landmark_s_gate_turns_with_the_robot():
    """The gate of a landmark seen lately holds the odometry's errors since then, which are
    in the robot's body frame: heading along map y, the robot's along-track error is along
    map y. A robot facing +y maps a landmark 7 m ahead, then drives 4 keyframes with an
    odometry of 1 m each (0.3 m along-track sigma, little across) that were 1.3 m: the
    landmark re-seen 1.2 m nearer is inside its 0.6 m gate and named. Gated as if those
    errors were along map x (not turned), it was 4 sigma off and refused."""
    facing_y = np.array([0.0, 0.0, np.pi / 2])
    slam = TeamSlam(0, 1, SlamParams(), facing_y, landmark_ids=False)
    associator = OwnLandmarks(slam, ExplorationParams().sensors)
    ahead = LandmarkReading(UNIDENTIFIED, 7.0, 0.0, 1e-4, 1e-5)  # at (0, 7)
    along_track = np.diag([0.09, 1e-6, 1e-8])
    nearer = LandmarkReading(UNIDENTIFIED, 7.0 - 4 * 1.3, 0.0, 1e-4, 1e-5)
    plan = ([((0.0, 0.0), _STILL, [])] + [((0.0, 0.0), _STILL, [ahead])] * 3
            + [((1.0, 0.0), along_track, [])] * 3 + [((1.0, 0.0), along_track, [nearer])])
    named = _drive(slam, associator, plan)
    assert [r.landmark_id for r in named[3].landmarks] == [0]
    assert [r.landmark_id for r in named[7].landmarks] == [0]
    assert list(slam.landmark_estimates()) == [owned_landmark_id(0, 0)]


class _FakeSlam:
    """The parts of TeamSlam that match_teammates uses, with landmarks placed by hand: each
    with ``sigma_m`` of its own, and the teammate's with ``drift_m`` in common (their map's
    offset against this robot's, as a graph's joint marginals hold it)."""

    def __init__(self, points: dict[int, tuple[float, float]], sigma_m: float,
                 drift_m: float = 0.0) -> None:
        self.robot_id = 0
        self.slam_params = SlamParams()
        self.points = {i: np.array(p, dtype=float) for i, p in points.items()}
        self.sigma_m = sigma_m
        self.drift_m = drift_m
        self.landmark_correspondences: list[tuple[int, int]] = []

    def landmark_estimates(self):
        return dict(self.points)

    def landmarks_joint_covariance(self, landmark_ids):
        theirs = np.array([landmark_owner(i) != self.robot_id for i in landmark_ids], float)
        per_landmark = (np.eye(len(landmark_ids)) * self.sigma_m ** 2
                        + np.outer(theirs, theirs) * self.drift_m ** 2)
        return np.kron(per_landmark, np.eye(2))

    def add_landmark_correspondences(self, pairs):
        self.landmark_correspondences.extend(pairs)


def _own(n):
    return owned_landmark_id(0, n)


def _theirs(n):
    return owned_landmark_id(1, n)


def test_a_planted_wrong_correspondence_is_rejected_and_true_ones_kept():
    """The teammate's map is offset by 0.6 m (drift, 0.5 m sigma in the graph); its
    landmark 3 is a wrong one 1.2 m from own landmark 3 the other way: each pair alone is
    within the radius and the gate, only the wrong one disagrees with the others' offset."""
    offset = np.array([0.6, 0.0])
    own = {_own(k): (10.0 * k, 20.0) for k in range(4)}
    theirs = {_theirs(k): tuple(np.array(own[_own(k)]) + offset) for k in range(3)}
    theirs[_theirs(3)] = tuple(np.array(own[_own(3)]) + [-0.6, 1.0])
    slam = _FakeSlam({**own, **theirs}, sigma_m=0.05, drift_m=0.5)
    associator = OwnLandmarks(slam, ExplorationParams().sensors)
    accepted = associator.match_teammates()
    assert sorted(accepted) == [(_own(k), _theirs(k)) for k in range(3)]
    # Later, a new wrong candidate is checked against the correspondences held: rejected;
    # a new true one is kept.
    slam.points[_own(4)] = np.array([40.0, 20.0])
    slam.points[_theirs(4)] = np.array([40.0, 20.0]) + offset
    slam.points[_own(5)] = np.array([50.0, 20.0])
    slam.points[_theirs(5)] = np.array([50.0, 20.0]) - offset
    assert associator.match_teammates() == [(_own(4), _theirs(4))]
    assert (_own(3), _theirs(3)) not in slam.landmark_correspondences


def test_a_single_candidate_waits_for_a_second_consistent_one():
    slam = _FakeSlam({_own(0): (5.0, 5.0), _theirs(0): (5.2, 5.0)}, sigma_m=0.05,
                     drift_m=0.5)
    associator = OwnLandmarks(slam, ExplorationParams().sensors)
    assert associator.match_teammates() == []
    slam.points[_own(1)] = np.array([15.0, 5.0])
    slam.points[_theirs(1)] = np.array([15.2, 5.0])
    assert sorted(associator.match_teammates()) == [(_own(0), _theirs(0)),
                                                    (_own(1), _theirs(1))]


def test_the_maximum_consistent_set_is_the_largest_clique():
    rng = np.random.default_rng(0)
    for _ in range(50):
        size = rng.integers(1, 9)
        graph = rng.random((size, size)) < 0.6
        graph = graph & graph.T
        np.fill_diagonal(graph, True)
        chosen = maximum_consistent_set(graph)
        assert all(graph[i, j] for i in chosen for j in chosen)
        largest = max(len(c) for k in range(1, size + 1)
                      for c in itertools.combinations(range(size), k)
                      if all(graph[i, j] for i in c for j in c))
        assert len(chosen) == largest
    graph = np.ones((3, 3), dtype=bool)
    graph[0, 2] = graph[2, 0] = False
    assert maximum_consistent_set(graph, required=[2]) == [1, 2]


def test_pairwise_consistency_cancels_a_common_offset():
    a = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    b = a + [1.0, -0.5]
    covariance = np.kron(np.eye(3), np.eye(2) * 2 * 0.01 ** 2)  # a's and b's, independent
    assert pairwise_consistency(a - b, covariance, 0.99).all()
    b[2] += [0.3, 0.0]
    consistent = pairwise_consistency(a - b, covariance, 0.99)
    assert consistent[0, 1] and not consistent[0, 2] and not consistent[1, 2]


def test_a_drift_common_to_the_offsets_widens_each_gate_and_cancels_between_them():
    """Offsets of 1.1 m under a common drift of 1 m sigma (the joint covariance): each is
    within its own gate, and two that differ by 0.3 m are not consistent (the drift
    cancels); without the drift each offset is outside its gate."""
    offsets = np.array([[1.0, -0.5], [1.0, -0.5], [1.3, -0.5]])
    own = np.kron(np.eye(3), np.eye(2) * 2 * 0.01 ** 2)
    drifted = own + np.kron(np.ones((3, 3)), np.eye(2))
    assert offsets_within_gate(offsets, drifted, 0.99).all()
    assert not offsets_within_gate(offsets, own, 0.99).any()
    consistent = pairwise_consistency(offsets, drifted, 0.99)
    assert consistent[0, 1] and not consistent[0, 2] and not consistent[1, 2]


def test_association_counts_against_truth():
    """Robot 0's graph: landmark A from true 4 (two readings right, one of clutter), B
    from clutter (spurious, its two readings wrong), C from true 4 again (its reading right,
    the landmark a spurious duplicate); a detection of true 9 left out (missed)."""
    def reading(bearing):
        return LandmarkReading(UNIDENTIFIED, 3.0, bearing, 1e-6, 1e-6)
    scans = {(0, 0): ((reading(0.1), reading(0.2), reading(0.3)), (4, 9, CLUTTER)),
             (0, 10): ((reading(0.4), reading(0.5)), (4, CLUTTER)),
             (0, 20): ((reading(0.6), reading(0.7)), (4, CLUTTER))}
    a, b, c, theirs = _own(0), _own(1), _own(2), _theirs(0)
    readings = [(0, 0, a, 0.1, 3.0), (0, 0, a, 0.3, 3.0), (0, 1, a, 0.4, 3.0),
                (0, 1, b, 0.5, 3.0), (0, 2, c, 0.6, 3.0), (0, 2, b, 0.7, 3.0),
                (1, 0, theirs, 0.1, 3.0)]
    scans[1, 0] = scans[0, 0]
    counts = robot_association(0, readings, [0, 1, 2], [(a, theirs), (b, theirs)], scans,
                               10)
    assert counts == AssociationCounts(correct=3, wrong=3, missed=1, true_detections=4,
                                       spurious_landmarks=2, correspondences_correct=1,
                                       correspondences_wrong=1)
    assert counts.precision == pytest.approx(4 / 8) and counts.recall == pytest.approx(3 / 4)
    summary = association_summary([counts, AssociationCounts()])
    assert summary["correct"] == 3 and len(summary["robots"]) == 2
    assert 0.0 <= summary["precision"] <= 1.0 and 0.0 <= summary["recall"] <= 1.0
