"""The sonar's sensing model (issue 38, point 1): identities on or off, misses and clutter.

Defaults keep the paper's ideal sonar (every landmark in range, named, nothing else); misses
and clutter come from a stream of their own, so the noise of what is detected does not
change; bad settings are refused by em-sim, em-bench and run_team.sh with exit code 2.
"""
import math
import subprocess

import numpy as np
import pytest
from ros_process import RUN_TEAM

from em_exploration_ros.core.params import ExplorationParams, MotionParams, SensorParams, SlamParams
from em_exploration_ros.core.records.readings import UNIDENTIFIED, LandmarkReading
from em_exploration_ros.core.slam.team_slam import KeyframeBuilder
from em_exploration_ros.core.world.sensors import CLUTTER, SensorSimulator
from em_exploration_ros.core.world.simulation import WorldSimulation
from em_exploration_ros.core.world.world import World
from em_exploration_ros.tools import bench, sim_cli

MOTION = MotionParams()
SCANS = 4000


def _world() -> World:
    """Four landmarks (unsorted ids) around a robot at the origin of a 50 m map."""
    return World(width_m=50.0, height_m=50.0,
                 landmarks=np.array([[14.0, 10.0], [10.0, 14.0], [6.0, 10.0], [30.0, 30.0]]),
                 landmark_ids=np.array([9, 2, 5, 4]), landmark_radius_m=1.0,
                 robot_radius_m=0.8, start_poses=np.array([[10.0, 10.0, 0.0],
                                                           [12.0, 10.0, 0.0]]))


POSE = np.array([10.0, 10.0, 0.3])


def _simulator(seed: int = 0, **sensing) -> SensorSimulator:
    return SensorSimulator(_world(), SensorParams(**sensing), MOTION,
                           np.random.SeedSequence(seed))


def test_the_ideal_sonar_names_every_landmark_in_range_and_nothing_else():
    readings, sources = _simulator().sonar_scan(0, POSE)
    assert [r.landmark_id for r in readings] == [2, 5, 9] and sources == (2, 5, 9)
    assert all(r.identified for r in readings)


def test_misses_and_clutter_leave_the_noise_of_detected_landmarks_unchanged():
    """The k-th scan's range and bearing noise is the same with misses and clutter."""
    ideal, faulty = _simulator(seed=3), _simulator(seed=3, detection_probability=0.5,
                                                   clutter_rate=2.0)
    for _ in range(50):
        truth = {r.landmark_id: r for r in ideal.sonar(0, POSE)}
        readings, sources = faulty.sonar_scan(0, POSE)
        for reading, source in zip(readings, sources):
            if source == CLUTTER:
                assert reading.landmark_id == UNIDENTIFIED
            else:
                assert reading == truth[source]


def test_misses_follow_the_detection_probability():
    sim = _simulator(seed=1, detection_probability=0.7)
    counts = np.array([len(sim.sonar(0, POSE)) for _ in range(SCANS)])
    rate = counts.mean() / 3  # three landmarks in range
    assert abs(rate - 0.7) < 4 * math.sqrt(0.7 * 0.3 / (3 * SCANS))
    assert _simulator(detection_probability=0.0).sonar(0, POSE) == []


def test_clutter_is_poisson_and_uniform_in_range_and_bearing():
    rate = 3.0
    sim = _simulator(seed=2, clutter_rate=rate, landmark_ids=False)
    ranges, bearings, counts = [], [], []
    for _ in range(SCANS):
        readings, sources = sim.sonar_scan(0, POSE)
        clutter = [r for r, s in zip(readings, sources) if s == CLUTTER]
        counts.append(len(clutter))
        ranges += [r.range_m for r in clutter]
        bearings += [r.bearing_rad for r in clutter]
    counts = np.array(counts)
    assert abs(counts.mean() - rate) < 4 * math.sqrt(rate / SCANS)
    assert abs(counts.var() - rate) < 0.3  # Poisson: variance = mean
    ranges, bearings = np.array(ranges), np.array(bearings)
    assert ranges.min() >= 0.0 and ranges.max() <= 7.5
    assert bearings.min() > -math.pi and bearings.max() <= math.pi
    for values, low, high in ((ranges, 0.0, 7.5), (bearings, -math.pi, math.pi)):
        histogram, _ = np.histogram(values, bins=5, range=(low, high))
        np.testing.assert_allclose(histogram / len(values), 0.2, atol=0.02)


def test_without_identities_a_scan_is_unnamed_and_in_bearing_order():
    readings, sources = _simulator(seed=4, landmark_ids=False, clutter_rate=2.0).sonar_scan(
        0, POSE)
    assert all(r.landmark_id == UNIDENTIFIED and not r.identified for r in readings)
    bearings = [r.bearing_rad for r in readings]
    assert bearings == sorted(bearings)
    assert sorted(s for s in sources if s != CLUTTER) == [2, 5, 9]


def test_misses_and_clutter_repeat_with_the_seed_and_differ_between_robots():
    settings = {"detection_probability": 0.6, "clutter_rate": 1.5}
    first, second = _simulator(seed=8, **settings), _simulator(seed=8, **settings)
    scans = [first.sonar_scan(0, POSE) for _ in range(20)]
    for _ in range(5):  # another robot's draws do not change robot 0's
        second.sonar_scan(1, POSE)
    assert scans == [second.sonar_scan(0, POSE) for _ in range(20)]
    other = _simulator(seed=9, **settings)
    assert scans != [other.sonar_scan(0, POSE) for _ in range(20)]


def test_the_world_keeps_each_detection_s_truth_for_the_evaluator():
    params = ExplorationParams().replace(sensors={"landmark_ids": False, "clutter_rate": 2.0,
                                                  "detection_probability": 0.8})
    world = WorldSimulation(params)
    frame = world.sense(0)
    sources = world.detection_sources(0)
    assert len(sources) == len(frame.landmarks)
    assert all(not r.identified for r in frame.landmarks)


def test_a_keyframe_keeps_only_named_detections():
    builder = KeyframeBuilder(0, SlamParams())
    named = LandmarkReading(3, 4.0, 0.1, 1e-6, 1e-6)
    unnamed = LandmarkReading(UNIDENTIFIED, 2.0, -0.4, 1e-6, 1e-6)
    keyframe = builder.add_step(0, 0.0, None, [unnamed, named], [])
    assert keyframe.landmarks == (named,)
    # Without identities the robot's association names them next: all are kept.
    keeping = KeyframeBuilder(0, SlamParams(), keep_unidentified=True)
    assert keeping.add_step(0, 0.0, None, [unnamed, named], []).landmarks == (unnamed, named)


@pytest.mark.parametrize("sensing, message", [
    ({"detection_probability": 1.5}, "SensorParams.detection_probability = 1.5 is outside"),
    ({"detection_probability": -0.1}, "SensorParams.detection_probability = -0.1 is outside"),
    ({"clutter_rate": -1.0}, "SensorParams.clutter_rate = -1.0 is outside"),
    ({"landmark_ids": "off"}, "SensorParams.landmark_ids must be true or false"),
])
def test_parameters_refuse_bad_sensing(sensing, message):
    with pytest.raises(ValueError, match=message):
        ExplorationParams().replace(sensors=sensing)


def test_em_sim_flags_set_the_sensing():
    args = sim_cli.build_parser().parse_args(["--landmark-ids", "off", "--detection-prob",
                                              "0.9", "--clutter-rate", "0.5"])
    sensors = sim_cli.params_from_args(args).sensors
    assert (sensors.landmark_ids, sensors.detection_probability, sensors.clutter_rate) == (
        False, 0.9, 0.5)
    assert sim_cli.params_from_args(sim_cli.build_parser().parse_args([])) == (
        ExplorationParams())


@pytest.mark.parametrize("args, message", [
    (["--detection-prob", "1.5"], "argument --detection-prob: must be in [0, 1], got 1.5"),
    (["--detection-prob", "-0.1"], "argument --detection-prob: must be in [0, 1], got -0.1"),
    (["--detection-prob", "nan"], "argument --detection-prob: must be in [0, 1], got nan"),
    (["--clutter-rate", "-1"], "argument --clutter-rate: must be in [0, 1000], got -1"),
    (["--landmark-ids", "maybe"], "argument --landmark-ids: invalid choice: 'maybe'"),
])
def test_em_sim_and_em_bench_refuse_bad_sensing(capsys, args, message):
    """One line says what is wrong, a second where to read on (no usage text above them:
    argparse's own put the error under 11 lines of it), exit code 2."""
    for main, prefix, prog in ((sim_cli.main, [], "em-sim"),
                               (bench.main, ["planners"], "em-bench planners")):
        with pytest.raises(SystemExit) as exit_info:
            main([*prefix, *args])
        assert exit_info.value.code == 2
        error, hint = capsys.readouterr().err.splitlines()
        assert error.startswith(f"{prog}: error: ") and message in error, error
        assert hint == f"Try '{prog} --help'."


@pytest.mark.parametrize("args, message", [
    (["--detection-prob", "1.5"], "--detection-prob must be in [0, 1], got '1.5'"),
    (["--clutter-rate", "-1"], "--clutter-rate expects a number, got '-1'"),
    (["--landmark-ids", "maybe"], "--landmark-ids must be on or off, got 'maybe'"),
    (["--landmark-ids"], "--landmark-ids needs a value"),
])
def test_run_team_refuses_bad_sensing(args, message):
    result = subprocess.run(["bash", str(RUN_TEAM), *args], capture_output=True, text=True,
                            timeout=20.0, stdin=subprocess.DEVNULL)
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and message in errors[0], result.stderr


def test_run_team_help_lists_the_sensing_flags():
    result = subprocess.run(["bash", str(RUN_TEAM), "--help"], capture_output=True, text=True,
                            timeout=20.0, stdin=subprocess.DEVNULL)
    for flag in ("--landmark-ids on|off", "--detection-prob P", "--clutter-rate R"):
        assert flag in result.stdout
