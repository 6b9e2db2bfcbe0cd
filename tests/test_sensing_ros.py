"""The lockstep ROS team under the field's sensing (issue 38, point 4): with landmark
identities off, missed detections and clutter, em-world, the em-robot processes and
em-evaluator choose em-sim's targets (the association runs in each robot's core, the misses
and clutter come from the world's seeded streams)."""
import json

import pytest
from ros_process import REPO_ROOT, finish_team_run, start_team_run

from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.core.sessions.team_runner import TeamRunner

#: Bound of the end-to-end run (set-up check, start-up, exploration, shutdown) [s].
RUN_TIMEOUT_S = 400.0


@pytest.mark.parametrize("landmark_ids, detection_prob, clutter_rate", [
    ("off", 0.9, 1.0), ("on", 0.8, 2.0)])
def test_the_ros_team_chooses_em_sim_s_targets(tmp_path, landmark_ids, detection_prob,
                                               clutter_rate):
    summary_path = tmp_path / "run" / "summary.json"
    run, _ = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST",
                            "--map-size", "40", "--landmarks", "4", "--seed", "2",
                            "--max-sim-time", "600", "--landmark-ids", landmark_ids,
                            "--detection-prob", str(detection_prob),
                            "--clutter-rate", str(clutter_rate),
                            "--summary", str(summary_path))
    code = finish_team_run(run, RUN_TIMEOUT_S)
    assert code == 0, run.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    reference = TeamRunner(load_params(REPO_ROOT / "config" / "exploration.yaml").replace(
        world={"num_robots": 3, "width_m": 40.0, "height_m": 40.0, "num_landmarks": 4},
        planner={"name": "NEAREST"}, run={"seed": 2},
        sensors={"landmark_ids": landmark_ids == "on",
                 "detection_probability": detection_prob,
                 "clutter_rate": clutter_rate})).run().to_dict()
    assert [r["targets"] for r in summary["robots"]] == [r["targets"] for r in
                                                         reference["robots"]]
    assert (summary["stop_reason"], summary["sim_time_s"]) == (reference["stop_reason"],
                                                               reference["sim_time_s"])
