"""SE(2) helpers: wrapping, composition identities, point transforms, Jacobians."""
import gtsam
import numpy as np
import pytest

from em_exploration_ros.core.geometry import (between, compose, compose_jacobians,
                                              coordinate_to_body_covariance, inverse,
                                              inverse_jacobian,
                                              inverse_transform_points, range_bearing,
                                              transform_points, wrap_angle)


def _random_poses(rng: np.random.Generator, count: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-20, 20, (count, 2)), rng.uniform(-np.pi, np.pi, count)])


def _matrix(pose: np.ndarray) -> np.ndarray:
    """Homogeneous 3x3 transform of a pose (independent reference for composition)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def test_wrap_angle_hand_values_and_half_open_interval() -> None:
    values = np.array([0.5, np.pi, -np.pi, 3 * np.pi, -3 * np.pi / 2, 2 * np.pi, -7.0])
    expected = np.array([0.5, np.pi, np.pi, np.pi, np.pi / 2, 0.0, -7.0 + 2 * np.pi])
    np.testing.assert_allclose(wrap_angle(values), expected, atol=1e-12)
    many = np.random.default_rng(0).uniform(-50, 50, 10000)
    wrapped = wrap_angle(many)
    assert np.all(wrapped > -np.pi) and np.all(wrapped <= np.pi)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(many), atol=1e-9)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(many), atol=1e-9)
    assert wrap_angle(np.zeros((2, 3))).shape == (2, 3)


def test_compose_matches_homogeneous_matrices() -> None:
    rng = np.random.default_rng(1)
    a, b = _random_poses(rng, 50), _random_poses(rng, 50)
    c = compose(a, b)
    for ai, bi, ci in zip(a, b, c):
        product = _matrix(ai) @ _matrix(bi)
        np.testing.assert_allclose(_matrix(ci), product, atol=1e-9)


def test_compose_between_inverse_identities() -> None:
    rng = np.random.default_rng(2)
    a, b = _random_poses(rng, 100), _random_poses(rng, 100)
    np.testing.assert_allclose(between(a, compose(a, b)), b, atol=1e-9)
    np.testing.assert_allclose(compose(a, between(a, b)), b, atol=1e-9)
    np.testing.assert_allclose(compose(a, inverse(a)), np.zeros_like(a), atol=1e-9)
    np.testing.assert_allclose(inverse(inverse(a)), a, atol=1e-9)
    np.testing.assert_allclose(between(a, b), compose(inverse(a), b), atol=1e-9)
    # Broadcasting: one pose against many.
    np.testing.assert_allclose(between(a[0], b), between(np.tile(a[0], (100, 1)), b), atol=1e-12)


def test_between_hand_example() -> None:
    a = np.array([1.0, 1.0, np.pi / 2])
    b = np.array([1.0, 3.0, np.pi])
    np.testing.assert_allclose(between(a, b), [2.0, 0.0, np.pi / 2], atol=1e-12)


def test_transform_points_round_trip_and_hand_example() -> None:
    pose = np.array([2.0, -1.0, np.pi / 2])
    body = np.array([[1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_allclose(transform_points(pose, body), [[2.0, 0.0], [0.0, -1.0]],
                               atol=1e-12)
    rng = np.random.default_rng(3)
    points = rng.uniform(-10, 10, (30, 2))
    np.testing.assert_allclose(inverse_transform_points(pose, transform_points(pose, points)),
                               points, atol=1e-9)
    poses = _random_poses(rng, 30)
    paired = transform_points(poses, points)
    np.testing.assert_allclose(paired[4], transform_points(poses[4], points[4:5])[0], atol=1e-12)
    np.testing.assert_allclose(inverse_transform_points(poses, paired), points, atol=1e-9)


def test_range_bearing_hand_example_and_wrapping() -> None:
    pose = np.array([1.0, 1.0, np.pi / 2])
    ranges, bearings = range_bearing(pose, np.array([[1.0, 3.0], [0.0, 1.0], [1.0, 0.0]]))
    np.testing.assert_allclose(ranges, [2.0, 1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(bearings, [0.0, np.pi / 2, np.pi], atol=1e-12)
    behind = range_bearing(np.array([0.0, 0.0, 3.0]), np.array([-1.0, -0.1]))[1]
    assert -np.pi < behind <= np.pi
    np.testing.assert_allclose(behind, wrap_angle(np.arctan2(-0.1, -1.0) - 3.0), atol=1e-12)


def test_compose_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(4)
    a, b = _random_poses(rng, 10), _random_poses(rng, 10)
    j_a, j_b = compose_jacobians(a, b)
    assert j_a.shape == (10, 3, 3) and j_b.shape == (10, 3, 3)
    h = 1e-6
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        d_a = (compose(a + step, b) - compose(a - step, b)) / (2 * h)
        d_b = (compose(a, b + step) - compose(a, b - step)) / (2 * h)
        np.testing.assert_allclose(j_a[:, :, k], d_a, atol=1e-6)
        np.testing.assert_allclose(j_b[:, :, k], d_b, atol=1e-6)
    single_a, single_b = compose_jacobians(a[0], b[0])
    np.testing.assert_allclose(single_a, j_a[0])
    np.testing.assert_allclose(single_b, j_b[0])


def test_coordinate_to_body_covariance_rotates_position_block() -> None:
    pose = np.array([3.0, 4.0, np.pi / 2])
    body = coordinate_to_body_covariance(pose, np.diag([1.0, 4.0, 9.0]))
    np.testing.assert_allclose(body, np.diag([4.0, 1.0, 9.0]), atol=1e-12)


@pytest.mark.parametrize("theta", [-2.5, 0.3, 1.9])
def test_coordinate_to_body_covariance_is_the_gtsam_pose2_tangent_frame(theta: float) -> None:
    pose = np.array([1.0, -2.0, theta])
    eps = 1e-6
    tangent_jacobian = np.column_stack([
        gtsam.Pose2(*pose).localCoordinates(gtsam.Pose2(*(pose + eps * np.eye(3)[k]))) / eps
        for k in range(3)])
    coordinate_cov = np.array([[2.0, 0.5, 0.1], [0.5, 1.0, -0.2], [0.1, -0.2, 0.3]])
    np.testing.assert_allclose(coordinate_to_body_covariance(pose, coordinate_cov),
                               tangent_jacobian @ coordinate_cov @ tangent_jacobian.T, atol=1e-5)


def test_a_single_angle_wraps_to_the_same_bits_as_an_array_of_angles() -> None:
    rng = np.random.default_rng(4)
    angles = np.concatenate([rng.uniform(-60.0, 60.0, 5000),
                             [np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 0.0, -0.0, 1e-300,
                              np.nextafter(np.pi, 0.0), np.nextafter(-np.pi, 0.0),
                              np.nextafter(-np.pi, -4.0)]])
    as_array = wrap_angle(angles)
    one_by_one = np.array([wrap_angle(float(a)) for a in angles])
    numpy_scalars = np.array([wrap_angle(a) for a in angles])  # np.float64 elements
    np.testing.assert_array_equal(one_by_one, as_array)
    np.testing.assert_array_equal(numpy_scalars, as_array)
    # Within one rounding of (-pi, pi]: the float nearest -3 pi wraps to one ulp above pi.
    assert np.all((as_array > -np.pi) & (as_array <= np.nextafter(np.pi, 4.0)))
    assert wrap_angle(-np.pi) == np.pi and np.shape(wrap_angle(1.0)) == ()


def test_single_poses_give_the_same_bits_as_a_batch_of_poses() -> None:
    """compose, between and compose_jacobians take a Python-float path for one pose
    pair; it must round exactly like the array path (the agents' decisions depend on it)."""
    rng = np.random.default_rng(5)
    a = _random_poses(rng, 3000)
    b = _random_poses(rng, 3000)
    a[:10, 2] = [np.pi, -np.pi, 0.0, -0.0, 1e-300, 40.0, -40.0, np.pi / 2, -np.pi / 2, 1e8]
    composed, relative, (j_a, j_b) = compose(a, b), between(a, b), compose_jacobians(a, b)
    for index in range(len(a)):
        np.testing.assert_array_equal(compose(a[index], b[index]), composed[index])
        np.testing.assert_array_equal(between(a[index], b[index]), relative[index])
        single_j_a, single_j_b = compose_jacobians(a[index], b[index])
        np.testing.assert_array_equal(single_j_a, j_a[index])
        np.testing.assert_array_equal(single_j_b, j_b[index])
    # Lists and tuples are single poses too.
    np.testing.assert_array_equal(compose(list(a[0]), tuple(b[0])), composed[0])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_single_pose_gives_nan_like_a_batch_instead_of_raising(bad: float) -> None:
    pose = np.array([1.0, 2.0, bad])
    other = np.array([0.5, -0.5, 0.3])
    with np.errstate(invalid="ignore"):
        for single, batch in ((compose(pose, other), compose(pose[None], other[None])[0]),
                              (between(pose, other), between(pose[None], other[None])[0]),
                              (wrap_angle(bad), wrap_angle(np.array([bad]))[0])):
            np.testing.assert_array_equal(single, batch)
        single_j_a, _ = compose_jacobians(pose, other)
        np.testing.assert_array_equal(single_j_a, compose_jacobians(pose[None], other[None])[0][0])


def test_the_inverse_s_jacobian_matches_finite_differences():
    pose, step = np.array([1.5, -0.7, 2.2]), 1e-7
    numeric = np.column_stack([(inverse(pose + step * axis) - inverse(pose - step * axis))
                               / (2 * step) for axis in np.eye(3)])
    assert inverse_jacobian(pose) == pytest.approx(numeric, abs=1e-6)
