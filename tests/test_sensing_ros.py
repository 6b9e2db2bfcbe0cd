"""The lockstep ROS team under the field's sensing (issue 38, point 4): with landmark
identities off, missed detections and clutter, em-world, the em-robot processes and
em-evaluator choose em-sim's targets (the association runs in each robot's core, the misses
and clutter come from the world's seeded streams), and em-evaluator counts the robots'
associations against ground truth as em-sim does (point 3): the truth of the scans reaches
it alone, on /world/sonar_truth/robot_i."""
import json
from concurrent.futures import ThreadPoolExecutor

from ros_process import (REPO_ROOT, ProcessSet, finish_team_run, graph_reader, start_team_run,
                         wait_until)

from em_exploration_ros.core.evaluation.association_stats import association_line
from em_exploration_ros.core.params_yaml import load_params
from em_exploration_ros.core.sessions.team_runner import TeamRunner

#: Bound of the end-to-end run (set-up check, start-up, exploration, shutdown) [s].
RUN_TIMEOUT_S = 400.0
#: Bound of the wait for the nodes' subscriptions to show in the graph [s].
GRAPH_TIMEOUT_S = 60.0


def only_the_evaluator_reads_the_truth_of_the_scans(domain: str) -> None:
    """While the team runs (in ``domain``): the world publishes /world/sonar_truth/robot_i,
    alone, the evaluator subscribes to it, and no robot does (each robot's own subscriptions
    are in the graph)."""
    topics = [f"/world/sonar_truth/robot_{robot}" for robot in range(3)]
    with graph_reader(domain) as graph:
        def nodes(infos) -> set[str]:
            return {info.node_name for info in infos}

        def all_discovered() -> bool:
            return (all("em_robot" in nodes(graph.get_subscriptions_info_by_topic(
                f"/robot_{robot}/sonar")) for robot in range(3))
                and all("em_evaluator" in nodes(graph.get_subscriptions_info_by_topic(topic))
                        and "em_world" in nodes(graph.get_publishers_info_by_topic(topic))
                        for topic in topics))
        # Discovery reaches this reader one process at a time: the world's writers may show
        # after the readers (seen on a loaded machine), so the wait is for all of them.
        wait_until(all_discovered, GRAPH_TIMEOUT_S,
                   "the robots' and the evaluator's readers and the world's writers")
        for topic in topics:
            assert nodes(graph.get_subscriptions_info_by_topic(topic)) == {"em_evaluator"}
            assert nodes(graph.get_publishers_info_by_topic(topic)) == {"em_world"}


#: (landmark identities, detection probability, clutter rate, landmarks, seed) of each case.
SENSINGS = [("off", 0.9, 1.0, 8, 0), ("on", 0.8, 2.0, 4, 2)]


def test_the_ros_team_chooses_em_sim_s_targets(tmp_path):
    """Each sensing of SENSINGS; the second one's team runs beside the first one's, in a
    domain of its own (stopped at once if the first one fails)."""
    with ThreadPoolExecutor(max_workers=1) as thread, ProcessSet() as beside:
        second = thread.submit(check_sensing, tmp_path / SENSINGS[1][0], *SENSINGS[1],
                               beside=beside)
        check_sensing(tmp_path / SENSINGS[0][0], *SENSINGS[0])
        second.result()


def check_sensing(tmp_path, landmark_ids: str, detection_prob: float, clutter_rate: float,
                  landmarks: int, seed: int, beside: ProcessSet | None = None) -> None:
    """One sensing's ROS team against em-sim (``beside``: ``start_team_run``)."""
    summary_path = tmp_path / "run" / "summary.json"
    run, domain = start_team_run(tmp_path, "--robots", "3", "--planner", "NEAREST",
                                 "--map-size", "40", "--landmarks", str(landmarks),
                                 "--seed", str(seed),
                                 "--max-sim-time", "600", "--landmark-ids", landmark_ids,
                                 "--detection-prob", str(detection_prob),
                                 "--clutter-rate", str(clutter_rate),
                                 "--summary", str(summary_path), beside=beside)
    code = finish_team_run(run, RUN_TIMEOUT_S,
                           lambda: only_the_evaluator_reads_the_truth_of_the_scans(domain))
    assert code == 0, run.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    reference = TeamRunner(load_params(REPO_ROOT / "config" / "exploration.yaml").replace(
        world={"num_robots": 3, "width_m": 40.0, "height_m": 40.0, "num_landmarks": landmarks},
        planner={"name": "NEAREST"}, run={"seed": seed},
        sensors={"landmark_ids": landmark_ids == "on",
                 "detection_probability": detection_prob,
                 "clutter_rate": clutter_rate})).run().to_dict()
    assert [r["targets"] for r in summary["robots"]] == [r["targets"] for r in
                                                         reference["robots"]]
    assert (summary["stop_reason"], summary["sim_time_s"]) == (reference["stop_reason"],
                                                               reference["sim_time_s"])
    # The association counts against ground truth, per robot and for the team, are em-sim's
    # (without identities the robots tied teammates' landmarks: their ties crossed DDS too).
    association = reference["association"]
    assert association["correct"] > 0 and 0.0 <= association["recall"] <= 1.0
    if landmark_ids == "off":
        assert association["correspondences_correct"] > 0
    assert summary["association"] == association
    # run_team.sh prints it among its last lines, as em-sim does.
    assert any(line.endswith(association_line(association))
               for line in run.output().splitlines()[-12:])
