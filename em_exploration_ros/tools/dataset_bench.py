"""em-bench dataset: a real dataset through the team's own data association and SLAM.

``em-bench dataset victoria_park [--robots K] [--poses N] [--params FILE] --out DIR`` reads
GTSAM's Victoria
Park dataset (``gtsam.findExampleDataFile``), withholds its landmark identities, drives it
with one robot or K robots of a decentralized team (consecutive segments of the trajectory,
core/evaluation/dataset_replay.py) with the odometry's heading sigma calibrated on the first
poses and the SLAM and association parameters of FILE (default: the defaults), and writes
DIR/summary.json: the association's precision and recall against the dataset's association,
the landmarks created, the landmarks' RMS against the batch least-squares solution, the
calibrated heading sigma, the SLAM parameters used and the wall times. Its last lines are
printed.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import gtsam

from em_exploration_ros.core.evaluation.association_stats import association_line
from em_exploration_ros.core.evaluation.dataset_replay import (MAX_ROBOTS, batch_solution,
                                                               calibrated_heading_sigma,
                                                               read_planar_dataset, replay,
                                                               with_heading_sigma)
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.tools.bench_trials import write_json

#: The datasets em-bench knows: name -> file of GTSAM's example data.
DATASETS = {"victoria_park": "victoria_park.txt"}

DATASET_HELP = "a real dataset (Victoria Park) through the team's association and SLAM"


def add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    """Description, arguments and handler of ``dataset``, the em-bench subcommand's parser."""
    parser.description = __doc__.split("\n\n")[1].replace("\n", " ")
    parser.add_argument("name", help=f"the dataset: {', '.join(DATASETS)}")
    parser.add_argument("--robots", default="1", metavar="K",
                        help=f"robots, each driving one of K consecutive segments "
                        f"(1 to {MAX_ROBOTS}; default 1)")
    parser.add_argument("--poses", metavar="N",
                        help="only the dataset's first N poses (default: all)")
    parser.add_argument("--params", type=Path, metavar="FILE",
                        help="ROS 2 parameter YAML file whose slam group (association and "
                        "SLAM) the robots use; the sensor's noise and range, and no "
                        "identities, come from the dataset")
    parser.add_argument("--out", type=Path, required=True, help="output folder")


def _positive(option: str, text: str | None) -> int | None:
    """``text`` as a positive integer (None stays None); ValueError naming ``option``."""
    if text is None:
        return None
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{option} must be a positive integer, got {text!r}") from None
    if value < 1:
        raise ValueError(f"{option} must be a positive integer, got {text!r}")
    return value


def check_dataset_arguments(args: argparse.Namespace
                            ) -> tuple[str, int, int | None, ExplorationParams]:
    """The dataset's file, robots, poses and parameters of ``args``; ValueError (one line,
    a parameter file's ``ParamsFileError`` too) naming the first argument that cannot give
    a run (``--out`` is em-bench's to check)."""
    if args.name not in DATASETS:
        raise ValueError(f"unknown dataset {args.name!r}; known: {', '.join(DATASETS)}")
    robots = _positive("--robots", args.robots)
    if robots > MAX_ROBOTS:
        raise ValueError(f"--robots must be at most {MAX_ROBOTS}, got {robots}")
    poses = _positive("--poses", args.poses)
    if poses is not None and poses < robots:
        raise ValueError(f"--poses {poses} cannot make {robots} segments of at least one pose")
    params = load_params(args.params) if args.params is not None else ExplorationParams()
    return DATASETS[args.name], robots, poses, params


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The printed end of a run: what ran, the association, landmarks, RMS, wall time."""
    return [f"{summary['dataset']}: {summary['dataset_poses']} poses, {summary['robots']} "
            f"robot(s), {summary['keyframes']} keyframes, {summary['detections']} "
            f"observations of {summary['dataset_landmarks']} landmarks, odometry heading "
            f"sigma {summary['odometry_heading_sigma_rad']:.4f} rad per pose (calibrated)",
            association_line(summary["association"]),
            f"landmarks created: {summary['landmarks_created']}",
            f"landmark RMS to the batch solution: {summary['landmark_rms_to_batch_m']:.3f} m",
            f"wall time: {summary['wall_time_s']:.1f} s (batch solution "
            f"{summary['batch_wall_time_s']:.1f} s)"]


def run_dataset(args: argparse.Namespace, file_name: str, robots: int,
                poses: int | None, params: ExplorationParams) -> int:
    """Run the replay of the checked arguments, write DIR/summary.json (DIR ready), print
    its last lines."""
    started = time.perf_counter()
    dataset = read_planar_dataset(gtsam.findExampleDataFile(file_name), poses)
    slam = params.slam  # the replay's: the dataset sets the sensors alone
    batch = batch_solution(dataset, slam.prior_sigmas)
    batch_s = time.perf_counter() - started
    heading_sigma = calibrated_heading_sigma(dataset, slam.prior_sigmas)
    summary = {"dataset": args.name,
               **replay(with_heading_sigma(dataset, heading_sigma), robots, batch, params),
               "odometry_heading_sigma_rad": heading_sigma,
               "slam_params": dataclasses.asdict(slam)}
    summary["batch_wall_time_s"] = batch_s
    summary["wall_time_s"] = time.perf_counter() - started
    write_json(args.out / "summary.json", summary)
    print("\n".join(summary_lines(summary)))
    return 0
