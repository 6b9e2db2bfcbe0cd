"""What em-evaluator writes and publishes from its session's effects: the metrics message,
the summary JSON (the summary so far while the run goes on, then the final one), and the
pictures beside it (the team map, and the timeline ``<stem>_timeline.png`` as em-sim draws
beside its summary)."""
from __future__ import annotations

from pathlib import Path

from em_exploration_msgs.msg import ExplorationMetrics

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.summary import RunSummary
from em_exploration_ros.core.output_paths import write_replacing
from em_exploration_ros.core.sessions.evaluator_effects import PublishMetrics
from em_exploration_ros.nodes.conversions import WORLD_FRAME, seconds_to_time

#: Suffix of the timeline picture beside a summary ``<stem>.json``.
TIMELINE_SUFFIX = "_timeline.png"


def metrics_to_msg(effect: PublishMetrics) -> ExplorationMetrics:
    """The team metrics of one evaluation as /evaluation/metrics carries them (frame
    ``world``, stamped with the evaluated step's simulation time)."""
    metrics = effect.metrics
    message = ExplorationMetrics(
        explored_ratio=metrics.explored_ratio, distance_m=metrics.distance_m,
        loc_rmse_m=metrics.loc_rmse_m, landmark_rmse_m=metrics.landmark_rmse_m,
        decisions=effect.decisions,
        robot_distance_m=[float(d) for d in metrics.robot_distances_m])
    message.header.stamp = seconds_to_time(metrics.stamp_s)
    message.header.frame_id = WORLD_FRAME
    return message


def replace_summary(path: Path, summary: RunSummary) -> None:
    """Write ``summary`` over the summary file at once (renamed over it: a process killed
    meanwhile leaves the previous one whole)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_replacing(path, summary.write)


def draw_pictures(summary: RunSummary, layers: TeamMapLayers, summary_path: Path,
                  map_path: Path) -> list[Path]:
    """The team map at ``map_path`` and the timeline beside the summary; returns both.

    The drawing modules (matplotlib) are imported here, at the run's end: at start-up they
    were 0.4 s of the evaluator's 1.2 s of imports, and the world waits for the evaluator
    before the first step (the robots' imports take 0.65 s)."""
    from em_exploration_ros.core.evaluation.map_render import render_team_map
    from em_exploration_ros.core.evaluation.run_timeline import render_timeline
    timeline_path = summary_path.with_name(summary_path.stem + TIMELINE_SUFFIX)
    render_team_map(layers, map_path)
    render_timeline(summary.to_dict(), timeline_path)
    return [map_path, timeline_path]
