"""Tests of the APF local planner, simulated with the world kinematics."""
import numpy as np
import pytest

from em_exploration_ros.core.params import MotionParams, SensorParams, WorldParams
from em_exploration_ros.core.planning.motion import ApfController
from em_exploration_ros.core.world.world import collides, generate_world, step_pose

MOTION = MotionParams()
LANDMARK_RADIUS = 1.0
ROBOT_RADIUS = 0.8
COLLISION_M = LANDMARK_RADIUS + ROBOT_RADIUS
STEP_M = MOTION.speed_mps * MOTION.time_step_s


def _drive(pose: list[float], target: list[float], landmarks: np.ndarray,
           max_steps: int) -> tuple[np.ndarray, bool]:
    """Trajectory (T, 3) from ``pose`` until the target is reached or ``max_steps`` pass."""
    controller = ApfController(MOTION, LANDMARK_RADIUS, ROBOT_RADIUS)
    target_xy = np.asarray(target, dtype=float)
    poses = [np.asarray(pose, dtype=float)]
    for _ in range(max_steps):
        if controller.reached(poses[-1], target_xy):
            return np.array(poses), True
        turn = controller.command(poses[-1], target_xy, landmarks)
        poses.append(step_pose(poses[-1], turn, STEP_M, MOTION))
    return np.array(poses), controller.reached(poses[-1], target_xy)


def _min_distance(trajectory: np.ndarray, landmarks: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(trajectory[:, None, :2] - landmarks[None], axis=2)))


def _straight_steps(start: list[float], target: list[float]) -> float:
    return float(np.linalg.norm(np.subtract(target, start[:2]))) / STEP_M


@pytest.mark.parametrize("target_y", [0.0, 0.01, -0.01])
def test_target_straight_behind_landmark(target_y: float) -> None:
    landmarks = np.array([[10.0, 0.0]])
    trajectory, reached = _drive([0.0, 0.0, 0.0], [20.0, target_y], landmarks, max_steps=400)
    assert reached
    assert len(trajectory) < 1.3 * _straight_steps([0, 0], [20, 0])
    assert _min_distance(trajectory, landmarks) >= COLLISION_M + MOTION.safety_margin_m - 1e-6
    # It goes around on one side only (no oscillation across the line), toward the target.
    side = np.sign(trajectory[np.abs(trajectory[:, 0] - 10.0) < 2.0, 1])
    assert np.all(side == side[0])
    if target_y != 0.0:
        assert side[0] == np.sign(target_y)


@pytest.mark.parametrize("start", [[0.0, 0.0, 0.0], [20.0, -12.0, 2.0], [30.0, 5.0, np.pi]])
def test_target_next_to_landmark(start: list[float]) -> None:
    # Target 2.5 m from the landmark centre, i.e. 0.7 m beyond the collision distance.
    landmarks = np.array([[22.5, 0.0]])
    target = [20.0, 0.0]
    trajectory, reached = _drive(start, target, landmarks, max_steps=600)
    assert reached
    assert len(trajectory) < 2.0 * _straight_steps(start, target) + 40
    assert _min_distance(trajectory, landmarks) > COLLISION_M


def test_narrow_gap_between_two_landmarks() -> None:
    # Centres 5 m apart: 0.8 m of slack beyond both safety margins.
    landmarks = np.array([[10.0, 2.5], [10.0, -2.5]])
    trajectory, reached = _drive([0.0, 0.3, 0.2], [20.0, -0.4], landmarks, max_steps=400)
    assert reached
    assert len(trajectory) < 1.2 * _straight_steps([0, 0.3], [20, -0.4])
    assert _min_distance(trajectory, landmarks) > COLLISION_M
    crossing = trajectory[np.argmin(np.abs(trajectory[:, 0] - 10.0))]
    assert abs(crossing[1]) < 0.5  # through the gap, not around it


def test_random_scenes_in_dense_generated_world() -> None:
    # 20 landmarks 6 m apart in 40 m x 40 m (denser than the paper's world); with this seed
    # the APF without the safety filter hits a landmark in one of the runs.
    world_params = WorldParams(width_m=40.0, height_m=40.0, num_landmarks=20,
                               landmark_min_separation_m=6.0, landmark_edge_margin_m=2.0)
    world = generate_world(world_params, SensorParams(), np.random.SeedSequence(1))
    rng = np.random.default_rng(5)
    runs = 0
    while runs < 10:
        start, target = rng.uniform(3.0, 37.0, size=(2, 2))
        clearance = np.linalg.norm(world.landmarks - np.stack([start, target])[:, None], axis=2)
        if clearance.min() < COLLISION_M + 0.5:
            continue
        runs += 1
        start_pose = [*start, rng.uniform(-np.pi, np.pi)]
        trajectory, reached = _drive(start_pose, list(target), world.landmarks, max_steps=800)
        assert reached
        assert len(trajectory) < 1.6 * _straight_steps(start_pose, list(target)) + 30
        assert not collides(world, trajectory[:, :2]).any()


def test_command_without_landmarks_points_at_target() -> None:
    controller = ApfController(MOTION, LANDMARK_RADIUS, ROBOT_RADIUS)
    empty = np.zeros((0, 2))
    assert controller.command(np.array([0.0, 0.0, 0.0]), np.array([10.0, 1.0]), empty) == \
        pytest.approx(np.arctan2(1.0, 10.0))
    behind = controller.command(np.array([0.0, 0.0, 0.0]), np.array([-10.0, -1.0]), empty)
    assert behind == pytest.approx(-MOTION.max_turn_per_step_rad)


def test_filter_turns_away_from_landmark_ahead() -> None:
    controller = ApfController(MOTION, LANDMARK_RADIUS, ROBOT_RADIUS)
    # Target right behind a landmark 2.3 m ahead: the robot must turn as hard as it can.
    turn = controller.command(np.array([0.0, 0.0, 0.0]), np.array([2.5, 0.0]),
                              np.array([[2.3, 0.0]]))
    assert abs(turn) == pytest.approx(MOTION.max_turn_per_step_rad)


def test_reached() -> None:
    controller = ApfController(MOTION, LANDMARK_RADIUS, ROBOT_RADIUS)
    assert controller.reached(np.array([1.0, 1.0, 3.0]), np.array([1.0, 2.0]))
    assert not controller.reached(np.array([1.0, 1.0, 3.0]), np.array([1.0, 2.01]))
