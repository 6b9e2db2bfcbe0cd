"""Association of detections without identities (core/slam/association.py): the chi-square
gate, measurement Jacobians, JCBB against brute force, tentative tracks against clutter."""
import itertools
import math

import numpy as np
import pytest

from em_exploration_ros.core.geometry import wrap_angle
from em_exploration_ros.core.slam.association import (RobotMotion, ScanCompatibility,
                                                      ScanPrediction, TentativeTracks,
                                                      chi2_quantile,
                                                      detection_points, jcbb,
                                                      predict_measurements)

NOISE = np.diag([(math.radians(0.5) / 1.96) ** 2, (0.002 / 1.96) ** 2])


@pytest.mark.parametrize("dof, probability, value", [
    (2, 0.95, 5.991464547), (2, 0.99, 9.210340372), (4, 0.99, 13.27670414),
    (6, 0.95, 12.59158724), (10, 0.999, 29.58829845), (1, 0.95, 3.841458821),
    (3, 0.99, 11.34486673), (5, 0.99, 15.08627247), (7, 0.95, 14.06714045)])
def test_chi2_quantile_matches_the_tables(dof, probability, value):
    assert chi2_quantile(dof, probability) == pytest.approx(value, rel=1e-8)


def test_measurement_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    pose, points = np.array([1.0, -2.0, 0.7]), rng.uniform(-8, 8, (5, 2))
    predicted, pose_jacobian, point_jacobian = predict_measurements(pose, points)
    step = 1e-6
    for k in range(3):
        moved = pose.copy()
        moved[k] += step
        change = predict_measurements(moved, points)[0] - predicted
        change[:, 0] = wrap_angle(change[:, 0])
        np.testing.assert_allclose(change / step, pose_jacobian[:, :, k], atol=1e-5)
    for k in range(2):
        moved = points.copy()
        moved[:, k] += step
        change = predict_measurements(pose, moved)[0] - predicted
        change[:, 0] = wrap_angle(change[:, 0])
        np.testing.assert_allclose(change / step, point_jacobian[:, :, k], atol=1e-5)


def test_detection_points_invert_the_measurement_and_carry_its_covariance():
    rng = np.random.default_rng(1)
    pose = np.array([3.0, 4.0, -2.5])
    pose_covariance = np.diag([0.04, 0.01, 0.002])
    points = rng.uniform(-5, 5, (4, 2)) + pose[:2]
    measured = predict_measurements(pose, points)[0]
    back, covariances = detection_points(pose, pose_covariance, measured,
                                         np.repeat(NOISE[None], 4, axis=0))
    np.testing.assert_allclose(back, points, atol=1e-9)
    samples = 20000
    poses = rng.multivariate_normal(pose, pose_covariance, samples)
    noisy = measured[0] + rng.multivariate_normal(np.zeros(2), NOISE, samples)
    drawn = np.stack([poses[:, 0] + noisy[:, 1] * np.cos(poses[:, 2] + noisy[:, 0]),
                      poses[:, 1] + noisy[:, 1] * np.sin(poses[:, 2] + noisy[:, 0])], axis=1)
    np.testing.assert_allclose(np.cov(drawn, rowvar=False), covariances[0], rtol=0.1,
                               atol=1e-4)


def _prediction(rng, landmarks, pose_sigma=(0.05, 0.05, 0.01), point_sigma=0.05):
    pose = np.array([0.0, 0.0, 0.2])
    points = rng.uniform(-6, 6, (landmarks, 2))
    return ScanPrediction(pose, np.diag(np.square(pose_sigma)), points,
                          np.repeat(np.eye(2)[None] * point_sigma ** 2, landmarks, axis=0))


def test_the_individual_gate_is_the_mahalanobis_distance_under_the_marginals():
    rng = np.random.default_rng(2)
    prediction = _prediction(rng, 3)
    predicted, pose_jacobian, point_jacobian = predict_measurements(prediction.pose,
                                                                    prediction.points)
    measured = predicted[[1]] + np.array([[0.01, -0.03]])
    compatibility = ScanCompatibility(prediction, measured, NOISE[None])
    covariance = (pose_jacobian[1] @ prediction.pose_covariance @ pose_jacobian[1].T
                  + point_jacobian[1] @ prediction.point_covariances[1] @ point_jacobian[1].T
                  + NOISE)
    innovation = np.array([0.01, -0.03])
    assert compatibility.nis[0, 1] == pytest.approx(
        innovation @ np.linalg.solve(covariance, innovation))
    # One sigma of the innovation along each axis is in the 99 % gate, four are not.
    sigma = np.sqrt(np.diag(covariance))
    for multiple, inside in ((1.0, True), (4.0, False)):
        off = ScanCompatibility(prediction, predicted[[1]] + multiple * sigma, NOISE[None])
        assert (off.nis[0, 1] <= chi2_quantile(2, 0.99)) == inside
        assert jcbb(off, 0.99)[0] == (1 if inside else None)


def _brute_force(compatibility: ScanCompatibility, probability: float):
    """Every hypothesis whose pairings are individually compatible, distinct and jointly
    compatible at every pairing in detection order (JCBB's search space); the one with the
    most pairings, then the lowest joint NIS."""
    gate = chi2_quantile(2, probability)
    options = [[None] + [landmark for landmark in range(compatibility.num_landmarks)
                         if compatibility.nis[d, landmark] <= gate]
               for d in range(compatibility.num_detections)]
    best, best_key = None, None
    for hypothesis in itertools.product(*options):
        pairs = [(d, landmark) for d, landmark in enumerate(hypothesis) if landmark is not None]
        if len({landmark for _, landmark in pairs}) < len(pairs):
            continue
        if any(compatibility.joint_nis(pairs[:k]) > chi2_quantile(2 * k, probability)
               for k in range(1, len(pairs) + 1)):
            continue
        key = (-len(pairs), compatibility.joint_nis(pairs))
        if best_key is None or key < best_key:
            best, best_key = hypothesis, key
    return tuple(best)


def test_jcbb_finds_what_brute_force_finds_on_small_random_scans():
    rng = np.random.default_rng(3)
    checked_ambiguous = 0
    for _ in range(300):
        landmarks, detections = rng.integers(1, 5), rng.integers(1, 5)
        # Landmarks close together and a loose pose: many individually compatible pairs.
        prediction = _prediction(rng, landmarks, pose_sigma=(0.3, 0.3, 0.05), point_sigma=0.2)
        prediction = ScanPrediction(prediction.pose, prediction.pose_covariance,
                                    rng.uniform(2, 4, (landmarks, 2)),
                                    prediction.point_covariances)
        truth = rng.integers(0, landmarks, detections)
        predicted = predict_measurements(prediction.pose, prediction.points)[0]
        measured = predicted[truth] + rng.normal(0, [0.05, 0.3], (detections, 2))
        compatibility = ScanCompatibility(prediction, measured,
                                          np.repeat(NOISE[None], detections, axis=0))
        answer = jcbb(compatibility, 0.99)
        assert answer == _brute_force(compatibility, 0.99)
        gate = chi2_quantile(2, 0.99)
        checked_ambiguous += int(((compatibility.nis <= gate).sum(axis=1) > 1).any())
    assert checked_ambiguous > 50


def test_jcbb_pairs_a_scan_with_clutter_as_it_was_made():
    rng = np.random.default_rng(4)
    correct = total = 0
    for _ in range(100):
        prediction = _prediction(rng, 6)
        true_pose = rng.multivariate_normal(prediction.pose, prediction.pose_covariance)
        true_points = prediction.points + rng.normal(0, 0.05, prediction.points.shape)
        seen = rng.permutation(6)[:4]
        measured = predict_measurements(true_pose, true_points[seen])[0]
        measured += rng.multivariate_normal(np.zeros(2), NOISE, len(seen))
        clutter = np.stack([rng.uniform(-np.pi, np.pi, 2), rng.uniform(0, 7.5, 2)], axis=1)
        scan = np.concatenate([measured, clutter])
        answer = jcbb(ScanCompatibility(prediction, scan, np.repeat(NOISE[None], 6, axis=0)),
                      0.99)
        expected = (*[int(landmark) for landmark in seen], None, None)
        correct += sum(a == e for a, e in zip(answer, expected))
        total += len(expected)
    assert correct / total >= 0.97


def test_tentative_tracks_confirm_a_landmark_and_never_clutter():
    rng = np.random.default_rng(5)
    tracks = TentativeTracks(confirm_hits=3, window_keyframes=5, gate_probability=0.99)
    landmark = np.array([4.0, 1.0])
    covariance = np.eye(2) * 0.02 ** 2
    confirmed_landmark, confirmed_clutter = [], 0
    for index in range(200):
        points = [rng.uniform(-7.5, 7.5, 2) for _ in range(rng.poisson(3.0))]
        seen = rng.random() < 0.8 and not confirmed_landmark
        if seen:
            points.append(landmark + rng.normal(0, 0.02, 2))
        if not points:
            continue
        answer = [confirmed is not None for confirmed in tracks.observe(
            index, np.array(points), np.repeat(covariance[None], len(points), axis=0))]
        if seen and answer[-1]:
            confirmed_landmark.append(index)
        confirmed_clutter += sum(answer[:-1] if seen else answer)
    assert len(confirmed_landmark) == 1 and confirmed_landmark[0] <= 6
    assert confirmed_clutter == 0
    assert len(tracks) <= 5 * 4  # only the last window's clutter is held


def test_a_track_is_dropped_when_not_seen_within_the_window():
    tracks = TentativeTracks(confirm_hits=2, window_keyframes=3, gate_probability=0.99)
    point, covariance = np.array([[1.0, 1.0]]), np.eye(2)[None] * 1e-4
    assert tracks.observe(0, point, covariance) == [None]
    assert tracks.observe(3, np.zeros((0, 2)), np.zeros((0, 2, 2))) == []
    assert len(tracks) == 0
    assert tracks.observe(4, point, covariance, ["at 4"]) == [None]
    assert tracks.observe(6, point, covariance, ["at 6"]) == [("at 4",)]
    assert len(tracks) == 0
    with pytest.raises(ValueError):
        TentativeTracks(confirm_hits=4, window_keyframes=3, gate_probability=0.99)


def test_a_confirmed_track_hands_back_its_earlier_sightings():
    """What the caller gave with each sighting comes back, oldest first, with the detection
    that confirms the track: the caller names those sightings' landmark too."""
    tracks = TentativeTracks(confirm_hits=3, window_keyframes=5, gate_probability=0.99)
    point, covariance = np.array([[2.0, 1.0]]), np.eye(2)[None] * 1e-4
    clutter = np.array([[-5.0, 3.0]])
    assert tracks.observe(0, point, covariance, ["a0"]) == [None]
    assert tracks.observe(1, clutter, covariance, ["c1"]) == [None]
    assert tracks.observe(2, np.vstack([clutter * -1, point]),
                                    np.repeat(covariance, 2, axis=0), ["c2", "a2"]) == [None, None]
    assert tracks.observe(4, point, covariance, ["a4"]) == [("a0", "a2")]
    assert len(tracks) == 2  # the two clutter tracks, not the confirmed one
    assert tracks.observe(5, point, covariance) == [None]  # a new track starts


def test_a_track_needs_the_fewest_confirmations_any_of_its_sightings_asked_for():
    """A loop closure's detection asks for fewer sightings (``loop_closure_confirm_hits``)
    than a new landmark's: its track confirms at its second sighting, another at its
    third."""
    tracks = TentativeTracks(confirm_hits=3, window_keyframes=5, gate_probability=0.99)
    points, covariances = np.array([[2.0, 1.0], [-4.0, 3.0]]), np.repeat(
        np.eye(2)[None] * 1e-4, 2, axis=0)
    assert tracks.observe(0, points, covariances, ["loop 0", "new 0"], [3, 3]) == [None, None]
    assert tracks.observe(1, points, covariances, ["loop 1", "new 1"], [2, 3]) == [
        ("loop 0",), None]
    assert tracks.observe(2, points[1:], covariances[1:], ["new 2"]) == [("new 0", "new 1")]
    assert len(tracks) == 0


def test_a_track_s_gate_holds_the_robot_s_motion_since_that_track_was_last_seen():
    """Tracks A (last seen at keyframe 0) and B (at 2) are 0.7 m from this keyframe's
    detections (keyframe 3). The robot's motion adds 0.04 m^2 per axis and keyframe since:
    A's gate holds three keyframes of it (0.7 m is 2.0 sigma: a sighting), B's one (3.5
    sigma: a new track). A gate widened by the whole window for both took both."""
    tracks = TentativeTracks(confirm_hits=3, window_keyframes=5, gate_probability=0.99)
    a, b = np.array([[0.0, 5.0]]), np.array([[10.0, 5.0]])
    covariance = np.eye(2)[None] * 1e-4
    asked = []

    def motion_since(since):
        asked.append(since)
        return np.diag([0.04, 0.04, 0.0]) * (3 - since)

    assert tracks.observe(0, a, covariance, ["a0"]) == [None]
    assert tracks.observe(2, b, covariance, ["b2"]) == [None]
    moved_away = np.vstack([a + [0.7, 0.0], b + [0.7, 0.0]])
    motion = RobotMotion(np.array([5.0, 0.0, 0.0]), motion_since)
    assert tracks.observe(3, moved_away, np.repeat(covariance, 2, axis=0), ["a3", "b3"],
                          motion=motion) == [None, None]
    assert sorted(asked) == [0, 2]
    assert len(tracks) == 3  # A seen twice now, B once, and the new track at B + 0.7 m
    assert tracks.observe(4, a + [0.7, 0.0], covariance, ["a4"]) == [("a0", "a3")]
