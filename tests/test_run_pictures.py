"""The run's pictures hold their layers: the map, the timeline and the animation, checked
on the plotted artists and the legend (not pixels), and em-sim's picture files."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from matplotlib.collections import EllipseCollection
from matplotlib.patches import Circle
from PIL import Image

from em_exploration_ros.core.evaluation.evaluator import TeamEvaluator, landmark_truth
from em_exploration_ros.core.evaluation.map_layers import (TeamMapLayers, evaluation_layers,
                                                           fused_ellipses)
from em_exploration_ros.core.evaluation.map_render import Z, team_map_figure
from em_exploration_ros.core.virtual_map.ellipses import UncertaintyEllipses
from em_exploration_ros.core.evaluation.rendezvous_stats import RendezvousOutcome
from em_exploration_ros.core.evaluation.run_animation import FrameRecorder, render_animation
from em_exploration_ros.core.evaluation.run_timeline import timeline_figure
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, TargetEntry
from em_exploration_ros.core.node_settings import EvaluatorNodeSettings
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.wire_model import seconds_to_nanoseconds, sim_time_s
from em_exploration_ros.core.sessions.effects import Dropped
from em_exploration_ros.core.sessions.evaluator_effects import PublishMetrics
from em_exploration_ros.core.sessions.evaluator_session import EvaluatorSession
from em_exploration_ros.core.sessions.robot_effects import KeyframeEstimate
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.nodes.conversions import (keyframe_covariance_from_msg,
                                                  keyframe_estimate_to_msg, planar_path,
                                                  serialized_path)
from em_exploration_ros.nodes.path_cdr import decode_path
from em_exploration_ros.tools import sim_cli

SMALL_RUN = ["--quiet", "--map-size", "40", "--landmarks", "4", "--max-steps", "20"]


def _layers(rendezvous: tuple[RendezvousOutcome, ...] = ()) -> TeamMapLayers:
    t = np.linspace(0.0, 1.0, 30)
    path = np.column_stack([5 + 30 * t, 10 + 20 * t, np.zeros_like(t)])
    ellipses = UncertaintyEllipses(np.array([[10.0, 10.0], [14.0, 10.0], [18.0, 10.0]]),
                                   np.array([[3.0, 1.5], [2.0, 2.0], [6.0, 3.0]]),
                                   np.array([0.0, 0.5, 1.0]))
    targets = {0: [TargetEntry(10.0, 12.0, "exploration")] * 40
               + [TargetEntry(20.0, 22.0, "revisiting")] * 3,
               1: [TargetEntry(30.0, 5.0, "rendezvous")] * 2}
    return TeamMapLayers(
        width_m=40.0, height_m=40.0, cell_size_m=2.0, explored=np.ones((20, 20), dtype=bool),
        true_landmarks=np.array([[30.0, 30.0], [10.0, 35.0], [20.0, 22.0]]),
        landmark_radius_m=0.1, true_paths={0: path, 1: path + [0.0, 4.0, 0.0]},
        estimated_paths={0: path + 0.3, 1: path + [0.3, 4.3, 0.0]},
        estimated_landmarks={0: np.array([[30.2, 29.9]]), 1: np.array([[10.1, 35.2]])},
        targets=targets, rendezvous=rendezvous,
        given_up={0: [GivenUpEntry(25.0, 25.0, 3.0, "blocked")],
                  1: [GivenUpEntry(5.0, 30.0, 4.0, "deadline"),
                      GivenUpEntry(6.0, 31.0, 9.0, "no progress")]},
        team_uncertainty=ellipses, title="test")


def _markers(axes, marker: str, size: float | None = None) -> list:
    return [line for line in axes.get_lines() if line.get_marker() == marker
            and (size is None or line.get_markersize() == size)]


def _points(lines: list) -> int:
    return sum(len(line.get_xdata()) for line in lines)


def _overlapping_texts(figure) -> list[tuple[str, str]]:
    renderer = figure.canvas.get_renderer()
    texts = [t for t in figure.axes[0].texts if t.get_text()]
    boxes = [t.get_window_extent(renderer) for t in texts]
    return [(texts[i].get_text(), texts[j].get_text()) for i in range(len(texts))
            for j in range(i + 1, len(texts)) if boxes[i].overlaps(boxes[j])]


MET = (RendezvousOutcome(0, 1, 1, 5.0, 20.0, 20.0, "met"),
       RendezvousOutcome(1, 0, 2, 6.0, 20.5, 20.0, "met"),
       RendezvousOutcome(1, 0, 3, 7.0, 20.2, 20.3, "met"),
       RendezvousOutcome(0, 1, 4, 9.0, 35.0, 8.0, "timed_out"))


def test_map_holds_every_layer_and_a_legend_entry_for_each_symbol() -> None:
    layers = _layers(MET)
    figure = team_map_figure(layers)
    axes = figure.axes[0]
    labels = [text.get_text() for text in axes.get_legend().get_texts()]
    assert labels == ["robot 0", "robot 1", "true path", "estimated path", "start", "landmark",
                      "landmark estimate", "exploration target", "revisiting target",
                      "rendezvous target", "target given up", "cell uncertainty (1 sigma)",
                      "rendezvous met", "rendezvous not met"]
    # One start marker per robot, every target, given-up target and landmark estimate.
    assert _points(_markers(axes, "o", 8)) == 2
    assert _points(_markers(axes, "^")) == 40 and _points(_markers(axes, "s")) == 3
    assert _points(_markers(axes, "*")) == 2 and _points(_markers(axes, "X")) == 3
    assert _points(_markers(axes, "x")) == 2
    rings = _markers(axes, "o", 14)
    assert [ring.get_markeredgecolor() for ring in rings] == ["black"] * 3 + ["0.5"]
    # Chosen targets are small; the rendezvous targets and rings lie above them.
    assert all(line.get_markersize() <= 4 for line in _markers(axes, "^") + _markers(axes, "s"))
    assert min(line.get_zorder() for line in rings + _markers(axes, "*")) > Z["targets"]
    # Landmarks are drawn above targets and paths, at a size that shows on a 40 m map.
    discs = [patch for patch in axes.patches if isinstance(patch, Circle)]
    assert len(discs) == 3 and all(disc.get_zorder() > Z["true_path"] for disc in discs)
    assert all(disc.radius >= 0.2 for disc in discs)
    # One ellipse per cell of the team virtual map.
    ellipses = [c for c in axes.collections if isinstance(c, EllipseCollection)]
    assert len(ellipses) == 1 and len(ellipses[0].get_offsets()) == 3
    # One label per meeting place, the reciprocal pair in one label, none over another.
    assert sorted(t.get_text() for t in axes.texts) == ["0\u21921", "0\u21921, 1\u21920 \u00d72"]
    assert _overlapping_texts(figure) == []


def test_crowded_rendezvous_labels_never_overlap() -> None:
    rng = np.random.default_rng(1)
    crowded = tuple(RendezvousOutcome(i % 3, (i + 1) % 3, i, float(i), *rng.uniform(15, 25, 2),
                                      "met" if i % 2 else "open") for i in range(40))
    figure = team_map_figure(_layers(crowded))
    assert _overlapping_texts(figure) == []
    assert len(figure.axes[0].texts) >= 3


def test_legend_leaves_out_what_is_not_drawn() -> None:
    layers = dataclasses.replace(_layers(), given_up={}, team_uncertainty=None,
                                 targets={0: [TargetEntry(10.0, 12.0, "exploration")]})
    labels = [t.get_text() for t in team_map_figure(layers).axes[0].get_legend().get_texts()]
    assert "target given up" not in labels and "cell uncertainty (1 sigma)" not in labels
    assert "revisiting target" not in labels and "rendezvous met" not in labels
    assert {"start", "landmark", "exploration target"} <= set(labels)


def test_fused_ellipses_keep_the_smallest_per_cell() -> None:
    centres = np.array([[1.0, 1.0], [3.0, 1.0]])
    small = UncertaintyEllipses(centres, np.array([[1.0, 1.0], [5.0, 5.0]]), np.zeros(2))
    large = UncertaintyEllipses(centres, np.array([[2.0, 2.0], [4.0, 4.0]]), np.ones(2))
    fused = fused_ellipses({0: small, 1: large})
    assert fused.count == 2
    by_x = {float(c[0]): tuple(a) for c, a in zip(fused.centres, fused.axes)}
    assert by_x == {1.0: (1.0, 1.0), 3.0: (4.0, 4.0)}


def test_evaluation_layers_from_published_truth_hold_every_true_path_and_the_uncertainty():
    # The ROS evaluator's world comes from /world/landmarks: no start poses.
    params = ExplorationParams().replace(world={"width_m": 40.0, "height_m": 40.0,
                                                "num_robots": 2})
    world = landmark_truth(params.world, np.array([0]), np.array([[20.0, 20.0]]), 0.5)
    evaluator = TeamEvaluator(world, params)
    poses = {r: np.array([[5.0 + k, 5.0 + 10 * r, 0.0] for k in range(10)]) for r in (0, 1)}
    for robot, path in poses.items():
        for k, pose in enumerate(path):
            evaluator.record_truth(robot, k * 1.0, pose)
    evaluator.evaluate(9.0, {r: (np.arange(10.0), p) for r, p in poses.items()}, {0: {}, 1: {}})
    covariances = {r: np.tile(np.diag([0.04, 0.04, 0.001]), (10, 1, 1)) for r in (0, 1)}
    given_up = {1: [GivenUpEntry(7.0, 15.0, 4.0, "blocked")]}
    layers = evaluation_layers(evaluator, poses, {0: np.zeros((0, 2)), 1: np.zeros((0, 2))},
                               {}, (), "t", given_up=given_up, pose_covariances=covariances)
    assert sorted(layers.true_paths) == [0, 1]
    assert all(len(layers.true_paths[r]) == 10 for r in (0, 1))
    assert layers.given_up == {1: given_up[1]}
    assert layers.team_uncertainty is not None and layers.team_uncertainty.count > 20
    sigma = layers.team_uncertainty.axes / 6.0  # 3-sigma full axes
    assert np.all(sigma[:, 0] >= sigma[:, 1]) and np.all(sigma[:, 1] > 0.2)
    without = evaluation_layers(evaluator, poses, {}, {}, (), "t")
    assert without.team_uncertainty is None and without.given_up == {}


def _summary(robots: int = 3) -> dict:
    history = [{"sim_time_s": 2.0 * k, "distance_m": 1.0 * k, "explored_ratio": 0.01 * k,
                "loc_rmse_m": 0.01 * k, "landmark_rmse_m": None if k < 3 else 0.02 * k,
                "robot_pose_sigma_m": [0.1 * k + r for r in range(robots)]} for k in range(20)]
    meetings = [{"requester_id": 0, "partner_id": 1, "stamp_s": 11.0},
                {"requester_id": 2, "partner_id": 0, "stamp_s": 27.0}]
    return {"planner": "EM_3", "num_robots": robots, "seed": 0, "stop_reason": "x",
            "history": history, "meetings": meetings}


def test_timeline_holds_each_metric_each_robot_and_the_rendezvous() -> None:
    figure = timeline_figure(_summary())
    explored, rmse, sigma = figure.axes[:3]
    assert [line.get_label() for line in explored.get_lines()][:1] == ["explored ratio"]
    curves = [line for line in rmse.get_lines() if not line.get_label().startswith("_")]
    assert [line.get_label() for line in curves] == ["robot RMSE", "landmark RMSE"]
    robots = [line for line in sigma.get_lines() if line.get_label().startswith("robot")]
    assert [line.get_label() for line in robots] == ["robot 0", "robot 1", "robot 2"]
    assert all(len(line.get_xdata()) == 20 for line in robots)
    for axes in (explored, rmse, sigma):
        marks = [line for line in axes.get_lines() if line.get_linestyle() == ":"]
        assert sorted(line.get_xdata()[0] for line in marks) == [11.0, 27.0]
        assert "meeting: inter-robot factor (2)" in [t.get_text()
                                                     for t in axes.get_legend().get_texts()]


def test_timeline_of_a_summary_without_position_uncertainty_says_so() -> None:
    summary = _summary()
    for sample in summary["history"]:
        del sample["robot_pose_sigma_m"]
    sigma = timeline_figure(summary).axes[2]
    assert "not recorded" in " ".join(t.get_text() for t in sigma.texts)


def test_animation_keeps_evenly_spread_frames_and_writes_them_all(tmp_path: Path) -> None:
    recorder = FrameRecorder(interval_s=2.0, max_frames=6)
    layers = _layers(MET)
    kept = [stamp for stamp in range(0, 21) if recorder.offer(float(stamp), layers)]
    # 0, 2, ..., 12 kept; the seventh frame halves them to 0, 4, 8, 12; then every 4 s.
    assert kept == [0, 2, 4, 6, 8, 10, 12, 16, 20] and recorder.interval_s == 4.0
    recorder.finish(21.0, layers)  # full: the final picture replaces the frame at 20 s
    assert [f.title for f in recorder.frames] == [f"test, t = {t} s"
                                                  for t in (0, 4, 8, 12, 16, 21)]
    gif = render_animation(recorder.frames, tmp_path / "a" / "run.gif", dpi=40)
    with Image.open(gif) as image:
        assert image.n_frames == 6


def test_em_sim_draws_its_pictures_beside_the_summary_unless_told_not_to(tmp_path) -> None:
    assert sim_cli.main(SMALL_RUN + ["--summary", str(tmp_path / "run.json")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "run.json", "run_map.png", "run_timeline.png"]
    quiet = tmp_path / "quiet"
    quiet.mkdir()
    assert sim_cli.main(SMALL_RUN + ["--summary", str(quiet / "run.json"), "--no-pictures",
                                     "--animate", str(quiet / "run.gif")]) == 0
    assert sorted(p.name for p in quiet.iterdir()) == ["run.gif", "run.json"]
    with Image.open(quiet / "run.gif") as image:  # 20 steps of 0.2 s: frames at 2 s, 4 s (the end)
        assert image.n_frames == 2


def test_em_sim_refuses_an_animation_it_cannot_write(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exited:
        sim_cli.main(SMALL_RUN + ["--animate", str(tmp_path / "run.avi")])
    assert exited.value.code == 2 and "must end in .gif" in capsys.readouterr().err


# -- the pose uncertainty the robots publish, in both drivers' pictures ----------------------

def _observer_with_covariances():
    """An observer of 2 robots on a 40 m map fed, keyframe by keyframe, each robot's path,
    landmarks and (robot 0 only) its latest keyframe's covariance, then the truth."""
    params = ExplorationParams().replace(
        world={"width_m": 40.0, "height_m": 40.0, "num_robots": 2, "num_landmarks": 1},
        run={"max_steps": 40})
    step_s, interval = params.motion.time_step_s, params.slam.keyframe_interval_steps
    session = EvaluatorSession(params, EvaluatorNodeSettings(
        metrics_interval_s=interval * step_s, estimate_wait_s=5.0), 0.0, 3.0)
    session.true_landmarks([0], np.array([[20.0, 20.0]]), 0.5, 0.0)

    def pose(robot: int, step: int) -> np.ndarray:
        return np.array([5.0 + 0.2 * step, 5.0 + 10.0 * robot, 0.0])

    def covariance(step: int) -> np.ndarray:
        return np.diag([0.01 + 0.001 * step, 0.02 + 0.001 * step, 1e-4])

    def publish(step: int, wall_s: float = 0.0) -> list:
        keyframes = np.arange(0, step + 1, interval)
        stamps = np.array([sim_time_s(k, step_s) for k in keyframes])
        effects = []
        for robot in (0, 1):
            ns = seconds_to_nanoseconds(sim_time_s(step, step_s))
            effects += session.path_estimate(robot, ns, stamps,
                                             np.array([pose(robot, k) for k in keyframes]),
                                             wall_s)
            effects += session.landmark_estimate(robot, ns, {}, wall_s)
        return effects

    def truth(step: int, wall_s: float = 0.0) -> list:
        return [e for robot in (0, 1)
                for e in session.true_pose(robot, step, pose(robot, step), wall_s)]

    def covariance_of(step: int, wall_s: float = 0.0, value: np.ndarray | None = None) -> list:
        return session.keyframe_covariance(
            0, seconds_to_nanoseconds(sim_time_s(step, step_s)),
            covariance(step) if value is None else value, wall_s)

    return session, interval, publish, truth, covariance_of, covariance


def test_the_observer_records_each_keyframe_covariance_as_published():
    session, interval, publish, truth, covariance_of, covariance = _observer_with_covariances()
    for step in range(2 * interval + 1):
        if step % interval == 0:
            assert covariance_of(step) == []
            publish(step)
        truth(step)
    # Implausible covariances are dropped: older than the last, not symmetric, not finite.
    older = covariance_of(interval)
    assert [type(e) for e in older] == [Dropped] and "older" in older[0].reason
    assert "symmetric" in covariance_of(2 * interval, value=np.array(
        [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))[0].reason
    assert "non-finite" in covariance_of(2 * interval, value=np.full((3, 3), np.nan))[0].reason
    # The next keyframe's path is in, its covariance not yet: the evaluation waits for it.
    step = 3 * interval
    publish(step)
    assert not any(isinstance(e, PublishMetrics) for e in truth(step, 1.0))
    assert any(isinstance(e, PublishMetrics) for e in covariance_of(step, 1.0))
    sigmas = [h.robot_pose_sigma_m for h in session.monitor.summary([[], []], 0.0).history]
    # Each evaluation reads robot 0's newest covariance as of the step before; robot 1
    # published none (NaN: null in the JSON).
    expected = [np.sqrt(covariance(k)[0, 0] + covariance(k)[1, 1])
                for k in range(0, 3 * interval, interval)]
    assert [s[0] for s in sigmas] == pytest.approx(expected)
    assert all(np.isnan(s[1]) for s in sigmas)
    # The map: the team virtual map from robot 0's keyframes (robot 1's have none).
    layers = session.map_layers("t")
    assert layers.team_uncertainty is not None and layers.team_uncertainty.count > 20


def test_em_sims_pictures_draw_the_uncertainty_and_each_robots_sigma_under_the_paths():
    runner = TeamRunner(ExplorationParams().replace(
        world={"width_m": 40.0, "height_m": 40.0, "num_landmarks": 4}, run={"max_steps": 40}))
    summary = runner.run().to_dict()
    layers = runner.map_layers()
    assert layers.team_uncertainty is not None and layers.team_uncertainty.count > 50
    axes = team_map_figure(layers).axes[0]
    ellipses = [c for c in axes.collections if isinstance(c, EllipseCollection)]
    assert len(ellipses) == 1
    assert len(ellipses[0].get_offsets()) == layers.team_uncertainty.count
    # Under the paths and targets (the only lines at the ellipses' level: the border).
    assert ellipses[0].get_zorder() < min(Z["true_path"], Z["estimated_path"], Z["targets"])
    assert {line.get_zorder() for line in axes.get_lines()} & {Z["true_path"], Z["targets"]}
    assert "cell uncertainty (1 sigma)" in [t.get_text() for t in axes.get_legend().get_texts()]
    # Every robot's position sigma at every evaluation once it has a keyframe.
    last = summary["history"][-1]["robot_pose_sigma_m"]
    assert len(last) == 3 and all(0.0 < s < 1.0 for s in last)
    sigma = timeline_figure(summary).axes[2]
    curves = [line for line in sigma.get_lines() if line.get_label().startswith("robot")]
    assert len(curves) == 3 and all(np.isfinite(c.get_ydata()[-1]) for c in curves)
    assert not sigma.texts


def _sigmas(summary: dict) -> np.ndarray:
    """(samples, robots) of the history's robot_pose_sigma_m, null as NaN."""
    return np.array([[np.nan if v is None else v for v in h["robot_pose_sigma_m"]]
                     for h in summary["history"]], dtype=float)


def test_the_ros_evaluator_draws_em_sims_uncertainty_from_the_published_messages():
    """What em-evaluator reads (each robot's estimated_pose and path, converted as the node
    converts them) gives the same layer and history as em-sim's observer."""
    params = ExplorationParams().replace(
        world={"width_m": 40.0, "height_m": 40.0, "num_landmarks": 4}, run={"max_steps": 40})
    runner = TeamRunner(params)
    ros = EvaluatorSession(params, runner.observer.settings, 0.0, 3.0)
    ros.true_world(runner.simulation.world, 0.0)
    observer = runner.observer

    class Relay:
        """em-sim's observer, each input also handed to ``ros`` as em-evaluator reads it
        from the messages (the estimates converted as the robot and the node convert them)."""

        def __getattr__(self, name):  # the rest: em-sim's observer
            return getattr(observer, name)

        def keyframe_covariance(self, robot, stamp_ns, covariance, wall_s):
            message = keyframe_estimate_to_msg(KeyframeEstimate(
                stamp_ns * 1e-9, np.zeros(3), covariance))
            stamp = message.header.stamp
            ros.keyframe_covariance(robot, stamp.sec * 1_000_000_000 + stamp.nanosec,
                                    keyframe_covariance_from_msg(message), wall_s)
            return observer.keyframe_covariance(robot, stamp_ns, covariance, wall_s)

        def path_estimate(self, robot, stamp_ns, stamps_s, poses, wall_s):
            path = decode_path(serialized_path(stamp_ns * 1e-9, stamps_s, poses))
            ros.path_estimate(robot, stamp_ns, *planar_path(path), wall_s)
            return observer.path_estimate(robot, stamp_ns, stamps_s, poses, wall_s)

        def landmark_estimate(self, *args):
            ros.landmark_estimate(*args)
            return observer.landmark_estimate(*args)

        def true_pose(self, *args):
            ros.true_pose(*args)
            return observer.true_pose(*args)

        def command(self, *args):
            ros.command(*args)
            return observer.command(*args)

        def team_update(self, *args):
            ros.team_update(*args)
            return observer.team_update(*args)

    runner.observer = Relay()
    summary = runner.run().to_dict()
    ours = ros.summary(0.0).to_dict()
    np.testing.assert_allclose(_sigmas(ours), _sigmas(summary), rtol=1e-9)
    assert np.isfinite(_sigmas(summary)[-1]).all()
    theirs, mine = observer.map_layers("t").team_uncertainty, ros.map_layers("t").team_uncertainty
    assert theirs is not None and mine is not None and mine.count == theirs.count > 50
    for field in ("centres", "axes", "angles"):
        np.testing.assert_allclose(getattr(mine, field), getattr(theirs, field), rtol=1e-5,
                                   atol=1e-6)
