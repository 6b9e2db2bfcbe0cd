"""A planar SLAM dataset replayed through the team's own data association and SLAM, the
dataset's landmark identities withheld, and scored against them.

The dataset is a file that ``gtsam.load2D`` reads (e.g. Victoria Park, shipped with GTSAM: a
car's odometry between consecutive poses and its laser's bearing-range observations of trees,
each observation naming its tree, the dataset's association). One robot, or K robots of a
decentralized team, drive it:

* **Robots.** The poses are cut into K consecutive segments; robot k drives segment k, from
  its first pose. Each robot runs ``TeamSlam`` (iSAM2, ``landmark_ids`` off) and
  ``OwnLandmarks`` as a robot of the team does: a keyframe's detections, without identity,
  are associated with its own landmarks (JCBB, tentative tracks), the keyframe passes through
  ``TeamWireFormat`` (what the teammates receive), goes into its graph, one SLAM update, then
  the teammates' landmarks are matched to its own (``match_teammates``, pairwise
  consistency). A keyframe is cut at the segment's first pose and at every pose with
  observations; the odometry of the poses between is accumulated (``OdometryAccumulator``,
  first order), as a robot accumulates its steps between keyframes.
* **A common frame.** The dataset has no robot-to-robot detection. Robot 0's first keyframe
  is anchored at the dataset's first pose (``TeamSlam``'s prior); every other robot knows its
  start in that frame (as the paper's robots know their launch poses): its first keyframe
  carries a teammate reading of robot 0's first keyframe, the relative pose of the two starts
  in the batch solution (below), with the prior's sigmas. Nothing else ties the robots:
  which landmarks they share is found only by ``match_teammates``.
* **Links.** Perfect: in lockstep ticks, every keyframe a robot made at tick t is in every
  teammate's graph at tick t + 1 (added, one update, matching), as the team's records are
  applied one step after they were made.
* **Noise.** The sensors' noise is the dataset's factor noise: one bearing and range sigma
  for every observation (``ValueError`` otherwise), the odometry's per pose; em-bench
  dataset replaces the odometry's heading sigma by one calibrated on the first
  ``CALIBRATION_POSES`` poses (:func:`calibrated_heading_sigma`, :func:`with_heading_sigma`):
  Victoria Park's stated 0.002 rad per pose allows 0.02 rad over 100 poses, where its
  heading drifts about 0.1 rad against the batch solution, mostly a bias.

Scoring (truth side only: nothing of it reaches a robot):

* ``association``: ``association_stats.team_association`` with the dataset's association as
  the truth of each detection (a keyframe's index is its step, ``keyframe_interval_steps``
  1): precision and recall as in em-sim.
* ``landmarks_created``: the robots' own landmarks, summed.
* ``landmark_rms_to_batch_m``: each robot's own landmarks in its own graph (which holds the
  team's data) against the batch solution of the same poses with the dataset's association,
  each standing for the dataset landmark most of its readings came from; RMS over all
  robots' [m]. The batch solution: Levenberg-Marquardt on the whole graph (a prior on the
  first pose), started from an incremental iSAM2 pass (``BATCH_CHUNK_POSES`` poses per
  update): started from dead reckoning it stops in a local minimum (Victoria Park: error
  1.05e5 against 2339).

Frames and units: the dataset's frame; poses ``(x [m], y [m], theta [rad])``, observations
``(bearing [rad, body frame], range [m])``.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from em_exploration_ros.core.geometry import between, wrap_angle
from em_exploration_ros.core.params import BOUND_95_TO_SIGMA, ExplorationParams
from em_exploration_ros.core.records.readings import (UNIDENTIFIED, KeyframeMeasurements,
                                                      LandmarkReading, OdometryReading,
                                                      TeammateReading, sonar_variances)
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.slam.own_landmarks import RECENT_KEYFRAMES, OwnLandmarks
from em_exploration_ros.core.slam.team_slam import (OdometryAccumulator, TeamSlam,
                                                    body_to_map_covariance, landmark_owner)
from em_exploration_ros.core.evaluation.association_stats import (KeyframeScans,
                                                                  landmark_sources,
                                                                  team_association)

#: Poses per iSAM2 update of the pass that starts the batch solution (Victoria Park: 20 reach
#: the optimum, error 2339, in 11 s; 100 stop at 4200).
BATCH_CHUNK_POSES = 20
#: The range [m] at which ``load2D`` means a ``LANDMARK`` line's x-y variance to hold
#: (:func:`observation_sigmas`).
LOAD2D_XY_RANGE_M = 10.0
#: Robots of a team at most (``TeamSlam``'s limit).
MAX_ROBOTS = 26
#: Poses of the calibration drive of :func:`calibrated_heading_sigma` (Victoria Park: the
#: first 600 of 6969, 300 m of driving, 44 of its 151 trees).
CALIBRATION_POSES = 600


@dataclass(frozen=True)
class DatasetPose:
    """One pose of the dataset: the odometry from the previous pose (None at the first), its
    observations ``(D, 2)`` (bearing [rad], range [m]) and the dataset landmark of each."""

    odometry: OdometryReading | None
    observations: np.ndarray
    sources: tuple[int, ...]


@dataclass(frozen=True)
class PlanarDataset:
    """A ``load2D`` dataset cut to its first poses: the poses in chain order with their keys
    in the file, the odometry's between factors, the first pose ``start`` (3,) of ``load2D``'s
    initial values, and one noise of every observation (:func:`observation_sigmas`)."""

    poses: tuple[DatasetPose, ...]
    pose_keys: tuple[int, ...]
    odometry: gtsam.NonlinearFactorGraph
    start: np.ndarray
    bearing_sigma_rad: float
    range_sigma_m: float

    @property
    def num_detections(self) -> int:
        """Observations of the poses kept."""
        return sum(len(pose.sources) for pose in self.poses)

    @property
    def max_range_m(self) -> float:
        """The farthest observation [m] (0 without any)."""
        return max((float(pose.observations[:, 1].max()) for pose in self.poses
                    if len(pose.sources)), default=0.0)


def observation_sigmas(loaded: Sequence[float]) -> tuple[float, float]:
    """Bearing [rad] and range [m] sigma of the file's observations from the sigmas
    ``load2D`` gave their factors. A ``LANDMARK`` line (Victoria Park's) states an isotropic
    x-y variance v of the landmark's position; ``load2D`` takes sqrt(v) as the range sigma
    and, meaning "the uncertainty at a range of 10 m" (its comment), sqrt(v / 10) as the
    bearing sigma, which is not that: sqrt(v) / 10 is (0.063 rad for v = 0.4 m^2 where it
    gives 0.2 rad). Such pairs (bearing^2 * 10 = range^2) are taken as the file states them;
    any other pair (a ``BR`` line's own sigmas) as loaded."""
    bearing, range_m = float(loaded[0]), float(loaded[1])
    if math.isclose(bearing ** 2 * LOAD2D_XY_RANGE_M, range_m ** 2, rel_tol=1e-9):
        return range_m / LOAD2D_XY_RANGE_M, range_m
    return bearing, range_m


def read_planar_dataset(path: str, max_poses: int | None = None) -> PlanarDataset:
    """The dataset at ``path`` (``gtsam.load2D`` format: between factors of consecutive poses,
    bearing-range factors), its first ``max_poses`` poses if given. ``ValueError`` if the
    odometry is not one chain or the observations' noise differs between them."""
    graph, initial = gtsam.load2D(path)
    odometry = {}
    observations: dict[int, list[gtsam.BearingRangeFactor2D]] = {}
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.BetweenFactorPose2):
            odometry[factor.keys()[0]] = factor
        elif isinstance(factor, gtsam.BearingRangeFactor2D):
            observations.setdefault(factor.keys()[0], []).append(factor)
    chain = [min(initial.keys())]
    while chain[-1] in odometry and (max_poses is None or len(chain) < max_poses):
        chain.append(odometry[chain[-1]].keys()[1])
    if max_poses is None and len(chain) != len(odometry) + 1:
        raise ValueError(f"{path}: the odometry is not one chain of consecutive poses")
    kept = gtsam.NonlinearFactorGraph()
    sigmas = set()
    poses = []
    for position, key in enumerate(chain):
        reading = None
        if position:
            factor = odometry[chain[position - 1]]
            kept.push_back(factor)
            measured = factor.measured()
            delta = np.array([measured.x(), measured.y(), measured.theta()])
            reading = OdometryReading(delta, body_to_map_covariance(
                delta, factor.noiseModel().covariance()))
        seen = observations.get(key, [])
        sigmas.update(tuple(factor.noiseModel().sigmas()) for factor in seen)
        poses.append(DatasetPose(
            reading, np.array([[f.measured().bearing().theta(), f.measured().range()]
                               for f in seen]).reshape(-1, 2),
            tuple(gtsam.symbolIndex(f.keys()[1]) for f in seen)))
    if len(sigmas) > 1:
        raise ValueError(f"{path}: the observations' noise differs ({len(sigmas)} kinds); "
                         f"the team's readings share one")
    bearing_sigma, range_sigma = observation_sigmas(sigmas.pop() if sigmas else (0.0, 0.0))
    start = initial.atPose2(chain[0])
    return PlanarDataset(tuple(poses), tuple(chain), kept,
                         np.array([start.x(), start.y(), start.theta()]), bearing_sigma,
                         range_sigma)


def calibrated_heading_sigma(dataset: PlanarDataset, prior_sigmas: Sequence[float],
                             calibration_poses: int = CALIBRATION_POSES,
                             window_keyframes: int = RECENT_KEYFRAMES) -> float:
    """The odometry's heading sigma [rad per pose] calibrated on the dataset's first
    ``calibration_poses`` poses, as a robot would on a calibration drive with surveyed
    landmarks: the batch solution of those poses alone (:func:`batch_solution`, the
    dataset's association), the odometry's heading error against it summed over windows
    of ``window_keyframes`` consecutive keyframes (the span over which ``OwnLandmarks``
    gates a landmark on the odometry since it was last seen), and the per-pose sigma of a
    random walk with that mean square over the window's poses. Nothing after the segment
    is read."""
    segment = dataclasses.replace(
        dataset, poses=dataset.poses[:calibration_poses],
        pose_keys=dataset.pose_keys[:calibration_poses])
    poses, _ = batch_solution(segment, prior_sigmas)
    errors = np.array([0.0] + [wrap_angle(between(poses[i - 1], poses[i])[2]
                                          - segment.poses[i].odometry.delta[2])
                               for i in range(1, len(segment.poses))])
    keyframes = [i for i, pose in enumerate(segment.poses) if pose.sources]
    cuts = keyframes[::window_keyframes]
    windows = [(a, b) for a, b in zip(cuts[:-1], cuts[1:])]
    if not windows:
        raise ValueError(f"{calibration_poses} poses hold fewer than {window_keyframes + 1} "
                         f"keyframes to calibrate on")
    squared = sum(errors[a + 1:b + 1].sum() ** 2 for a, b in windows)
    return float(np.sqrt(squared / sum(b - a for a, b in windows)))


def with_heading_sigma(dataset: PlanarDataset, sigma_rad: float) -> PlanarDataset:
    """``dataset`` with every odometry reading's heading variance ``sigma_rad ** 2`` [rad^2]
    (its x and y as the file states them; the heading is the same in every frame). The
    batch solution keeps the file's factors (``dataset.odometry``)."""
    def recalibrated(pose: DatasetPose) -> DatasetPose:
        if pose.odometry is None:
            return pose
        covariance = np.array(pose.odometry.covariance, dtype=float)
        covariance[2, :] = covariance[:, 2] = 0.0
        covariance[2, 2] = sigma_rad ** 2
        return dataclasses.replace(pose, odometry=OdometryReading(pose.odometry.delta,
                                                                  covariance))
    return dataclasses.replace(dataset, poses=tuple(recalibrated(p) for p in dataset.poses))


def replay_params(dataset: PlanarDataset, base: ExplorationParams | None = None
                  ) -> ExplorationParams:
    """The team's parameters for ``dataset``: its observation noise (the shared reading noise
    of the team stream), a sonar range of its farthest observation, no landmark identities,
    teammate readings (the starts) with the prior's sigmas; SLAM and association as in
    ``base`` (a parameter file's; default the defaults)."""
    params = base if base is not None else ExplorationParams()
    prior = params.slam.prior_sigmas
    return params.replace(sensors={
        "landmark_ids": False,
        "sonar_max_range_m": max(math.ceil(dataset.max_range_m), 1),
        "sonar_bearing_bound_rad": dataset.bearing_sigma_rad * BOUND_95_TO_SIGMA,
        "sonar_range_bound_m": dataset.range_sigma_m * BOUND_95_TO_SIGMA,
        "robot_obs_xy_bound_m": prior[0] * BOUND_95_TO_SIGMA,
        "robot_obs_theta_bound_rad": prior[2] * BOUND_95_TO_SIGMA})


def batch_solution(dataset: PlanarDataset, prior_sigmas: Sequence[float]
                   ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Poses ``(N, 3)`` in chain order and landmarks ``{dataset landmark: (2,)}`` of the
    least-squares solution of the dataset's odometry and observations (the dataset's
    association, :func:`observation_sigmas`) with a prior (``prior_sigmas``) on the first
    pose at ``dataset.start``: Levenberg-Marquardt from an incremental iSAM2 pass (module
    docstring)."""
    observation_noise = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([dataset.bearing_sigma_rad, dataset.range_sigma_m]))
    first = dataset.pose_keys[0]
    prior = gtsam.PriorFactorPose2(first, gtsam.Pose2(*dataset.start),
                                   gtsam.noiseModel.Diagonal.Sigmas(np.array(prior_sigmas)))
    whole = gtsam.NonlinearFactorGraph()
    isam = gtsam.ISAM2()
    estimate = gtsam.Values()
    factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    factors.push_back(prior)
    values.insert(first, gtsam.Pose2(*dataset.start))

    def current(key: int) -> gtsam.Pose2:
        return (values if values.exists(key) else estimate).atPose2(key)

    for position, (key, pose) in enumerate(zip(dataset.pose_keys, dataset.poses)):
        if position:
            between_factor = dataset.odometry.at(position - 1)
            factors.push_back(between_factor)
            values.insert(key, current(dataset.pose_keys[position - 1]).compose(
                between_factor.measured()))
        for (bearing, range_m), source in zip(pose.observations, pose.sources):
            point = gtsam.symbol("l", source)
            factors.push_back(gtsam.BearingRangeFactor2D(
                key, point, gtsam.Rot2.fromAngle(bearing), range_m, observation_noise))
            if not (values.exists(point) or estimate.exists(point)):
                values.insert(point, current(key).transformFrom(gtsam.Point2(
                    range_m * math.cos(bearing), range_m * math.sin(bearing))))
        if (position + 1) % BATCH_CHUNK_POSES == 0 or position + 1 == len(dataset.poses):
            whole.push_back(factors)
            isam.update(factors, values)
            estimate = isam.calculateEstimate()
            factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    solution = gtsam.LevenbergMarquardtOptimizer(whole, estimate,
                                                 gtsam.LevenbergMarquardtParams()).optimize()
    poses = np.array([[p.x(), p.y(), p.theta()] for p in
                      (solution.atPose2(key) for key in dataset.pose_keys)]).reshape(-1, 3)
    landmarks = {gtsam.symbolIndex(key): np.asarray(solution.atPoint2(key), dtype=float)
                 for key in solution.keys() if gtsam.symbolChr(key) == ord("l")}
    return poses, landmarks


def segments(num_poses: int, num_robots: int) -> list[range]:
    """The K consecutive segments of ``num_poses`` poses, as equal as can be."""
    bounds = np.linspace(0, num_poses, num_robots + 1).round().astype(int)
    return [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


class _ReplayRobot:
    """One robot driving its segment of the dataset: its graph and its association, fed in
    the order ``RobotAgent`` feeds them (the teammates' records of the previous step, one
    update and matching; then its own keyframe associated, rounded as sent, one update and
    matching)."""

    def __init__(self, robot_id: int, num_robots: int, params: ExplorationParams,
                 anchor: np.ndarray) -> None:
        self.robot_id = robot_id
        self.slam = TeamSlam(robot_id, num_robots, params.slam, anchor, landmark_ids=False)
        self.associator = OwnLandmarks(self.slam, params.sensors)
        self.wire = TeamWireFormat(params)

    def receive(self, keyframes: Sequence[KeyframeMeasurements]) -> None:
        """The teammates' keyframes of the previous tick: added, one update, matching."""
        if not keyframes:
            return
        for keyframe in keyframes:
            self.slam.add_keyframe(keyframe)
        self._update()

    def own(self, keyframe: KeyframeMeasurements) -> KeyframeMeasurements:
        """An own keyframe of unidentified detections: associated, as sent, in the graph;
        returns it as the teammates receive it."""
        keyframe = self.wire.keyframe(self.associator.associate(keyframe))
        self.slam.add_keyframe(keyframe)
        self._update()
        return keyframe

    def _update(self) -> None:
        self.slam.update()
        self.associator.match_teammates()


def _keyframes(robot_id: int, dataset: PlanarDataset, segment: range,
               variances: tuple[float, float], start_tie: TeammateReading | None
               ) -> list[tuple[KeyframeMeasurements, int]]:
    """Robot ``robot_id``'s keyframes over ``segment`` with the pose each was cut at: the
    first pose (with ``start_tie``, if any) and every pose with observations, which become
    unidentified readings with the sonar's ``variances`` (range [m^2], bearing [rad^2])."""
    accumulator = OdometryAccumulator()
    keyframes = []
    for position in segment:
        pose = dataset.poses[position]
        if position != segment.start:
            accumulator.add(pose.odometry)
            if not pose.sources:
                continue
        delta, covariance = accumulator.take()
        index = len(keyframes)
        keyframes.append((KeyframeMeasurements(
            robot_id=robot_id, index=index, stamp_s=float(index), is_first=index == 0,
            previous_index=index - 1, odom_delta=delta, odom_covariance=covariance,
            landmarks=tuple(LandmarkReading(UNIDENTIFIED, float(range_m), float(bearing),
                                            *variances)
                            for bearing, range_m in pose.observations),
            teammates=(start_tie,) if index == 0 and start_tie is not None else ()),
            position))
    return keyframes


def replay(dataset: PlanarDataset, num_robots: int,
           batch: tuple[np.ndarray, dict[int, np.ndarray]],
           base: ExplorationParams | None = None) -> dict[str, Any]:
    """Drive ``dataset`` with ``num_robots`` robots (module docstring) with the SLAM and
    association parameters of ``base`` (:func:`replay_params`), scored against ``batch``
    (:func:`batch_solution` with the prior's sigmas); returns the summary:
    ``dataset_poses``, ``robots``, ``keyframes``, ``detections``, ``dataset_landmarks``
    (observed in the poses kept), ``association``, ``landmarks_created``,
    ``landmark_rms_to_batch_m``. ``ValueError`` for fewer than one robot, more than
    ``MAX_ROBOTS``, or fewer poses than robots."""
    if not 1 <= num_robots <= MAX_ROBOTS:
        raise ValueError(f"robots must be in [1, {MAX_ROBOTS}], got {num_robots}")
    if len(dataset.poses) < num_robots:
        raise ValueError(f"{len(dataset.poses)} poses cannot make {num_robots} segments")
    params = replay_params(dataset, base)
    batch_poses, batch_landmarks = batch
    cuts = segments(len(dataset.poses), num_robots)
    robots = [_ReplayRobot(r, num_robots, params, dataset.start) for r in range(num_robots)]
    plans = []
    for robot, segment in zip(robots, cuts):
        tie = None
        if robot.robot_id:
            tie = TeammateReading(0, between(batch_poses[segment.start], batch_poses[0]),
                                  np.diag(np.square(params.slam.prior_sigmas)))
        plans.append(_keyframes(robot.robot_id, dataset, segment,
                                sonar_variances(params.sensors), tie))
    scans = {(keyframe.robot_id, keyframe.index): (keyframe.landmarks,
                                                   dataset.poses[position].sources)
             for plan in plans for keyframe, position in plan}
    sent: list[list[KeyframeMeasurements]] = [[] for _ in robots]
    for tick in range(max(len(plan) for plan in plans) + 1):
        for robot in robots:
            robot.receive([keyframe for other, made in enumerate(sent)
                           if other != robot.robot_id for keyframe in made])
        sent = [[robot.own(plan[tick][0])] if tick < len(plan) else []
                for robot, plan in zip(robots, plans)]
    slams = [robot.slam for robot in robots]
    return {
        "dataset_poses": len(dataset.poses), "robots": num_robots,
        "keyframes": sum(len(plan) for plan in plans),
        "detections": dataset.num_detections,
        "dataset_landmarks": len(batch_landmarks),
        "association": team_association(slams, scans, 1),
        "landmarks_created": sum(1 for slam in slams for landmark in slam.landmark_estimates()
                                 if landmark_owner(landmark) == slam.robot_id),
        "landmark_rms_to_batch_m": landmark_rms_to_batch(slams, scans, batch_landmarks)}


def landmark_rms_to_batch(slams: Sequence[TeamSlam], scans: KeyframeScans,
                          batch_landmarks: dict[int, np.ndarray]) -> float:
    """RMS [m] of each robot's own landmarks in its own graph against the batch landmark
    each stands for (by the majority of its readings); NaN when there is none."""
    squared = []
    for slam in slams:
        stands_for, _ = landmark_sources(slam.landmark_readings(), scans, 1)
        for landmark, point in slam.landmark_estimates().items():
            if landmark_owner(landmark) == slam.robot_id and stands_for.get(landmark) \
                    in batch_landmarks:
                squared.append(np.sum((point - batch_landmarks[stands_for[landmark]]) ** 2))
    return float(np.sqrt(np.mean(squared))) if squared else float("nan")
