"""Parameters of the exploration system, with the paper's values as defaults.

Every number of the method lives here, grouped by the part of the system that uses it.
Each field carries a description, a unit and a valid range in its metadata, so the ROS
nodes can declare it as a parameter (``<group>.<field>``) and the tools can load it from
YAML. Units follow REP-103: metres, radians, seconds.

Sources: the paper (shared/seed) and the reference implementation's values
(shared/reference/PARAMETERS.md). Where the two disagree, the default follows the paper
and the reference behaviour is an option; the field's description says which is which.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import warnings
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Callable, Iterable, Mapping

from em_exploration_ros.core.planner_registry import installed_planner_names
from em_exploration_ros.core.untrusted_yaml import shown_value

#: Ratio between a 95% error bound and the standard deviation of a Gaussian.
BOUND_95_TO_SIGMA = 1.96
#: Occupancy probability of a cell never observed (log-odds 0).
UNKNOWN_PROBABILITY = 0.5
#: Fewest virtual map cells along each side of the world: with fewer, at most one cell
#: along a side lies away from the map edge (frontiers ignore cells near it,
#: frontiers.boundary_distance_m) and the explored ratio moves in steps of 1/9 of the map
#: or more.
MIN_CELLS_PER_SIDE = 4


def param_field(default: Any, description: str, low: float | None = None,
                high: float | None = None,
                choices: tuple[str, ...] | Callable[[], tuple[str, ...]] | None = None) -> Any:
    """A dataclass field with its documentation and range kept in metadata; ``choices``, the
    values a text may take, may be a function that lists them when asked (``field_choices``)."""
    metadata = {"description": description, "low": low, "high": high, "choices": choices}
    return field(default=default, metadata=metadata)


def field_choices(f: dataclasses.Field) -> tuple[str, ...] | None:
    """The values the text parameter ``f`` may take (for ``planner.name``, the planners
    installed now: ``core.planner_registry``), or None for any text."""
    choices = f.metadata.get("choices")
    return choices() if callable(choices) else choices


@dataclass(frozen=True)
class WorldParams:
    """The simulated environment: a rectangle [0, width] x [0, height] in the world frame."""

    width_m: float = param_field(100.0, "Environment width along world x [m].", 10.0, 2000.0)
    height_m: float = param_field(100.0, "Environment height along world y [m].", 10.0, 2000.0)
    num_robots: int = param_field(3, "Number of robots in the team.", 1, 26)
    num_landmarks: int = param_field(20, "Number of point landmarks placed at random.", 0, 1000)
    landmark_radius_m: float = param_field(1.0, "Physical radius of a landmark [m].", 0.0, 10.0)
    landmark_min_separation_m: float = param_field(
        10.0, "Minimum distance between two landmark centres [m].", 0.0, 100.0)
    robot_radius_m: float = param_field(0.8, "Collision radius of a robot [m].", 0.0, 5.0)
    start_region_x_fraction: tuple[float, float] = param_field(
        (0.1, 0.2), "Start region along x, as fractions of width (middle-left of the map).")
    start_region_y_fraction: tuple[float, float] = param_field(
        (0.45, 0.55), "Start region along y, as fractions of height (middle-left of the map).")
    start_min_separation_m: float = param_field(
        2.0, "Minimum distance between two robots' start positions [m].", 0.0, 10.0)
    start_max_separation_m: float = param_field(
        6.0, "Maximum distance between two robots' start positions [m]; must stay below "
        "the sonar range so a robot senses those teammates at the start.", 0.0, 100.0)
    start_group_robots: int = param_field(
        5, "Largest team whose robots all start within start_max_separation_m of each other "
        "in the start region. A larger team's start region grows with the team (sides "
        "scaled by sqrt(num_robots / start_group_robots) about the same centre, clipped to "
        "the map) and each robot starts within that distance of the start_group_robots - 1 "
        "robots placed before it (a chain of readings anchors every robot).", 2, 26)
    landmark_clearance_from_start_m: float = param_field(
        3.0, "Minimum distance between a landmark and a robot's start position [m].", 0.0, 50.0)
    landmark_edge_margin_m: float = param_field(
        2.0, "Minimum distance between a landmark centre and the map edge [m] (project "
        "choice; the paper does not state one).", 0.0, 100.0)
    file: str = param_field(
        "", "World YAML file (map size, landmarks, start poses; docs/worlds.md) the run "
        "starts from instead of the world run.seed generates; empty: generate it. "
        "width_m, height_m, num_landmarks and landmark_radius_m must match the file "
        "(em-sim and run_team.sh --world set them).")


@dataclass(frozen=True)
class SensorParams:
    """Simulated sonar, teammate detection and dead reckoning; errors are 95% bounds."""

    sonar_max_range_m: float = param_field(7.5, "Maximum sonar range [m].", 0.1, 100.0)
    sonar_range_bound_m: float = param_field(0.002, "Sonar range error, 95% bound [m].", 0.0, 10.0)
    sonar_bearing_bound_rad: float = param_field(
        math.radians(0.5), "Sonar bearing error, 95% bound [rad] (0.5 deg).", 0.0, 1.0)
    robot_obs_xy_bound_m: float = param_field(
        0.002, "Teammate relative-position error per axis, 95% bound [m].", 0.0, 10.0)
    robot_obs_theta_bound_rad: float = param_field(
        math.radians(0.2), "Teammate relative-heading error, 95% bound [rad] (0.2 deg).", 0.0, 1.0)
    gyro_bound_rad: float = param_field(
        math.radians(0.5), "Gyro heading error accumulated over one odometry interval, "
        "95% bound [rad] (0.5 deg).", 0.0, 1.0)
    accel_bound_m: float = param_field(
        0.05, "Accelerometer translation error over one odometry interval, 95% bound [m]; "
        "capped by accel_bound_fraction of the distance moved.", 0.0, 10.0)
    accel_bound_fraction: float = param_field(
        0.05, "Translation error bound as a fraction of the distance moved in the interval.",
        0.0, 1.0)
    odometry_interval_steps: int = param_field(
        10, "Number of simulation steps over which the gyro/accelerometer bounds apply; "
        "noise is drawn every step with variance bound^2 / 1.96^2 / interval.", 1, 1000)
    noise_enabled: bool = param_field(True, "False makes every sensor output noise-free.")
    landmark_ids: bool = param_field(
        True, "Each sonar detection names its landmark (the paper's ideal sensing: the "
        "simulated sonar resolves data association; a false detection is named as none); "
        "false: no detection carries an identity and each robot associates its own.")
    detection_probability: float = param_field(
        1.0, "Probability that the sonar detects a landmark within its range, each landmark "
        "and scan independently (seeded); 1: the paper's sonar, which never misses one.",
        0.0, 1.0)
    clutter_rate: float = param_field(
        0.0, "Mean number of false detections per sonar scan (Poisson, seeded), spread "
        "uniformly over the sonar's field of view: range in [0, sonar_max_range_m], bearing "
        "in [-pi, pi); 0: the paper's sonar, which reports no landmark that is not there.",
        0.0, 1000.0)

    @property
    def ideal_sonar(self) -> bool:
        """The paper's sonar: every landmark in range detected and named, nothing else."""
        return (self.landmark_ids and self.detection_probability == 1.0
                and self.clutter_rate == 0.0)

    @property
    def sonar_range_sigma_m(self) -> float:
        """Standard deviation of a sonar range reading [m]."""
        return self.sonar_range_bound_m / BOUND_95_TO_SIGMA

    @property
    def sonar_bearing_sigma_rad(self) -> float:
        """Standard deviation of a sonar bearing reading [rad]."""
        return self.sonar_bearing_bound_rad / BOUND_95_TO_SIGMA


@dataclass(frozen=True)
class MotionParams:
    """Robot kinematics and the artificial potential field local planner."""

    time_step_s: float = param_field(0.2, "Simulation time step [s].", 0.001, 10.0)
    speed_mps: float = param_field(1.0, "Constant forward speed while moving [m/s].", 0.01, 10.0)
    max_turn_per_step_rad: float = param_field(
        math.radians(15.0), "Largest heading change in one step (one action) [rad].", 0.0, math.pi)
    goal_tolerance_m: float = param_field(
        1.0, "A target counts as reached within this distance [m].", 0.01, 50.0)
    apf_attractive_gain: float = param_field(1.0, "Gain of the attractive potential (unitless).",
                                             0.0, 100.0)
    apf_repulsive_gain: float = param_field(
        8.0, "Gain of the repulsive potential of a landmark [m^3].", 0.0, 1000.0)
    apf_influence_m: float = param_field(
        3.0, "Distance from a landmark's surface beyond which it does not repel [m].", 0.0, 50.0)
    safety_margin_m: float = param_field(
        0.3, "Extra clearance kept between robot and landmark surfaces [m].", 0.0, 10.0)
    target_timeout_factor: float = param_field(
        3.0, "A target not reached within this many times its straight-line travel time "
        "(plus target_timeout_margin_s) is given up and a new one chosen.", 1.0, 100.0)
    target_timeout_margin_s: float = param_field(
        30.0, "Extra time allowed to reach a target [s].", 0.0, 1e5)


@dataclass(frozen=True)
class SlamParams:
    """Per-robot team factor graph (iSAM2)."""

    keyframe_interval_steps: int = param_field(
        10, "A keyframe (graph pose) every this many simulation steps; the SLAM update rate.",
        1, 1000)
    prior_sigmas: tuple[float, float, float] = param_field(
        (1e-4, 1e-4, 1e-6), "Prior on robot 0's first pose: sigma of (x [m], y [m], theta [rad]).")
    use_fixed_sigmas: bool = param_field(
        False, "Reference behaviour: use the fixed hand-set sigmas below instead of the "
        "covariances derived from the sensor noise (paper default: derived).")
    fixed_odometry_sigmas: tuple[float, float, float] = param_field(
        (0.03, 0.03, 0.004), "Reference odometry factor sigmas (x [m], y [m], theta [rad]).")
    fixed_bearing_range_sigmas: tuple[float, float] = param_field(
        (0.004, 0.001), "Reference bearing-range factor sigmas (bearing [rad], range [m]).")
    fixed_robot_obs_sigmas: tuple[float, float, float] = param_field(
        (0.1, 0.1, 0.004), "Reference inter-robot factor sigmas (x [m], y [m], theta [rad]).")
    virtual_robot_obs_sigmas: tuple[float, float, float] = param_field(
        (0.01, 0.01, 0.004), "Sigmas of virtual inter-robot observations in the EM step "
        "(x [m], y [m], theta [rad]).")
    relinearize_threshold: float = param_field(0.01, "iSAM2 relinearization threshold.", 0.0, 10.0)
    extra_update_iterations: int = param_field(
        2, "At most this many extra iSAM2 update() calls after adding new measurements, "
        "stopping as soon as no variable needs relinearization.", 0, 100)
    covariance_floor_sigma: float = param_field(
        1e-4, "Sigma added in quadrature to every sensor-derived noise model [m or rad], so "
        "degenerate covariances (robot at rest, noise-free sensors) stay invertible; 1e-6 "
        "made the graph too ill-conditioned for Cholesky once robots waited.", 0.0, 1.0)
    divergence_check_step: float = param_field(
        1.0, "An iSAM2 update whose largest step exceeds this (m or rad) is checked: if it "
        "raised the graph's error more than divergence_error_ratio times, the estimate is "
        "re-solved in batch (Powell's dogleg) and iSAM2 restarted from it.", 0.0, 1e6)
    divergence_error_ratio: float = param_field(
        2.0, "Rise of the graph's total error over one update that counts as a diverging "
        "Gauss-Newton step (ratio of the error after to the error before).", 1.0, 1e6)
    association_gate_probability: float = param_field(
        0.99, "Without landmark identities (sensors.landmark_ids false): probability of the "
        "chi-square gates of data association: a detection against a landmark (individual), "
        "a scan's pairings together (JCBB), a detection against a tentative track, a "
        "teammate's landmark against an own one and two such correspondences together "
        "(pairwise consistency).", 0.5, 0.999999)
    robot_detection_gate_probability: float = param_field(
        0.999, "Without landmark identities: probability of the chi-square gate (3 degrees "
        "of freedom) within which two detections of the same two robots must close their "
        "loop through both robots' odometry to agree; a detection enters the graph only "
        "once it agrees with at least one, and half, of the others within "
        "track_window_keyframes (pairwise consistency). Wider than "
        "association_gate_probability: it is there to refuse gross errors, and a brief "
        "meeting's one pair refused by chance loses the meeting.", 0.5, 0.999999)
    track_confirm_hits: int = param_field(
        3, "Without landmark identities: a detection that matches no landmark starts a "
        "tentative track, which becomes a landmark once seen in this many of the last "
        "track_window_keyframes keyframes (clutter seldom is).", 1, 100)
    track_window_keyframes: int = param_field(
        5, "Without landmark identities: the window of keyframes of a tentative track; a "
        "track not seen for this many keyframes is dropped.", 1, 100)
    loop_closure_confirm_hits: int = param_field(
        2, "Without landmark identities: a detection paired with a landmark not seen for "
        "a while (gated on the wide marginals: a loop closure) names it only once its track "
        "was seen in this many of the last track_window_keyframes keyframes (one clutter "
        "point in that gate bends a map).", 1, 100)
    correspondence_sigma_m: float = param_field(
        0.01, "Without landmark identities: sigma per axis [m] of the factor that ties a "
        "teammate's landmark to the robot's own (the same point), under a Huber loss.",
        1e-6, 10.0)
    correspondence_huber_k: float = param_field(
        1.345, "Without landmark identities: Huber threshold (whitened residual) of a "
        "correspondence factor; beyond it the factor pulls linearly, not quadratically.",
        0.01, 100.0)
    landmark_cauchy_k: float = param_field(
        4.0, "Without landmark identities: Cauchy threshold (whitened residual) of every "
        "bearing-range factor; a reading far beyond it (a wrong association) pulls less the "
        "further it is off. 0: Gaussian, as with identities.", 0.0, 100.0)

    def __post_init__(self) -> None:
        """``ValueError`` unless a tentative track can be confirmed within its window:
        ``track_confirm_hits`` and ``loop_closure_confirm_hits`` at most
        ``track_window_keyframes``."""
        for name in ("track_confirm_hits", "loop_closure_confirm_hits"):
            if getattr(self, name) > self.track_window_keyframes:
                raise ValueError(f"SlamParams.{name} ({getattr(self, name)}) must be at most "
                                 f"track_window_keyframes ({self.track_window_keyframes}): a "
                                 f"track is seen at most once per keyframe of its window")


@dataclass(frozen=True)
class MapParams:
    """The virtual map: occupancy (explored area) and per-cell uncertainty."""

    cell_size_m: float = param_field(
        2.0, "Virtual map cell size [m] (paper: 2 m small, 4 m large map).", 0.1, 50.0)
    prob_free: float = param_field(0.3, "Occupancy probability of an observed free cell.", 0.0, 1.0)
    prob_occupied: float = param_field(0.7, "Occupancy probability of an observed landmark cell.",
                                       0.0, 1.0)
    prob_min: float = param_field(0.05, "Lower clamp of cell occupancy probability.", 0.0, 1.0)
    prob_max: float = param_field(0.95, "Upper clamp of cell occupancy probability.", 0.0, 1.0)
    explored_free_below: float = param_field(
        0.45, "A cell is explored (free) below this probability.", 0.0, 1.0)
    explored_occupied_above: float = param_field(
        0.55, "A cell is explored (occupied) above this probability.", 0.0, 1.0)
    virtual_landmark_prior_sigma_m: float = param_field(
        1.2, "Prior sigma per axis of a never-observed virtual landmark [m].", 0.0, 100.0)

    def __post_init__(self) -> None:
        """``ValueError`` unless a never-observed cell (probability 0.5) is unexplored:
        ``explored_free_below <= 0.5 <= explored_occupied_above``."""
        if not self.explored_free_below <= UNKNOWN_PROBABILITY <= self.explored_occupied_above:
            raise ValueError(
                f"MapParams.explored_free_below ({self.explored_free_below}) must be at most "
                f"{UNKNOWN_PROBABILITY} and explored_occupied_above "
                f"({self.explored_occupied_above}) at least {UNKNOWN_PROBABILITY}: a cell "
                f"never observed has probability {UNKNOWN_PROBABILITY} and is not explored")


@dataclass(frozen=True)
class FrontierParams:
    """Candidate targets: exploration, revisiting and rendezvous frontiers."""

    boundary_distance_m: float = param_field(
        4.0, "Cells closer than this to the map edge are never frontiers [m].", 0.0, 100.0)
    explored_neighbors_below: int = param_field(
        3, "A frontier cell has fewer than this many explored 4-neighbours. The reference code "
        "tests (count - 1) < 2, i.e. fewer than 3; fewer than 2 leaves no frontier at all on "
        "a single sensing disc.", 1, 5)
    exploration_radius_m: float = param_field(
        10.0, "Exploration frontiers are those within this distance of the robot [m].", 0.0, 500.0)
    all_frontiers_below_ratio: float = param_field(
        0.2, "While the explored ratio is below this, every exploration frontier is a candidate.",
        0.0, 1.0)
    revisit_radius_m: float = param_field(
        10.0, "Revisiting frontiers lie within this distance of a known landmark [m].", 0.0, 500.0)
    min_revisiting: int = param_field(
        5, "If fewer revisiting frontiers exist, add frontiers whose straight path passes near "
        "a landmark.", 0, 1000)
    rendezvous_min_distance_m: float = param_field(
        10.0, "A teammate's target is a rendezvous candidate only farther than this [m].",
        0.0, 500.0)
    rendezvous_waiting_penalty: bool = param_field(
        False, "Add |d_self - d_teammate| (expected waiting as distance) to a rendezvous "
        "candidate's U_D, as the reference code does; the paper's U_D is the distance alone.")
    rendezvous_timeout_factor: float = param_field(
        2.0, "A rendezvous partner waits at most this factor times the requester's travel "
        "time to the meeting point (straight line at cruise speed), plus "
        "rendezvous_timeout_margin_s.", 0.0, 100.0)
    rendezvous_timeout_margin_s: float = param_field(
        20.0, "Fixed part of the rendezvous wait limit [s sim time].", 0.0, 1e5)
    teammate_silent_after_s: float = param_field(
        60.0, "A teammate whose latest team update is older than this is out of contact "
        "[s sim time]: a partner stops waiting for it; it stays a rendezvous candidate at "
        "its last known target (meeting restores the link).", 0.0, 1e6)
    max_candidates: int = param_field(
        40, "At most this many candidates are evaluated per decision (nearest first).", 1, 1000)


@dataclass(frozen=True)
class ProgressParams:
    """Judging progress toward a target from the robot's own data, and giving targets up.

    Defaults chosen from measured runs (docs/robustness.md, "Unreachable targets (no
    livelock)"): in runs that finish, no robot driving to a target went ``window_s`` without
    its odometry moving or its estimated target distance shrinking by ``min_progress_m``.
    """

    window_s: float = param_field(
        20.0, "Progress window [s sim time]: a target is given up when, for this long, the "
        "odometry showed less than min_progress_m of translation although forward motion "
        "was commanded at every step (blocked), or the estimated distance to the target "
        "did not shrink by min_progress_m (no progress).", 0.1, 1e5)
    min_progress_m: float = param_field(
        1.0, "Minimum progress within the progress window [m]: odometry translation while "
        "driving, and shrinking of the estimated distance to the target.", 0.0, 1000.0)
    blacklist_radius_m: float = param_field(
        8.0, "After a target is given up (blocked, no progress or deadline), no candidate "
        "within this distance of it is chosen again by that robot [m]; 0 excludes only the "
        "target itself.", 0.0, 1000.0)
    blacklist_duration_s: float = param_field(
        600.0, "How long a given-up target excludes candidates [s sim time]; 1e9: the rest "
        "of the run.", 0.0, 1e9)


@dataclass(frozen=True)
class PlannerParams:
    """Utility-based target selection: EM_2, EM_3, CE, BSP and the nearest frontier rule
    (NEAREST)."""

    name: str = param_field("EM_3", "Planner to use: a built-in one or an installed plugin's "
                            "(docs/plugins.md).", choices=installed_planner_names)
    virtual_waypoint_spacing_m: float = param_field(
        2.0, "Spacing of virtual waypoints along a candidate path in the EM step [m].", 0.1, 100.0)
    allocation_d_max_m: float = param_field(
        30.0, "Task allocation h(d) = 1 - d / d_max below d_max [m].", 0.1, 1000.0)
    allocation_history: int = param_field(
        0, "Number of each teammate's latest targets used by task allocation; 0: all of them "
        "(the paper's set A of all historical targets; the reference code uses 5).", 0, 100000)
    allocation_counts_meeting_point: bool = param_field(
        False, "Count a rendezvous candidate's meeting point (the partner's current target) "
        "in its own U_T, as a literal reading of Eq. (11) does; by default a rendezvous is "
        "not duplicated exploration of the partner's target.")
    q_min: float = param_field(
        0.55, "Algorithm 2: minimum probability of being observed for a cell to count "
        "(the explored threshold as a probability of observation).", 0.0, 1.0)
    history_change_tolerance: float = param_field(
        1e-12, "U_M: a history pose whose covariance trace a candidate reduces by at most "
        "this fraction keeps its current virtual-map contribution. The default is round-off "
        "(exact U_M); a larger value (e.g. 1e-3) is an approximation that recomputes only the "
        "cells of materially changed poses (error measured by em-bench latency).", 0.0, 1.0)
    utility_variant: str = param_field(
        "paper", "'paper': Eq. (13) with U_M over cells observed in both maps; 'reference': "
        "the reference implementation's weights (U_M over all cells, U_T * 100 max(1-r, 0), "
        "U_D * 10 r).", choices=("paper", "reference"))
    em2_lambdas: tuple[float, float, float] = param_field(
        (1.0, 0.0, 10.0), "EM_2 weights (lambda_0 on U_M, lambda_1 on U_T, lambda_2 on U_D).")
    em3_lambdas: tuple[float, float, float] = param_field(
        (1.0, 20.0, 10.0), "EM_3 weights; lambda_1 is multiplied by (1 - explored ratio).")
    ce_lambdas: tuple[float, float] = param_field(
        (1.0, 10.0), "CE weights (lambda_0 on U_D, lambda_1 on U_T).")
    bsp_lambdas: tuple[float, float] = param_field(
        (5.0, 1.0), "BSP weights (lambda_0 on U_D, lambda_1 on U_M = sum trace(sqrt(Sigma_x))).")


@dataclass(frozen=True)
class LinkParams:
    """The links between robots (``core/links/link_model.py``): range, loss, latency, bandwidth.
    The defaults are perfect links: every update reaches every teammate at the next step."""

    range_m: float = param_field(
        0.0, "Communication range [m]: team data reaches only teammates at most this far "
        "away (true positions); 0 = unlimited.", 0.0, 1e6)
    loss_probability: float = param_field(
        0.0, "Probability that one transmission is lost for one receiver (seeded, "
        "independent per transmission and receiver).", 0.0, 0.99)
    latency_s: float = param_field(
        0.0, "Delay from the end of a transmission to its arrival [s sim time].", 0.0, 3600.0)
    bandwidth_bytes_per_s: float = param_field(
        0.0, "Each robot's send budget [bytes per simulated second, CDR on the wire]; "
        "0 = unlimited.", 0.0, 1e9)
    queue_frames: int = param_field(
        20, "Most frames waiting for a robot's channel; a frame offered to a full queue is "
        "dropped (tail drop; the gap repair asks for it again).", 1, 10000)
    repair_interval_s: float = param_field(
        5.0, "A robot missing records of teammates' streams asks for one gap at most this "
        "often, and re-sends to one requester at most this often [s sim time] (requests "
        "cross the links too and cost bandwidth).", 0.0, 3600.0)


@dataclass(frozen=True)
class RunParams:
    """When an exploration run stops, and its seed."""

    seed: int = param_field(0, "Seed of the world and of every noise draw.", 0, 2**31 - 1)
    until_explored: float = param_field(0.85, "Stop when the team's explored ratio reaches this.",
                                        0.0, 1.0)
    max_steps: int = param_field(20000, "Stop after this many simulation steps.", 1, 10**8)
    max_distance_m: float = param_field(
        1e9, "Stop when the team has travelled this far in total [m] (reference: 1400 m).",
        0.0, 1e9)
    stall_timeout_s: float = param_field(
        300.0, "End the run as stalled when, for this long [s sim time], the team neither "
        "travelled nor explored new area (exit code 4); 0 disables the rule.", 0.0, 1e9)


#: Planner names that were renamed, old -> new. The old name still selects its planner,
#: with a deprecation warning ("NF" read like the paper's cited Next Frontier method).
RENAMED_PLANNERS: Mapping[str, str] = MappingProxyType({"NF": "NEAREST"})

#: Parameters that were removed, ``'group.field'`` -> why. A file that still sets one loads
#: with a deprecation warning; the value is ignored.
REMOVED_PARAMETERS: Mapping[str, str] = MappingProxyType({
    "planner.allocation_waypoint_spacing_m": "task allocation uses the targets themselves",
    "frontiers.rendezvous_timeout_s": "the wait scales with the requester's travel "
                                      "(frontiers.rendezvous_timeout_factor, _margin_s)"})


class ParameterDeprecationWarning(FutureWarning):
    """A deprecated parameter name or value was used (shown once per message and process)."""


def upgrade_deprecated(groups: Mapping[str, Mapping[str, Any]]
                       ) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """``groups`` (``{group: {field: value}}``) with the removed parameters dropped and
    renamed planner names replaced by the new ones, and one message per replacement."""
    upgraded = {group: dict(values) if isinstance(values, Mapping) else values
                for group, values in groups.items()}
    messages = []
    for name, reason in REMOVED_PARAMETERS.items():
        group, _, field_name = name.partition(".")
        if isinstance(upgraded.get(group), dict) and field_name in upgraded[group]:
            del upgraded[group][field_name]
            messages.append(f"parameter {name} is deprecated and ignored ({reason}); "
                            "remove it from the parameter file")
    planner = upgraded.get("planner")
    planner_name = planner.get("name") if isinstance(planner, dict) else None
    if isinstance(planner_name, str) and planner_name in RENAMED_PLANNERS:
        upgraded["planner"]["name"] = RENAMED_PLANNERS[planner_name]
        messages.append(_planner_renamed(planner_name))
    return upgraded, messages


def _planner_renamed(old_name: str) -> str:
    """The deprecation message of the renamed planner ``old_name``."""
    new_name = RENAMED_PLANNERS[old_name]
    return f"planner name {old_name!r} is deprecated; using {new_name!r} (write {new_name})"


def current_planner_name(name: str) -> str:
    """``name``, or the new name of a renamed planner (with a
    ``ParameterDeprecationWarning``); for command-line options that name planners."""
    if name in RENAMED_PLANNERS:
        warnings.warn(_planner_renamed(name), ParameterDeprecationWarning, stacklevel=1)
        return RENAMED_PLANNERS[name]
    return name


def _upgraded_with_warnings(groups: Mapping[str, Mapping[str, Any]]
                            ) -> dict[str, dict[str, Any]]:
    """``upgrade_deprecated`` with each message issued as a ``ParameterDeprecationWarning``."""
    upgraded, messages = upgrade_deprecated(groups)
    for message in messages:
        warnings.warn(message, ParameterDeprecationWarning, stacklevel=1)
    return upgraded


@dataclass(frozen=True)
class ExplorationParams:
    """All parameter groups of one exploration run."""

    world: WorldParams = field(default_factory=WorldParams)
    sensors: SensorParams = field(default_factory=SensorParams)
    motion: MotionParams = field(default_factory=MotionParams)
    slam: SlamParams = field(default_factory=SlamParams)
    map: MapParams = field(default_factory=MapParams)
    frontiers: FrontierParams = field(default_factory=FrontierParams)
    progress: ProgressParams = field(default_factory=ProgressParams)
    planner: PlannerParams = field(default_factory=PlannerParams)
    links: LinkParams = field(default_factory=LinkParams)
    run: RunParams = field(default_factory=RunParams)

    def __post_init__(self) -> None:
        """``ValueError`` if the virtual map has fewer than ``MIN_CELLS_PER_SIDE`` cells
        along a side of the world."""
        shortest_side_m = min(self.world.width_m, self.world.height_m)
        if self.map.cell_size_m * MIN_CELLS_PER_SIDE > shortest_side_m:
            raise ValueError(
                f"MapParams.cell_size_m = {self.map.cell_size_m} m gives fewer than "
                f"{MIN_CELLS_PER_SIDE} cells along the world's {shortest_side_m} m side; "
                f"use at most {shortest_side_m / MIN_CELLS_PER_SIDE:g} m")

    def flat(self) -> dict[str, Any]:
        """All parameters as ``{'group.field': value}``, the ROS parameter names."""
        out: dict[str, Any] = {}
        for group in dataclasses.fields(self):
            group_value = getattr(self, group.name)
            for f in dataclasses.fields(group_value):
                out[f"{group.name}.{f.name}"] = getattr(group_value, f.name)
        return out

    def replace(self, **group_overrides: Mapping[str, Any]) -> "ExplorationParams":
        """A copy with some fields changed: ``params.replace(world={'num_robots': 5})``.

        Deprecated names and values are upgraded with a ``ParameterDeprecationWarning``
        (``upgrade_deprecated``)."""
        group_overrides = _upgraded_with_warnings(group_overrides)
        groups = {f.name for f in dataclasses.fields(self)}
        _refuse_unknown(group_overrides, groups, "parameter group")
        changed = {name: replace_checked(getattr(self, name), overrides)
                   for name, overrides in group_overrides.items()}
        return dataclasses.replace(self, **changed)


def replace_checked(group: Any, overrides: Mapping[str, Any]) -> Any:
    """Copy of a parameter group with ``overrides`` applied after type and range checks."""
    fields = {f.name: f for f in dataclasses.fields(group)}
    _refuse_unknown(overrides, fields, f"parameter in {type(group).__name__}")
    checked = {name: _checked_value(type(group).__name__, fields[name], getattr(group, name), value)
               for name, value in overrides.items()}
    return dataclasses.replace(group, **checked)


def closest_name_hint(name: str, known: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the known name closest to a misspelt ``name``, or ''."""
    matches = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f" (did you mean '{matches[0]}'?)" if matches else ""


def _refuse_unknown(names: Iterable[str], known: Iterable[str], what: str) -> None:
    """``ValueError`` for the first of ``names`` not in ``known``, with the closest name."""
    known = sorted(known)
    for name in sorted(set(names) - set(known)):
        raise ValueError(f"unknown {what}: '{name}'{closest_name_hint(name, known)}; "
                         f"known: {', '.join(known)}")


def _as_float(value: Any) -> float:
    """``float(value)``, with an integer beyond the float range as +-inf (so the finiteness
    check refuses it instead of ``OverflowError``)."""
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def _checked_value(group_name: str, f: dataclasses.Field, default: Any, value: Any) -> Any:
    """Coerce ``value`` to the type of the field's default and check its range."""
    where = f"{group_name}.{f.name}"
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{where} must be true or false, got {shown_value(value)}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or len(value) != len(default):
            raise ValueError(f"{where} must be a list of {len(default)} numbers, "
                             f"got {shown_value(value)}")
        try:
            coerced_tuple = tuple(_as_float(v) for v in value)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{where} must be numbers, got {shown_value(value)}") from error
        if not all(math.isfinite(v) for v in coerced_tuple):
            raise ValueError(f"{where} must be finite, got {shown_value(value)}")
        return coerced_tuple
    if isinstance(default, str):
        choices = field_choices(f)
        if not isinstance(value, str) or (choices is not None and value not in choices):
            raise ValueError(f"{where} must be one of {choices}, got {shown_value(value)}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ValueError(f"{where} must be an integer, got {shown_value(value)}")
    else:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where} must be a number, got {shown_value(value)}")
        number = _as_float(value)
        if not math.isfinite(number):
            raise ValueError(f"{where} must be finite, got {shown_value(value)}")
        value = number
    low, high = f.metadata.get("low"), f.metadata.get("high")
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"{where} = {shown_value(value)} is outside [{low}, {high}]")
    return value
