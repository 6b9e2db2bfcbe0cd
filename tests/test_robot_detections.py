"""Robot-to-robot detections screened by pairwise consistency (``core/slam/robot_detections``):
the loop test, the screen's decisions, and a team graph without landmark identities that
leaves a planted wrong detection out while the true ones go in."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from em_exploration_ros.core.geometry import between, compose
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.readings import KeyframeMeasurements, TeammateReading
from em_exploration_ros.core.slam.association import chi2_quantile
from em_exploration_ros.core.slam.robot_detections import (RobotDetection,
                                                           RobotDetectionScreen,
                                                           detections_agree)
from em_exploration_ros.core.slam.team_slam import TeamSlam

DETECTION_COVARIANCE = np.diag([0.05 ** 2, 0.05 ** 2, 0.01 ** 2])
ODOMETRY_COVARIANCE = np.diag([0.02 ** 2, 0.02 ** 2, 0.005 ** 2])
GATE = chi2_quantile(3, 0.99)
STEP = np.array([2.0, 0.0, 0.05])  # each robot's motion per keyframe, in its body frame


def trajectory(start, count: int) -> list[np.ndarray]:
    """Poses of a robot driving ``STEP`` per keyframe from ``start``."""
    poses = [np.asarray(start, dtype=float)]
    for _ in range(count - 1):
        poses.append(compose(poses[-1], STEP))
    return poses


def detection(observer: int, observed: int, index: int, poses: dict, error=(0.0, 0.0, 0.0)
              ) -> RobotDetection:
    """``observer``'s detection of ``observed`` at ``index``, exact unless ``error`` (added
    to the relative pose)."""
    relative = between(poses[observer][index], poses[observed][index]) + np.asarray(error)
    return RobotDetection((observer, index),
                          TeammateReading(observed, relative, DETECTION_COVARIANCE))


def motion(poses: dict, robot: int, since: int, until: int):
    """Exact odometry of ``robot`` between two indices, with ``ODOMETRY_COVARIANCE`` per
    keyframe."""
    return (between(poses[robot][since], poses[robot][until]),
            (until - since) * ODOMETRY_COVARIANCE)


POSES = {0: trajectory([0.0, 0.0, 0.0], 20), 1: trajectory([3.0, 4.0, 1.0], 20)}


def test_two_robots_seeing_each_other_agree_at_one_index_and_over_odometry():
    same = (detection(0, 1, 3, POSES), detection(1, 0, 3, POSES))
    assert detections_agree(*same, motion(POSES, 0, 3, 3), motion(POSES, 1, 3, 3), GATE)
    later = detection(1, 0, 7, POSES)
    assert detections_agree(same[0], later, motion(POSES, 0, 3, 7), motion(POSES, 1, 3, 7),
                            GATE)


@pytest.mark.parametrize("error", [(1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 0.3)])
def test_a_detection_off_by_a_metre_or_a_turn_does_not_agree(error):
    wrong = detection(1, 0, 7, POSES, error)
    assert not detections_agree(detection(0, 1, 3, POSES), wrong, motion(POSES, 0, 3, 7),
                                motion(POSES, 1, 3, 7), GATE)


def test_readings_stated_exact_are_tested_on_the_floor():
    exact = [RobotDetection(item.observer, TeammateReading(item.reading.robot_id,
                                                           item.reading.relative_pose,
                                                           np.zeros((3, 3))))
             for item in (detection(0, 1, 3, POSES), detection(1, 0, 3, POSES))]
    still = (np.zeros(3), np.zeros((3, 3)))
    assert detections_agree(*exact, still, still, GATE, floor_variance=1e-6)
    moved = RobotDetection((1, 3), TeammateReading(
        0, exact[1].reading.relative_pose + [0.1, 0.0, 0.0], np.zeros((3, 3))))
    assert not detections_agree(exact[0], moved, still, still, GATE, floor_variance=1e-6)
    assert not detections_agree(*exact, still, still, GATE)  # singular: no test, no trust


def test_a_heading_error_the_odometry_s_drift_explains_agrees():
    """Over a long stretch the odometry's covariance grows and holds a larger misfit."""
    drifted = detection(1, 0, 11, POSES, (0.0, 0.0, 0.08))
    assert not detections_agree(detection(0, 1, 10, POSES), drifted,
                                motion(POSES, 0, 10, 11), motion(POSES, 1, 10, 11), GATE)
    loose = (motion(POSES, 0, 1, 11)[0], 50 * ODOMETRY_COVARIANCE)
    assert detections_agree(detection(0, 1, 1, POSES), drifted, loose,
                            motion(POSES, 1, 1, 11), GATE)


def screen_all(screen: RobotDetectionScreen, newest: int):
    return screen.screen(lambda robot, since, until: motion(POSES, robot, since, until),
                         lambda robot: newest)


def test_the_screen_accepts_agreeing_detections_and_leaves_a_wrong_one_out_when_past():
    screen = RobotDetectionScreen(window=5, gate_probability=0.99, floor_variance=1e-12)
    true = [detection(0, 1, 2, POSES), detection(1, 0, 2, POSES), detection(0, 1, 3, POSES)]
    wrong = detection(1, 0, 3, POSES, (0.0, 2.0, 0.0))
    for item in [*true, wrong]:
        screen.offer(item)
    accepted, left_out = screen_all(screen, newest=3)
    assert accepted == true and left_out == []
    assert screen.num_waiting == 1  # the wrong one, until both robots are 5 keyframes on
    accepted, left_out = screen_all(screen, newest=7)
    assert accepted == [] and screen.num_waiting == 1
    accepted, left_out = screen_all(screen, newest=8)
    assert accepted == [] and screen.num_waiting == 0
    assert [item.detection for item in left_out] == [wrong]
    assert left_out[0].reason == ("agrees with 0 of the 3 other detections of these robots "
                                  "within 5 keyframes")


def test_a_lone_detection_waits_for_company_and_is_taken_with_it():
    screen = RobotDetectionScreen(window=5, gate_probability=0.99, floor_variance=1e-12)
    screen.offer(detection(0, 1, 4, POSES))
    assert screen_all(screen, newest=6) == ([], [])
    screen.offer(detection(1, 0, 6, POSES))
    accepted, _ = screen_all(screen, newest=6)
    assert [item.index for item in accepted] == [4, 6]
    lone = detection(0, 1, 12, POSES)  # more than 5 keyframes after the last one
    screen.offer(lone)
    accepted, left_out = screen_all(screen, newest=17)
    assert accepted == [] and [item.detection for item in left_out] == [lone]
    assert left_out[0].reason.startswith("no other detection of these robots")


def test_accepted_detections_vouch_for_a_new_one_and_against_a_wrong_one():
    screen = RobotDetectionScreen(window=5, gate_probability=0.99, floor_variance=1e-12)
    screen.accept_unscreened(detection(0, 1, 0, POSES))
    screen.accept_unscreened(detection(1, 0, 0, POSES))
    screen.offer(detection(0, 1, 1, POSES))
    screen.offer(detection(1, 0, 1, POSES, (1.5, 0.0, 0.0)))
    accepted, _ = screen_all(screen, newest=1)
    assert [(item.observer, item.index) for item in accepted] == [((0, 1), 1)]


def team_slam_with_a_planted_wrong_detection(landmark_ids: bool) -> TeamSlam:
    """Robot 0's graph of two robots driving side by side (exact odometry and detections at
    every keyframe), but robot 1's detection of robot 0 at keyframe 6 is 3 m off."""
    params = ExplorationParams().slam
    poses = {0: trajectory([0.0, 0.0, 0.0], 12), 1: trajectory([0.0, 6.0, 0.0], 12)}
    slam = TeamSlam(0, 2, params, poses[0][0], landmark_ids=landmark_ids)
    for index in range(12):
        for robot, other in ((0, 1), (1, 0)):
            relative = between(poses[robot][index], poses[other][index])
            if (robot, index) == (1, 6):
                relative = relative + np.array([3.0, 0.0, 0.0])
            slam.add_keyframe(KeyframeMeasurements(
                robot, index, float(index), index == 0, index - 1,
                np.zeros(3) if index == 0 else between(poses[robot][index - 1],
                                                       poses[robot][index]),
                np.zeros((3, 3)) if index == 0 else ODOMETRY_COVARIANCE, (),
                (TeammateReading(other, relative, DETECTION_COVARIANCE),)))
            slam.update()
    slam.truth = poses
    return slam


def test_a_graph_without_identities_leaves_the_planted_detection_out(caplog):
    with caplog.at_level(logging.WARNING, logger="em_exploration_ros.core.slam.team_slam"):
        screened = team_slam_with_a_planted_wrong_detection(landmark_ids=False)
    assert screened.inter_robot_factors(0, 1) == 2 * 12 - 1
    assert "robot 1's detection of robot 0 at keyframe 6 left out: agrees with 0 of the " \
        in caplog.text
    errors = [np.linalg.norm(screened.pose(1, k)[:2] - screened.truth[1][k][:2])
              for k in range(12)]
    assert max(errors) < 1e-3
    # The paper's ideal sensing takes every detection as it comes: the planted one bends
    # robot 1's trajectory.
    ideal = team_slam_with_a_planted_wrong_detection(landmark_ids=True)
    assert ideal.inter_robot_factors(0, 1) == 2 * 12
    assert np.linalg.norm(ideal.pose(1, 6)[:2] - ideal.truth[1][6][:2]) > 0.05


@pytest.mark.parametrize("turn_after, taken", [(2, True), (3, False)])
def test_a_detection_agreeing_with_half_of_the_others_is_taken_though_older_ones_disagree(
        turn_after, taken):
    """Accepted detections need not agree with each other: a new one at keyframe 6 that
    agrees with those since a turn error in robot 1's odometry (after keyframe
    ``turn_after``) but not with those before goes in when that is half of the 6 accepted
    at keyframes 0-5 (3 of 6), not when fewer (2 of 6)."""
    screen = RobotDetectionScreen(window=6, gate_probability=0.99, floor_variance=1e-12)
    for index in range(6):
        screen.accept_unscreened(detection(0, 1, index, POSES))

    def motion_with_a_turn_error(robot, since, until):
        delta, covariance = motion(POSES, robot, since, until)
        if robot == 1 and since <= turn_after < until:
            delta = compose(delta, [0.0, 0.0, 0.05])
        return delta, covariance

    new = detection(1, 0, 6, POSES)
    screen.offer(new)
    accepted, _ = screen.screen(motion_with_a_turn_error, lambda robot: 6)
    assert accepted == ([new] if taken else [])


def test_detections_further_apart_than_the_window_are_not_compared():
    """A forged record may name a keyframe long past: the screen walks no odometry chain
    longer than its window, and leaves the detection out at once."""
    screen = RobotDetectionScreen(window=5, gate_probability=0.99, floor_variance=1e-12)
    for index in range(3):
        screen.accept_unscreened(detection(0, 1, 100 + index, {0: {100 + k: POSES[0][k]
                                                                  for k in range(3)},
                                                              1: {100 + k: POSES[1][k]
                                                                  for k in range(3)}}))
    old = detection(1, 0, 2, POSES)
    screen.offer(old)
    asked = []

    def motion_within_the_window(robot, since, until):
        asked.append(until - since)
        return motion(POSES, robot, since, until)

    accepted, left_out = screen.screen(motion_within_the_window, lambda robot: 102)
    assert accepted == [] and [item.detection for item in left_out] == [old]
    assert left_out[0].reason.startswith("no other detection") and asked == []
