"""Team liveness bookkeeping: statuses, their changes and downtimes."""
from __future__ import annotations

from em_exploration_ros.core.agent.liveness import (ACTIVE, FINISHED, LOST, REJOINED,
                                                    StatusChange, TeamLiveness)


def test_statuses_change_with_times_and_downtime_is_summed():
    team = TeamLiveness(3)
    assert [team.status(r) for r in range(3)] == [ACTIVE] * 3
    assert team.heard(0, 1.0, 1.0, "alive") is False          # never lost: no change
    assert team.lost(1, 10.0, 5.0, "lease expired")
    assert not team.lost(1, 11.0, 6.0, "lease expired")      # no news
    assert team.heard(1, 30.0, 15.0, "alive again")
    assert team.status(1) == REJOINED
    assert team.lost(1, 50.0, 20.0, "lease expired")
    assert team.downtime_s(1, until_sim_time_s=70.0) == (30.0 - 10.0) + (70.0 - 50.0)
    assert team.changes(1) == [StatusChange(LOST, 10.0, 5.0, "lease expired"),
                               StatusChange(REJOINED, 30.0, 15.0, "alive again"),
                               StatusChange(LOST, 50.0, 20.0, "lease expired")]
    assert team.finished(2, 40.0, 18.0) and team.status(2) == FINISHED
    assert not team.finished(2, 41.0, 19.0)
    assert not team.finished(1, 60.0, 22.0)  # a lost robot's flag is stale news
    assert team.downtime_s(0, 70.0) == 0.0 and team.changes(0) == []
