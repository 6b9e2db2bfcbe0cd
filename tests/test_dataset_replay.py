"""Victoria Park through the team's own association and SLAM (em-bench dataset): a prefix of
the dataset with one robot and with two, the summary's keys and floors of its association,
the observation noise as the file states it, the odometry's heading sigma calibrated on the
first poses, and bad arguments refused in one line."""
import json
import subprocess
import sys

import gtsam
import numpy as np
import pytest

from em_exploration_ros.core.evaluation.dataset_replay import (CALIBRATION_POSES,
                                                               batch_solution,
                                                               calibrated_heading_sigma,
                                                               observation_sigmas,
                                                               read_planar_dataset, replay,
                                                               replay_params, segments,
                                                               with_heading_sigma)
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.tools.bench import build_parser
from em_exploration_ros.tools.dataset_bench import check_dataset_arguments

POSES = 600


@pytest.fixture(scope="module")
def prefix():
    dataset = read_planar_dataset(gtsam.findExampleDataFile("victoria_park.txt"), POSES)
    return dataset, batch_solution(dataset, replay_params(dataset).slam.prior_sigmas)


def test_the_heading_sigma_is_calibrated_on_the_first_poses_only(prefix):
    """The first 600 poses (all of this prefix) give 0.00595 rad per pose, three times the
    file's 0.002: its heading errors add up over 10 keyframes far beyond its stated noise.
    A longer dataset gives the same: nothing after the calibration drive is read."""
    dataset, _ = prefix
    prior_sigmas = replay_params(dataset).slam.prior_sigmas
    sigma = calibrated_heading_sigma(dataset, prior_sigmas)
    assert sigma == pytest.approx(0.00595, abs=1e-5)
    longer = read_planar_dataset(gtsam.findExampleDataFile("victoria_park.txt"),
                                 CALIBRATION_POSES + 100)
    assert calibrated_heading_sigma(longer, prior_sigmas) == sigma
    calibrated = with_heading_sigma(dataset, sigma)
    before, after = dataset.poses[7].odometry, calibrated.poses[7].odometry
    np.testing.assert_array_equal(after.delta, before.delta)
    np.testing.assert_array_equal(after.covariance[:2, :2], before.covariance[:2, :2])
    assert after.covariance[2, 2] == sigma ** 2 and before.covariance[2, 2] == 4e-6
    assert not after.covariance[2, :2].any() and not after.covariance[:2, 2].any()
    with pytest.raises(ValueError, match="fewer than 11 keyframes"):
        calibrated_heading_sigma(dataset, prior_sigmas, calibration_poses=10)


def test_the_prefix_is_read_as_the_file_states_it(prefix):
    dataset, (poses, landmarks) = prefix
    assert len(dataset.poses) == POSES and dataset.poses[0].odometry is None
    assert dataset.num_detections == 386 and len(landmarks) == 44
    assert poses.shape == (POSES, 3) and np.allclose(poses[0], dataset.start, atol=1e-3)
    # The file's x-y variance 0.4 m^2: range sigma sqrt(0.4), bearing sigma sqrt(0.4) / 10 m.
    assert dataset.range_sigma_m == pytest.approx(0.4 ** 0.5)
    assert dataset.bearing_sigma_rad == pytest.approx(0.4 ** 0.5 / 10)
    assert observation_sigmas((0.01, 0.02)) == (0.01, 0.02)  # a BR line's own sigmas


def test_segments_cut_the_poses_consecutively():
    assert segments(10, 3) == [range(0, 3), range(3, 7), range(7, 10)]
    assert segments(5, 1) == [range(0, 5)]


@pytest.mark.parametrize("robots, precision, recall", [(1, 0.95, 0.87), (2, 0.96, 0.86)])
def test_a_prefix_is_associated_without_identities(prefix, robots, precision, recall):
    dataset, batch = prefix
    sigma = calibrated_heading_sigma(dataset, replay_params(dataset).slam.prior_sigmas)
    summary = replay(with_heading_sigma(dataset, sigma), robots, batch)
    assert set(summary) == {"dataset_poses", "robots", "keyframes", "detections",
                            "dataset_landmarks", "association", "landmarks_created",
                            "landmark_rms_to_batch_m"}
    association = summary["association"]
    assert len(association["robots"]) == robots
    assert association["true_detections"] == summary["detections"] == 386
    # Floors of what the association reaches on this prefix with the calibrated heading
    # sigma (measured: precision 0.960 and 0.970, recall 0.878 and 0.868, landmark RMS to
    # the batch 1.80 m and 0.80 m; recall 0.736 and 0.663 before a track's earlier
    # sightings were named, 0.891 and 0.870 before a loop closure waited for its track),
    # not the goal of 0.98 and 0.9 (docs/results.md).
    assert association["precision"] >= precision and association["recall"] >= recall
    assert 20 <= summary["landmarks_created"] <= 60
    assert summary["landmark_rms_to_batch_m"] < 2.0


def test_a_parameter_file_s_slam_group_reaches_the_robots(prefix):
    """Tracks confirmed at 2 sightings instead of 3 name more of the prefix's readings (the
    dataset holds no clutter); the file's sensor settings give way to the dataset's."""
    dataset, batch = prefix
    sigma = calibrated_heading_sigma(dataset, replay_params(dataset).slam.prior_sigmas)
    calibrated = with_heading_sigma(dataset, sigma)
    base = ExplorationParams().replace(slam={"track_confirm_hits": 2},
                                       sensors={"landmark_ids": True, "sonar_max_range_m": 5})
    assert replay_params(dataset, base).slam.track_confirm_hits == 2
    assert not replay_params(dataset, base).sensors.landmark_ids
    assert replay_params(dataset, base).sensors == replay_params(dataset).sensors
    default = replay(calibrated, 1, batch)["association"]
    sooner = replay(calibrated, 1, batch, base)["association"]
    assert sooner["correct"] > default["correct"] and sooner["recall"] > default["recall"]


def test_em_bench_dataset_writes_the_summary_and_prints_its_last_lines(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    slam:\n      track_confirm_hits: 2\n")
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.bench", "dataset", "victoria_park",
         "--poses", "200", "--robots", "2", "--params", str(params),
         "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["dataset"] == "victoria_park" and summary["robots"] == 2
    assert summary["dataset_poses"] == 200 and summary["wall_time_s"] > 0
    assert summary["slam_params"]["track_confirm_hits"] == 2
    assert summary["slam_params"]["loop_closure_confirm_hits"] == 2  # the default
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("victoria_park: 200 poses, 2 robot(s)")
    assert lines[0].endswith(f"odometry heading sigma "
                             f"{summary['odometry_heading_sigma_rad']:.4f} rad per pose "
                             f"(calibrated)")
    assert lines[1].startswith("association: precision ")
    assert lines[2] == f"landmarks created: {summary['landmarks_created']}"
    assert lines[3].startswith("landmark RMS to the batch solution: ")
    assert lines[4].startswith("wall time: ")


@pytest.mark.parametrize("arguments, message", [
    (["nowhere"], "unknown dataset 'nowhere'; known: victoria_park"),
    (["victoria_park", "--robots", "0"], "--robots must be a positive integer, got '0'"),
    (["victoria_park", "--robots", "27"], "--robots must be at most 26, got 27"),
    (["victoria_park", "--poses", "many"], "--poses must be a positive integer, got 'many'"),
    (["victoria_park", "--poses", "2", "--robots", "3"],
     "--poses 2 cannot make 3 segments of at least one pose"),
])
def test_bad_arguments_are_refused(tmp_path, arguments, message):
    args = build_parser().parse_args(["dataset", *arguments, "--out", str(tmp_path)])
    with pytest.raises(ValueError) as refused:
        check_dataset_arguments(args)
    assert str(refused.value) == message


def test_a_bad_parameter_file_is_refused_in_one_line_with_exit_2(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    slam:\n      track_confirm_hits: 0\n")
    args = build_parser().parse_args(["dataset", "victoria_park", "--params", str(params),
                                      "--out", str(tmp_path / "out")])
    with pytest.raises(ValueError, match="track_confirm_hits"):
        check_dataset_arguments(args)
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.bench", "dataset", "victoria_park",
         "--params", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and result.stdout == ""
    first, hint = result.stderr.strip().splitlines()
    assert first.startswith("em-bench: error: ") and "missing.yaml" in first
    assert hint == "Try 'em-bench --help'."
    assert not (tmp_path / "out").exists()


def test_em_bench_refuses_bad_arguments_in_one_line_with_exit_2(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.bench", "dataset", "victoria_park",
         "--robots", "x", "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip().splitlines() == [
        "em-bench: error: --robots must be a positive integer, got 'x'",
        "Try 'em-bench --help'."]
    assert not (tmp_path / "out").exists()
