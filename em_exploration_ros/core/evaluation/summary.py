"""The run summary: one JSON schema for em-sim, run_team.sh and the benchmark.

Top-level keys (units in the names): ``explored_ratio``, ``distance_m`` (all robots),
``loc_rmse_m``, ``landmark_rmse_m``, ``decisions``, ``wall_s``, ``sim_time_s``,
``decision_time_median_s``, ``decision_time_max_s``, ``robots`` (per robot: ``id``,
``distance_m``, ``decisions``, ``targets`` (in order: ``x``, ``y`` [m, map frame],
``type`` (exploration / revisiting / rendezvous)), ``decision_times_s``, ``status``
(active / finished / lost / rejoined at the end), ``status_changes`` (``status``,
``sim_time_s``, ``wall_s``, ``reason``; the first and latest 100, with
``status_changes_omitted`` left out between them), ``downtime_s`` and ``downtime_wall_s``
(simulated and wall seconds lost), ``given_up`` (targets the robot gave up, in order: ``x``,
``y`` [m, map frame], ``stamp_s``, ``reason``: blocked / no progress / deadline), ``blocked_s``
(simulation time during which the robot's odometry showed it blocked while it commanded
forward motion) and ``slam_recoveries`` (SLAM updates that diverged or failed and were
re-solved in batch); ``given_up``, ``blocked_s`` and ``slam_recoveries`` are null where the
writer cannot know them),
plus ``seed``,
``planner``, ``num_robots``, ``map_size_m``, ``cell_size_m`` (the virtual map's cell side),
``num_landmarks``, ``stop_reason`` and
``history``: samples of the metrics against distance travelled (with each robot's position
uncertainty ``robot_pose_sigma_m`` where the writer knows it); ``decisions_by_type``
(decisions per frontier type), ``planner_failures`` (decisions where the planner failed and
the nearest frontier rule chose), ``rendezvous`` (requested / met / timed_out / open, see
``rendezvous_stats``) and ``meetings`` (per rendezvous with an inter-robot factor, the
requester's pose-covariance trace just before and after it), ``team_updates``
(em-sim and the benchmark: how many teammate updates the links delivered on time, late or
never), ``association`` (em-sim, when the sonar is not the paper's ideal one: the robots'
data association against ground truth, ``precision``, ``recall`` and the counts of
``association_stats``, the team's and per robot; null otherwise).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from em_exploration_ros.core.agent.liveness import ACTIVE, StatusChange

REQUIRED_KEYS = ("explored_ratio", "distance_m", "loc_rmse_m", "landmark_rmse_m", "decisions",
                 "wall_s", "sim_time_s", "decision_time_median_s", "decision_time_max_s",
                 "robots")
ROBOT_KEYS = ("id", "distance_m", "decisions", "targets", "decision_times_s")
TARGET_TYPES = ("exploration", "revisiting", "rendezvous")


@dataclass
class TargetEntry:
    """One chosen target: position in the map frame [m] and its frontier type."""

    x: float
    y: float
    type: str


@dataclass
class GivenUpEntry:
    """A target a robot gave up: position in the map frame [m], when [s sim time], why."""

    x: float
    y: float
    stamp_s: float
    reason: str


@dataclass
class RobotSummary:
    """Per-robot part of the summary."""

    id: int
    distance_m: float = 0.0
    decisions: int = 0
    targets: list[TargetEntry] = field(default_factory=list)
    decision_times_s: list[float] = field(default_factory=list)
    status: str = ACTIVE
    status_changes: list[StatusChange] = field(default_factory=list)
    status_changes_omitted: int = 0
    downtime_s: float = 0.0
    downtime_wall_s: float = 0.0
    given_up: list[GivenUpEntry] | None = None
    blocked_s: float = math.nan
    slam_recoveries: int | None = None


@dataclass
class RendezvousCounts:
    """How many rendezvous were requested, met, timed out (ended without meeting) and
    still open at the end of the run (see ``rendezvous_stats``)."""

    requested: int = 0
    met: int = 0
    timed_out: int = 0
    open: int = 0


@dataclass
class MeetingEntry:
    """A rendezvous that produced an inter-robot factor between requester and partner:
    the requester's latest pose-covariance trace [m^2 + rad^2] just before and after the
    SLAM update that added it at ``stamp_s`` [s]; requested at ``requested_at_s`` [s]."""

    requester_id: int
    partner_id: int
    rendezvous_id: int
    requested_at_s: float
    stamp_s: float
    trace_before_m2: float
    trace_after_m2: float


@dataclass
class HistorySample:
    """Team metrics at one moment, for plots against distance travelled or time;
    ``robot_pose_sigma_m``: each robot's position uncertainty [m] (by id; empty where the
    writer does not know it)."""

    sim_time_s: float
    distance_m: float
    explored_ratio: float
    loc_rmse_m: float
    landmark_rmse_m: float
    robot_pose_sigma_m: list[float] = field(default_factory=list)


@dataclass
class RunSummary:
    """Result of one exploration run."""

    seed: int
    planner: str
    num_robots: int
    map_size_m: tuple[float, float]
    #: Side of a virtual map cell [m] (the paper: 2 m on the 100 m map, 4 m on the 200 m map).
    cell_size_m: float
    num_landmarks: int
    explored_ratio: float = 0.0
    distance_m: float = 0.0
    loc_rmse_m: float = math.nan
    landmark_rmse_m: float = math.nan
    decisions: int = 0
    wall_s: float = 0.0
    sim_time_s: float = 0.0
    decision_time_median_s: float = math.nan
    decision_time_max_s: float = math.nan
    stop_reason: str = ""
    decisions_by_type: dict[str, int] = field(
        default_factory=lambda: {kind: 0 for kind in TARGET_TYPES})
    planner_failures: int = 0
    rendezvous: RendezvousCounts = field(default_factory=RendezvousCounts)
    meetings: list[MeetingEntry] = field(default_factory=list)
    #: Over every (team update, teammate) pair: ``sent``, delivered ``on_time`` / ``late``,
    #: ``never`` delivered (``core/links/link_model.py``); None where the writer cannot know.
    team_updates: dict[str, int] | None = None
    #: ``association_stats.association_summary``; None where the writer cannot know it or
    #: the sonar names every landmark it sees and nothing else.
    association: dict[str, Any] | None = None
    robots: list[RobotSummary] = field(default_factory=list)
    history: list[HistorySample] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """Plain data with NaN written as None (JSON has no NaN)."""
        return _nan_to_none(asdict(self))

    def write(self, path: str | Path) -> None:
        """Write the summary as indented JSON, creating parent folders."""
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(json.dumps(self.to_dict(), indent=2) + "\n", encoding="utf-8")


def activity_line(data: dict[str, Any]) -> str:
    """One line on a summary's decisions and rendezvous (``RunSummary.to_dict`` data), e.g.
    ``decisions: 120 exploration, 7 revisiting, 1 rendezvous; planner failed 0;
    rendezvous: 1 requested, 0 met, 1 timed out, 0 open``."""
    kinds = data.get("decisions_by_type") or {}
    meetings = data.get("rendezvous") or {}
    return ("decisions: " + ", ".join(f"{kinds.get(k, 0)} {k}" for k in TARGET_TYPES)
            + f"; planner failed {data.get('planner_failures', 0)}; rendezvous: "
            + ", ".join(f"{meetings.get(k, 0)} {k.replace('_', ' ')}"
                        for k in ("requested", "met", "timed_out", "open")))


def check_summary(data: dict[str, Any]) -> list[str]:
    """Problems with a parsed summary (empty when it follows the schema)."""
    problems = [f"missing key '{key}'" for key in REQUIRED_KEYS if key not in data]
    for robot in data.get("robots", []):
        problems += [f"robot entry missing '{key}'" for key in ROBOT_KEYS if key not in robot]
        for target in robot.get("targets", []):
            if target.get("type") not in TARGET_TYPES:
                problems.append(
                    f"robot {robot.get('id')}: unknown target type {target.get('type')!r}")
    return problems


def _nan_to_none(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _nan_to_none(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nan_to_none(item) for item in value]
    return value
