"""Virtual map uncertainty: Jacobians, hand-computed cell covariances, covariance intersection."""
import numpy as np
import pytest

from em_exploration_ros.core.geometry import range_bearing
from em_exploration_ros.core.virtual_map.cell_uncertainty import (CellObservations,
                                                                  cell_covariances_from_poses,
                                                                  inverse_2x2,
                                                                  information_to_covariance,
                                                                  inverse_sensor_model,
                                                                  observation_confidence)
from em_exploration_ros.core.virtual_map.occupancy import GridGeometry, observation_counts
from em_exploration_ros.core.params import MapParams, SensorParams

SENSORS = SensorParams()
MAP = MapParams()
GEOMETRY = GridGeometry(20.0, 10.0, 2.0)  # cell (row, col) centre ((col + .5) 2, (row + .5) 2)
SB2 = SENSORS.sonar_bearing_sigma_rad ** 2
SR2 = SENSORS.sonar_range_sigma_m ** 2


def _measure(pose: np.ndarray, point: np.ndarray) -> np.ndarray:
    distance, bearing = range_bearing(pose, point)
    return np.array([bearing, distance])


def _numerical_jacobians(pose: np.ndarray, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of (bearing, range) w.r.t. additive pose and point coordinates."""
    step = 1e-6

    def column(shift_pose: np.ndarray, shift_point: np.ndarray) -> np.ndarray:
        diff = (_measure(pose + shift_pose, point + shift_point)
                - _measure(pose - shift_pose, point - shift_point))
        diff[0] = (diff[0] + np.pi) % (2 * np.pi) - np.pi
        return diff / (2 * step)

    hx = np.column_stack([column(step * np.eye(3)[i], np.zeros(2)) for i in range(3)])
    hl = np.column_stack([column(np.zeros(3), step * np.eye(2)[i]) for i in range(2)])
    return hx, hl


def test_inverse_sensor_model_is_the_pseudo_inverse_formula() -> None:
    # Sigma_v = Hl^+ (Hx Sigma_x Hx^T + R) Hl^+^T with numerically differentiated Jacobians.
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(-5, 5, (20, 2)), rng.uniform(-3, 3, 20)])
    points = rng.uniform(-8, 8, (20, 2))
    roots = rng.normal(scale=0.2, size=(20, 3, 3))
    covs = roots @ np.swapaxes(roots, 1, 2)
    noise = np.diag([SB2, SR2])
    gain, model_noise = inverse_sensor_model(poses, points, SENSORS)
    body_gain, _ = inverse_sensor_model(poses, points, SENSORS, "body")
    for i, (pose, point, cov) in enumerate(zip(poses, points, covs)):
        hx, hl = _numerical_jacobians(pose, point)
        pseudo = np.linalg.pinv(hl)
        expected = pseudo @ (hx @ cov @ hx.T + noise) @ pseudo.T
        np.testing.assert_allclose(gain[i] @ cov @ gain[i].T + model_noise[i], expected,
                                   rtol=1e-6, atol=1e-12)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        to_map = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        np.testing.assert_allclose(body_gain[i] @ cov @ body_gain[i].T,
                                   gain[i] @ to_map @ cov @ to_map.T @ gain[i].T, atol=1e-12)


def test_inverse_2x2_closed_form() -> None:
    matrices = np.random.default_rng(4).normal(size=(50, 2, 2))
    inverse, det = inverse_2x2(matrices)
    np.testing.assert_allclose(inverse, np.linalg.inv(matrices), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(det, np.linalg.det(matrices), rtol=1e-9, atol=1e-12)


def covariance_intersection(covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection of 2x2 covariances ``(P, 2, 2)`` of one cell: observations
    whose pair covariance is the given one whatever the pose covariance. Returns the fused
    information ``(1, 2, 2)`` and the observed flag ``(1,)``."""
    count = len(covariances)
    same_cell = np.zeros(count, dtype=np.int64)
    observations = CellObservations(same_cell, same_cell, np.zeros((2, count)),
                                    covariances[:, [0, 0, 1], [0, 1, 1]].T, np.zeros((1, 2, 2)))
    return observations.fused_information(np.zeros((1, 3, 3)), num_cells=1)


def test_one_pose_one_cell_hand_computed() -> None:
    # Pose at (1, 1) heading +x; cell (row 0, col 2) has its centre 4 m ahead at (5, 1).
    # Hl^+ Hx = -[[1, 0, -dy], [0, 1, dx]] and Hl^+ R Hl^+^T = diag(sr^2, dx^2 sb^2).
    pose = np.array([[1.0, 1.0, 0.0]])
    cov = np.diag([0.01, 0.04, 0.0025])[None]
    covariances, observed = cell_covariances_from_poses(GEOMETRY, pose, cov, SENSORS, MAP)
    expected = np.diag([0.01 + SR2, 0.04 + 16 * 0.0025 + 16 * SB2])
    assert observed[0, 2]
    np.testing.assert_allclose(covariances[0, 2], expected, rtol=1e-12, atol=1e-15)


def test_body_frame_covariance_is_rotated_into_the_map_frame() -> None:
    # Heading +y: body x is map y. A body covariance diag(a, b, c) is map diag(b, a, c).
    pose = np.array([[1.0, 1.0, np.pi / 2]])
    body = np.diag([0.01, 0.04, 0.0025])[None]
    as_map = np.diag([0.04, 0.01, 0.0025])[None]
    from_body, _ = cell_covariances_from_poses(GEOMETRY, pose, body, SENSORS, MAP, "body")
    from_map, _ = cell_covariances_from_poses(GEOMETRY, pose, as_map, SENSORS, MAP, "map")
    np.testing.assert_allclose(from_body, from_map, rtol=1e-12, atol=1e-15)


def test_two_poses_fused_by_covariance_intersection_hand_computed() -> None:
    # Cell centre (5, 1) seen 4 m ahead from (1, 1) and 4 m behind from (9, 1).
    poses = np.array([[1.0, 1.0, 0.0], [9.0, 1.0, 0.0]])
    covs = np.array([np.diag([0.01, 0.04, 0.0025]), np.diag([0.09, 0.01, 0.0])])
    a1, b1 = 0.01 + SR2, 0.04 + 16 * 0.0025 + 16 * SB2
    a2, b2 = 0.09 + SR2, 0.01 + 16 * SB2
    w1 = 1 / (a1 * b1) / (1 / (a1 * b1) + 1 / (a2 * b2))
    fused_information = np.diag([w1 / a1 + (1 - w1) / a2, w1 / b1 + (1 - w1) / b2])
    covariances, _ = cell_covariances_from_poses(GEOMETRY, poses, covs, SENSORS, MAP)
    np.testing.assert_allclose(covariances[0, 2], np.linalg.inv(fused_information), rtol=1e-12)
    # Not the naive (independent) fusion, which would be overconfident.
    naive = np.linalg.inv(np.diag([1 / a1 + 1 / a2, 1 / b1 + 1 / b2]))
    assert np.trace(covariances[0, 2]) > 1.5 * np.trace(naive)


def test_identical_observations_are_not_double_counted() -> None:
    cov = np.array([[[0.3, 0.1], [0.1, 0.2]]] * 4)
    information, observed = covariance_intersection(cov)
    assert observed[0]
    np.testing.assert_allclose(np.linalg.inv(information[0]), cov[0], rtol=1e-12)


def test_covariance_intersection_is_consistent_for_any_correlation() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        count = int(rng.integers(2, 6))
        roots = rng.normal(size=(count, 2, 2))
        covariances = roots @ np.swapaxes(roots, 1, 2) + 0.05 * np.eye(2)
        information, _ = covariance_intersection(covariances)
        fused = np.linalg.inv(information[0])
        individual = np.linalg.inv(covariances)
        # The fused estimate is x = P sum_k w_k I_k x_k, i.e. gains P w_k I_k.
        _, det = inverse_2x2(covariances)
        weights = (1 / det) / np.sum(1 / det)
        gains = fused @ (weights[:, None, None] * individual)
        # Joint covariances with the given marginals: errors e_k = S_k Q_k z from one
        # shared z (fully correlated, random rotations Q_k), mixed with independent errors.
        roots_k = np.linalg.cholesky(covariances)
        for mix in (0.0, 0.5, 1.0):
            angles = rng.uniform(-np.pi, np.pi, count)
            rotations = np.array([[[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
                                  for a in angles])
            factors = roots_k @ rotations
            actual = sum(gains[i] @ (mix * factors[i] @ factors[j].T
                                     + (1 - mix) * (covariances[i] if i == j else 0.0))
                         @ gains[j].T for i in range(count) for j in range(count))
            assert np.linalg.eigvalsh(fused - actual).min() > -1e-10
        # Never more informative than the best input in any direction.
        for direction in rng.normal(size=(20, 2)):
            fused_info = direction @ information[0] @ direction
            assert fused_info <= max(direction @ i @ direction for i in individual) + 1e-9


def test_unobserved_cell_keeps_the_prior() -> None:
    pose = np.array([[1.0, 1.0, 0.0]])
    covariances, observed = cell_covariances_from_poses(GEOMETRY, pose, np.eye(3)[None] * 0.01,
                                                        SENSORS, MAP)
    assert not observed[4, 9]
    np.testing.assert_allclose(covariances[4, 9], 1.44 * np.eye(2))
    assert np.trace(covariances[4, 9]) == pytest.approx(2.88)


def test_observed_mask_matches_the_occupancy_rule_and_traces_agree() -> None:
    rng = np.random.default_rng(6)
    poses = np.column_stack([rng.uniform(0, 20, (15, 2)), rng.uniform(-3, 3, 15)])
    roots = rng.normal(scale=0.1, size=(15, 3, 3))
    covs = roots @ np.swapaxes(roots, 1, 2) + 1e-4 * np.eye(3)
    covariances, observed = cell_covariances_from_poses(GEOMETRY, poses, covs, SENSORS, MAP)
    np.testing.assert_array_equal(observed, observation_counts(GEOMETRY, poses, 7.5) > 0)
    observations = CellObservations.from_poses(GEOMETRY, poses, SENSORS)
    sums = observations.intersection_sums(covs, GEOMETRY.rows * GEOMETRY.cols)
    information, flat_observed = sums.information(), sums.observed
    np.testing.assert_allclose(sums.covariance_traces()[flat_observed],
                               np.trace(covariances, axis1=-2, axis2=-1).ravel()[flat_observed],
                               rtol=1e-10)
    assert np.all(sums.covariance_traces()[~flat_observed] == 0.0)
    np.testing.assert_allclose(
        information_to_covariance(information, flat_observed, 1.2).reshape(covariances.shape),
        covariances)
    assert np.all(np.linalg.eigvalsh(covariances) > 0)


def _random_poses(seed: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random poses (K, 3) in the 20 m x 10 m grid and random covariances."""
    rng = np.random.default_rng(seed)
    poses = np.column_stack([rng.uniform(0, 20, (count, 2)), rng.uniform(-3, 3, count)])
    roots = rng.normal(scale=0.1, size=(count, 3, 3))
    return poses, roots @ np.swapaxes(roots, 1, 2) + 1e-4 * np.eye(3)


def test_split_observations_sum_to_observations_of_all_poses() -> None:
    poses, covs = _random_poses(7, 8)
    cells = GEOMETRY.rows * GEOMETRY.cols
    whole = CellObservations.from_poses(GEOMETRY, poses, SENSORS, "body")
    first = np.arange(8) < 5
    summed = (whole.of_poses(first).intersection_sums(covs, cells)
              + whole.of_poses(~first).intersection_sums(covs, cells))
    expected = whole.fused_information(covs, cells)[0]
    np.testing.assert_allclose(summed.information(), expected, rtol=1e-12)
    # The linear coefficients reproduce G Sigma G^T + N of the explicit Jacobians.
    pose_two = whole.of_poses(np.arange(8) == 2)
    centres = GEOMETRY.cell_center(np.stack(np.divmod(pose_two.flat_cell, GEOMETRY.cols), axis=-1))
    gain, noise = inverse_sensor_model(np.repeat(poses[2:3], len(centres), axis=0), centres,
                                       SENSORS, "body")
    explicit = gain @ covs[2] @ np.swapaxes(gain, 1, 2) + noise
    information, _ = pose_two.fused_information(covs, cells)
    np.testing.assert_allclose(np.linalg.inv(information[pose_two.flat_cell]), explicit,
                               rtol=1e-10)


def test_observation_confidence_follows_the_log_odds_update() -> None:
    q = observation_confidence(np.array([0, 1, 2, 50]), MAP)
    np.testing.assert_allclose(q, [0.5, 0.7, 1 - 0.3 ** 2 / (0.3 ** 2 + 0.7 ** 2), 0.95])


def test_observations_of_a_subset_of_cells_give_those_cells_sums_bit_for_bit() -> None:
    poses, covs = _random_poses(11, 9)
    cells = GEOMETRY.rows * GEOMETRY.cols
    kept = np.random.default_rng(12).random(cells) < 0.4
    slots = np.full(cells, -1)
    slots[kept] = np.arange(np.count_nonzero(kept))
    whole = CellObservations.from_poses(GEOMETRY, poses, SENSORS, "body")
    subset = CellObservations.from_poses(GEOMETRY, poses, SENSORS, "body", slots)
    # Only pairs of kept cells, numbered by slot, in the same (pose) order.
    assert len(subset.flat_cell) == np.count_nonzero(kept[whole.flat_cell]) > 0
    np.testing.assert_array_equal(subset.flat_cell, slots[whole.flat_cell[kept[whole.flat_cell]]])
    full_sums = whole.intersection_sums(covs, cells)
    sums = subset.intersection_sums(covs, int(np.count_nonzero(kept)))
    np.testing.assert_array_equal(sums.weight, full_sums.weight[kept])
    np.testing.assert_array_equal(sums.weighted_information, full_sums.weighted_information[kept])
    np.testing.assert_array_equal(sums.covariance_traces(), full_sums.covariance_traces()[kept])


def test_grouped_sums_equal_each_groups_own_sums_bit_for_bit() -> None:
    poses, covs = _random_poses(5, 10)
    cells = GEOMETRY.rows * GEOMETRY.cols
    observations = CellObservations.from_poses(GEOMETRY, poses, SENSORS, "body")
    bounds = [0, 4, 4, 7, 10]  # group 1 has no pose: its sums are all zero
    group = np.repeat(np.arange(4), np.diff(bounds))
    grouped = observations.grouped_intersection_sums(covs, group, 4, cells)
    assert grouped.weight.shape == (4, cells)
    for index in range(4):
        alone = observations.of_poses(group == index).intersection_sums(covs, cells)
        np.testing.assert_array_equal(grouped[index].weight, alone.weight)
        np.testing.assert_array_equal(grouped[index].weighted_information,
                                      alone.weighted_information)
        np.testing.assert_array_equal(grouped.covariance_traces()[index],
                                      alone.covariance_traces())
    assert not np.any(grouped[1].observed)
