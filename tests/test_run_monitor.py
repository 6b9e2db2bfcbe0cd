"""The run monitor: one stop rule and one summary for em-sim and the evaluator node."""
import math

from em_exploration_ros.core.agent.liveness import LOST, TeamLiveness
from em_exploration_ros.core.evaluation.evaluator import TeamMetrics
from em_exploration_ros.core.evaluation.run_monitor import (EXIT_ROBOTS_LOST, EXIT_STALLED,
                                                            DecisionEntry, RobotProgressRecord,
                                                            RunMonitor, StallWatch, TeamFinished,
                                                            every_live_robot_finished, final_step)
from em_exploration_ros.core.evaluation.summary import GivenUpEntry, check_summary
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.records.team_data import FrontierType

STEP_S = ExplorationParams().motion.time_step_s


def metrics(step: int, explored: float, distances=(1.0, 2.0)) -> TeamMetrics:
    return TeamMetrics(step * STEP_S, float(sum(distances)), explored, 0.5, 0.4,
                       tuple(float(d) for d in distances))


def decision(step: int, x: float) -> DecisionEntry:
    return DecisionEntry(step * STEP_S, (x, 1.0), FrontierType.EXPLORATION, 0.01)


def test_final_step_takes_the_earlier_limit():
    params = ExplorationParams().replace(run={"max_steps": 50})
    assert final_step(params, 0.0) == 50
    assert final_step(params, 3.0) == 15
    assert final_step(params, 3.1) == 15
    assert final_step(params, 100.0) == 50


def test_summary_holds_the_values_of_the_step_where_the_rule_fired():
    monitor = RunMonitor(ExplorationParams().replace(run={"until_explored": 0.8}))
    assert monitor.observe(10, metrics(10, 0.5)) == ""
    reason = monitor.observe(20, metrics(20, 0.803, (3.0, 4.0)))
    assert reason.startswith("explored ratio 0.803") and monitor.stopped
    # the world went on: later evaluations change nothing
    assert monitor.observe(30, metrics(30, 0.84, (9.0, 9.0))) == reason
    monitor.record(metrics(40, 0.9, (9.0, 9.0)))
    summary = monitor.summary([[decision(5, 1.0), decision(19, 2.0), decision(20, 3.0),
                                decision(25, 4.0)], [decision(12, 5.0)]], wall_s=1.5)
    assert summary.explored_ratio == 0.803 and summary.distance_m == 7.0
    assert summary.sim_time_s == 20 * STEP_S and summary.stop_reason == reason
    assert [r.distance_m for r in summary.robots] == [3.0, 4.0]
    # decisions made before the stop step count, later ones do not
    assert [t.x for t in summary.robots[0].targets] == [1.0, 2.0]
    assert summary.decisions == 3 and len(summary.history) == 2
    assert check_summary(summary.to_dict()) == []


def test_summary_names_the_map_it_was_run_on():
    """Map side and cell side both: the paper's two maps differ in both (100 m with 2 m
    cells, 200 m with 4 m cells), so a summary without the cell would not say which ran."""
    params = ExplorationParams().replace(world={"width_m": 200.0, "height_m": 200.0},
                                         map={"cell_size_m": 4.0})
    data = RunMonitor(params).summary([[], []], wall_s=1.0).to_dict()
    assert (data["map_size_m"], data["cell_size_m"]) == ([200.0, 200.0], 4.0)


def test_targets_given_up_count_when_made_before_the_step_where_the_rule_fired():
    monitor = RunMonitor(ExplorationParams().replace(run={"until_explored": 0.8}))
    monitor.observe(20, metrics(20, 0.803))
    given_up = [GivenUpEntry(float(step), 0.0, step * STEP_S, "blocked") for step in (5, 19, 20)]
    summary = monitor.summary([[], []], wall_s=1.0, progress=[
        RobotProgressRecord(tuple(given_up), 3.2, 1), RobotProgressRecord((), 0.0)])
    # the watcher's list may hold targets given up after the stop step (the world went on)
    assert [g.x for g in summary.robots[0].given_up] == [5.0, 19.0]
    assert [r.blocked_s for r in summary.robots] == [3.2, 0.0]
    assert [r.slam_recoveries for r in summary.robots] == [1, None]  # None: not known
    assert summary.robots[1].given_up == []
    assert check_summary(summary.to_dict()) == []


def test_every_robot_finished_and_the_final_step_stop_the_run():
    params = ExplorationParams().replace(run={"max_steps": 40})
    finished = RunMonitor(params)
    assert finished.observe(10, metrics(10, 0.3), all_finished=True) == "every robot finished"
    limited = RunMonitor(params)
    assert limited.observe(30, metrics(30, 0.3)) == ""
    assert limited.observe(40, metrics(40, 0.3)).startswith("final step 40")


def test_every_robot_finished_learned_after_the_evaluation_stops_the_run_there():
    monitor = RunMonitor(ExplorationParams().replace(run={"max_steps": 400}))
    assert monitor.observe_finished(10) == "" and not monitor.stopped  # nothing evaluated yet
    assert monitor.observe(10, metrics(10, 0.3)) == ""
    assert monitor.observe(20, metrics(20, 0.4)) == ""   # the robots' answers come later
    assert monitor.observe_finished(20) == "every robot finished"
    assert monitor.stopped and monitor.final_metrics is monitor.history[-1]
    assert len(monitor.history) == 2                        # the evaluation is not repeated
    assert monitor.observe_finished(20) == "every robot finished"
    # an earlier rule stays the reason
    explored = RunMonitor(ExplorationParams().replace(run={"until_explored": 0.5}))
    first = explored.observe(10, metrics(10, 0.6))
    assert first.startswith("explored ratio") and explored.observe_finished(10) == first


def test_every_live_robot_finished_names_the_robots_lost_before_they_finished():
    """The evaluator's view of a chaos run: robot 1 SIGKILLed without --respawn (lost), robot
    2 restarted and rejoined (--respawn: live again), robot 3 killed after it had finished."""
    liveness = TeamLiveness(4, grace_s=4.0)
    liveness.finished(3, 20.0, 5.0)
    for robot in (1, 2, 3):
        liveness.liveliness_lost(robot, 30.0, 10.0)
    liveness.confirm(14.0)
    liveness.heard(2, 36.0, 18.0, "answers the world again")
    lost = [liveness.status(robot) == LOST for robot in range(4)]
    assert lost == [False, True, False, True]
    # robot 2 is live: it must finish too
    assert every_live_robot_finished([150, None, None, 100], lost) is None
    # robot 3 did its part before it was lost; robot 1 did not
    assert every_live_robot_finished([150, None, 148, 100], lost) == TeamFinished(150, (1,))
    # nobody lost: the team finished
    assert every_live_robot_finished([150, 149], [False, False]) == TeamFinished(150, ())
    # every robot lost: not this rule (the world stepping over or silence ends such a run)
    assert every_live_robot_finished([None, 100], [True, True]) is None


def test_a_run_whose_live_robots_finished_with_others_lost_ends_below_its_goal_with_code_5():
    """Stopped by the live robots' finishing at explored 0.75 < 0.85 with robot 1 lost: not
    a success (it once said "every robot finished" and exited 0). A run reaching its goal,
    or finishing with nobody lost (em-sim's only case), still ends with 0; a stall with 4."""
    params = ExplorationParams().replace(run={"until_explored": 0.85, "stall_timeout_s": 30.0})
    monitor = RunMonitor(params)
    assert monitor.observe(10, metrics(10, 0.5), lost=(1,)) == ""  # the others go on
    reason = monitor.observe(20, metrics(20, 0.75), all_finished=True, lost=(1,))
    assert reason == "every live robot finished; robots [1] lost"
    assert monitor.exit_code == EXIT_ROBOTS_LOST == 5
    assert monitor.summary([[], []], wall_s=1.0).stop_reason == reason
    late = RunMonitor(params)  # the robots' answers came after the evaluation
    late.observe(20, metrics(20, 0.75))
    assert late.observe_finished(20, lost=(2, 0)) == "every live robot finished; robots [0, 2] lost"
    assert late.exit_code == EXIT_ROBOTS_LOST
    team = RunMonitor(params)
    assert team.observe(20, metrics(20, 0.75), all_finished=True) == "every robot finished"
    assert team.exit_code == 0
    reached = RunMonitor(params)
    assert reached.observe(20, metrics(20, 0.86), all_finished=True, lost=(1,)).startswith(
        "explored ratio 0.860")
    assert reached.exit_code == 0
    stalled = RunMonitor(params)
    stalled.observe(10, metrics(10, 0.5))
    assert stalled.observe(160, metrics(160, 0.5), lost=(1,)).startswith("stalled: ")
    assert stalled.exit_code == EXIT_STALLED


def test_distance_limit_stops_the_run():
    monitor = RunMonitor(ExplorationParams().replace(run={"max_distance_m": 5.0}))
    assert monitor.observe(10, metrics(10, 0.1, (2.0, 3.0))).startswith("distance 5 m")


def test_a_run_ended_from_outside_is_summarized_at_its_last_evaluation():
    monitor = RunMonitor(ExplorationParams())
    empty = monitor.summary([[], []], wall_s=0.0)
    assert empty.decisions == 0 and math.isnan(empty.loc_rmse_m)
    monitor.observe(10, metrics(10, 0.2))
    monitor.observe(20, metrics(20, 0.4))
    monitor.record(metrics(23, 0.45))  # the steps recorded before the interruption
    monitor.end("interrupted")
    summary = monitor.summary([[decision(3, 1.0)], []], wall_s=2.0)
    assert summary.stop_reason == "interrupted" and summary.explored_ratio == 0.45
    assert not monitor.stopped and summary.decisions == 1


def test_a_team_without_travel_or_new_area_for_the_timeout_stalls():
    monitor = RunMonitor(ExplorationParams().replace(run={"stall_timeout_s": 30.0}))
    assert monitor.observe(10, metrics(10, 0.5)) == ""
    assert monitor.observe(100, metrics(100, 0.5, (1.0, 2.005))) == ""  # < 1 cm: no travel
    assert monitor.observe(159, metrics(159, 0.5)) == ""  # 29.8 s without progress
    reason = monitor.observe(160, metrics(160, 0.5))
    assert reason == ("stalled: no distance and no newly explored area for 30 s "
                      "(distance 3.0 m, explored 0.500)")
    assert monitor.stopped and monitor.stalled
    assert monitor.summary([[], []], wall_s=1.0).stop_reason == reason


def test_travel_or_new_area_restarts_the_stall_clock_and_zero_disables_it():
    watch = StallWatch(10.0)
    assert watch.update(metrics(0, 0.5)) == ""
    assert watch.update(metrics(45, 0.5, (1.0, 2.5))) == ""  # travelled
    assert watch.update(metrics(90, 0.51, (1.0, 2.5))) == ""  # explored new area
    assert watch.update(metrics(139, 0.51, (1.0, 2.5))) == ""
    assert watch.update(metrics(140, 0.51, (1.0, 2.5))).startswith("stalled: ")
    disabled = StallWatch(0.0)
    assert all(disabled.update(metrics(k * 1000, 0.5)) == "" for k in range(5))
