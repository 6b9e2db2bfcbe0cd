#!/usr/bin/env bash
# Run a team exploration over ROS 2: the world simulator, N robot processes and the evaluator,
# each its own OS process talking over DDS. This is the project's main command.
#
#   launch_scripts/run_team.sh                       3 robots, EM_3, 100 m x 100 m, 20 landmarks,
#                                                    until explored ratio 0.85, lockstep
#   launch_scripts/run_team.sh --robots 2 --planner NEAREST --map-size 40 --landmarks 4 --seed 3
#
# Run with --help for the options. Exit code: the evaluator's (0 done, 3 the robots or the world
# stopped publishing, 4 stalled: the team neither travelled nor explored new area for
# run.stall_timeout_s, 5 every live robot finished below the explored goal while other robots
# were lost), 7 the evaluator died before the run ended (its summary so far is kept), 1 if a
# process failed, 2 for bad arguments, 130 on Ctrl-C, 143 on SIGTERM,
# 129 on SIGHUP (the terminal closed, the SSH connection lost).
#
# Environment: EM_EVALUATOR_END_GRACE_S (default 60) wall seconds the evaluator has, after the
# world stepped over, to end the run before it is taken for wedged (a run's tests shorten it).
# EM_PLUGIN_PATH: folders (':'-separated) of planner plugins installed apart with pip install
# --target, on every process's PYTHONPATH (docs/plugins.md).
set -uo pipefail

# shellcheck source=launch_scripts/_common.sh
source "$(dirname "${BASH_SOURCE[0]}")/_common.sh"

PROG=run_team.sh
# Deprecated planner names, still accepted with a warning: old name -> new name.
declare -A RENAMED_PLANNERS=([NF]=NEAREST)
NODES=em_exploration_ros.nodes
RECORD_MODULE=em_exploration_ros.tools.record
TRACE_MODULE=em_exploration_ros.tools.step_trace
FOXGLOVE_MODULE=em_exploration_ros.tools.foxglove_bridge
# Grace periods [s] of a stop: after SIGINT (nodes write their results), after SIGTERM.
STOP_GRACE_S=10
KILL_GRACE_S=3
# --respawn: the world's "robot <i> lost" lines within this many seconds after a robot's
# (re)start, until the world takes the new process back, are about its previous process (its
# liveliness lease expiring), not the new one.
RESPAWN_GRACE_S=15
# --respawn: at most this many restarts per robot (a robot that keeps crashing stays down).
MAX_RESPAWNS=10
# --respawn: a restarted robot whose liveliness the world has not seen within this many
# seconds is wedged in its start-up (it is never reported lost: the world counts it stopped
# already) and is restarted again. Start-up takes 2-4 s here, 20 s on a loaded machine.
RESPAWN_CONFIRM_S=${EM_RESPAWN_CONFIRM_S:-60}
# Wall seconds the evaluator has, once the world has stepped over (its log says so), to write
# the summary and the map and exit; after that it is taken for wedged (or stopped) and the run
# fails. Generous: the final evaluation and the map of a large run take a few seconds.
EVALUATOR_END_GRACE_S=${EM_EVALUATOR_END_GRACE_S:-60}

usage() {
    cat <<EOF
usage: $PROG [options]

Runs em-world, N em-robot and em-evaluator as separate processes in one ROS 2 domain and
waits for the evaluator to end the run. Progress lines come from the evaluator; each process
logs to <run dir>/logs/<name>.log. Flags override the parameter file for every node.
Exit code: 0 done, 3 the world or the robots stopped publishing, 4 stalled (no team
progress for run.stall_timeout_s), 5 robots lost (every live robot finished below the
explored goal), 6 done but the recording (--record) is incomplete (em-record stopped
early, e.g. on a full disk: the bag holds the run up to then, and the summary's
"recording" says why), 7 the evaluator died before the run ended (the team is stopped;
the summary so far is kept, stop reason "evaluator lost: ..."), 1 a process failed,
2 bad arguments, 130 Ctrl-C, 143 SIGTERM, 129 SIGHUP (terminal closed).

options:
  --robots N              number of robots, 1..26 (file default: 3)
  --seed S                seed of the world and of every noise draw, >= 0 (default: 0)
  --planner NAME          EM_2, EM_3, CE, BSP, NEAREST or an installed plugin's planner
                          (docs/plugins.md; default: EM_3)
  --map-size M            side of the square map [m], 10..2000 (default: 100)
  --cell-size M           virtual map cell size [m], 0.1..50 (default: 2; the paper's 200 m
                          map: 4)
  --landmarks K           number of landmarks, 0..1000 (default: 20)
  --world FILE            world YAML file (map size, landmarks, start poses; docs/worlds.md)
                          instead of the world the seed generates; --robots defaults to one
                          per start (not with --map-size or --landmarks)
  --until-explored R      stop at this team explored ratio, 0..1 (default: 0.85)
  --max-sim-time S        stop after S seconds of simulation time (default: no limit)
  --comm-range M          links: communication range [m] (default 0 = unlimited)
  --comm-loss P           links: loss probability per transmission and receiver, 0..0.99
  --comm-latency S        links: latency [s sim time] (default 0)
  --comm-bandwidth B      links: each robot's send budget [bytes/s] (default 0 = unlimited)
                          (any of these set: the world relays all team data through the
                          link model, as em-sim does with the same flags)
  --landmark-ids on|off   sonar: on, each detection names its landmark (default); off, none
                          does and each robot associates its detections itself
  --detection-prob P      sonar: probability of detecting each landmark in range, 0..1
                          (default 1)
  --clutter-rate R        sonar: mean number of false detections per scan, uniform in range
                          and bearing, 0..1000 (default 0)
  --params FILE           ROS 2 parameter YAML (default: config/exploration.yaml)
  --realtime [FACTOR]     step on a wall timer, FACTOR sim seconds per wall second
                          (default 1.0) instead of lockstep
  --summary FILE          summary JSON (default: runs/<date>_seed<S>_<planner>/summary.json);
                          the map picture goes beside it (<stem>_map.png), logs in logs/
  --domain-id ID          ROS_DOMAIN_ID, 0..232 (default: a free id in 1..101, held by a lock)
  --record [PATH]         record every topic with em-record into the bag directory PATH
                          (default: bags/<date>_seed<S>_<planner>; must not exist)
  --foxglove [PORT]       serve the team live to the Foxglove app with em-foxglove on
                          ws://127.0.0.1:PORT (default PORT: 8765); the run goes on if it stops
  --respawn               restart a robot process that dies, or that the world reports lost
                          (alive but wedged or silent: SIGKILL, then the same command line),
                          or whose restart the world has not seen alive within
                          EM_RESPAWN_CONFIRM_S seconds (default 60); it rejoins the team
                          where it stopped. An evaluator that dies before the run ended is
                          restarted too: it reads the run back from the world's ground
                          truth and the robots' estimates, answers and streams
  --trace-steps DIR       record every publish and subscription callback of the world, the
                          robots and the evaluator into DIR/<name>.trace (DIR must not hold
                          traces yet); python -m em_exploration_ros.tools.step_trace report
                          DIR prints where a lockstep step's time goes
  --netns PREFIX          separate hosts: run robot i in network namespace PREFIXrobot_<i> and
                          every other process in PREFIXworld (they must exist and be joined;
                          needs root; DDS over UDPv4 with multicast discovery on the subnet).
                          python -m em_exploration_ros.tools.separate_hosts makes them
  -h, --help              show this help and exit
EOF
}

# Folders this run made before a check refused it, deepest first: removed again if empty.
MADE_FOR_THE_RUN=()
usage_error() {
    echo "$PROG: error: $*" >&2
    echo "Try '$PROG --help'." >&2
    (( ${#MADE_FOR_THE_RUN[@]} )) && rmdir "${MADE_FOR_THE_RUN[@]}" 2>/dev/null
    exit 2
}

is_int() { [[ $1 =~ ^[0-9]+$ ]]; }
is_number() { [[ $1 =~ ^([0-9]+([.][0-9]*)?|[.][0-9]+)([eE][-+]?[0-9]+)?$ ]]; }

# check_number FLAG VALUE LOW HIGH [int]: refuse a value that is not a number in [LOW, HIGH].
check_number() {
    local flag=$1 value=$2 low=$3 high=$4 kind=${5:-float}
    if [[ $kind == int ]]; then
        is_int "$value" || usage_error "$flag expects a whole number, got '$value'"
    else
        is_number "$value" || usage_error "$flag expects a number, got '$value'"
    fi
    awk -v v="$value" -v lo="$low" -v hi="$high" 'BEGIN { exit !(v + 0 >= lo + 0 && v + 0 <= hi + 0) }' \
        || usage_error "$flag must be in [$low, $high], got '$value'"
}

needs_value() {  # needs_value REST...: the flag in $arg must be followed by a value
    if ! (( $# )) || [[ $inline_value == 0 && $1 == --* ]]; then usage_error "$arg needs a value"; fi
}

# A number as a ROS double literal (the nodes declare these parameters as doubles).
as_double() { if [[ $1 =~ [.eE] ]]; then printf '%s' "$1"; else printf '%s.0' "$1"; fi; }

# A text as a ROS string literal: a YAML double-quoted string (ROS parses a -p value as YAML,
# so a bare path with " #" or ": " in it is cut short or refused). Control characters are
# refused with the arguments (check_path).
as_string() {
    local text=${1//\\/\\\\}
    printf '"%s"' "${text//\"/\\\"}"
}

# check_path FLAG PATH: refuse a path with a control character (a newline, a tab, ...): it
# would break the nodes' parameters and this script's report lines.
check_path() {
    [[ $2 != *[[:cntrl:]]* ]] \
        || usage_error "$1: the path must not contain control characters, got $(printf '%q' "$2")"
}

# exit_status_text STATUS: how a process ended, from its wait status ("exited with code 137
# (signal KILL)" for one killed by a signal: bash reports 128 + the signal number).
exit_status_text() {
    local text="exited with code $1"
    if (( $1 > 128 )) && kill -l "$1" >/dev/null 2>&1; then
        text+=" (signal $(kill -l "$1"))"
    fi
    printf '%s' "$text"
}

# -- arguments -------------------------------------------------------------------------------
ROBOTS="" SEED="" PLANNER="" MAP_SIZE="" CELL_SIZE="" LANDMARKS="" UNTIL="" MAX_SIM_TIME="" COMM_RANGE="" COMM_LOSS="" COMM_LATENCY="" COMM_BANDWIDTH=""
LANDMARK_IDS="" DETECTION_PROB="" CLUTTER_RATE=""
PARAMS_FILE="$EM_REPO_ROOT/config/exploration.yaml"
REALTIME="" SUMMARY="" DOMAIN_ID="" RECORD="" RECORD_PATH="" FOXGLOVE_PORT="" RESPAWN="" NETNS=""
TRACE_DIR="" WORLD_FILE=""

while (( $# )); do
    arg=$1
    shift
    if [[ $arg == --*=* ]]; then
        set -- "${arg#*=}" "$@"
        arg=${arg%%=*}
        inline_value=1
    else
        inline_value=0
    fi
    case $arg in
        -h|--help) usage; exit 0 ;;
        --robots) needs_value "$@"; check_number "$arg" "$1" 1 26 int; ROBOTS=$1; shift ;;
        --seed) needs_value "$@"; check_number "$arg" "$1" 0 2147483647 int; SEED=$1; shift ;;
        --planner)
            needs_value "$@"
            if [[ -n $1 && -n ${RENAMED_PLANNERS[$1]:-} ]]; then
                echo "$PROG: warning: planner name '$1' is deprecated; using" \
                     "'${RENAMED_PLANNERS[$1]}' (write ${RENAMED_PLANNERS[$1]})" >&2
                set -- "${RENAMED_PLANNERS[$1]}" "${@:2}"
            fi
            PLANNER=$1; shift ;;
        --map-size) needs_value "$@"; check_number "$arg" "$1" 10 2000; MAP_SIZE=$1; shift ;;
        --cell-size) needs_value "$@"; check_number "$arg" "$1" 0.1 50; CELL_SIZE=$1; shift ;;
        --landmarks) needs_value "$@"; check_number "$arg" "$1" 0 1000 int; LANDMARKS=$1; shift ;;
        --world)
            needs_value "$@"; check_path "$arg" "$1"
            WORLD_FILE=$(cd "$(dirname "$1")" 2>/dev/null && pwd)/$(basename "$1") \
                || usage_error "--world: no folder '$(dirname "$1")'"
            shift ;;
        --until-explored) needs_value "$@"; check_number "$arg" "$1" 0 1; UNTIL=$1; shift ;;
        --max-sim-time) needs_value "$@"; check_number "$arg" "$1" 0 1e9; MAX_SIM_TIME=$1; shift ;;
        --comm-range) needs_value "$@"; check_number "$arg" "$1" 0 1000000; COMM_RANGE=$1; shift ;;
        --comm-loss) needs_value "$@"; check_number "$arg" "$1" 0 0.99; COMM_LOSS=$1; shift ;;
        --comm-latency) needs_value "$@"; check_number "$arg" "$1" 0 3600; COMM_LATENCY=$1; shift ;;
        --comm-bandwidth)
            needs_value "$@"; check_number "$arg" "$1" 0 1000000000; COMM_BANDWIDTH=$1; shift ;;
        --landmark-ids)
            needs_value "$@"
            case $1 in
                on) LANDMARK_IDS=true ;;
                off) LANDMARK_IDS=false ;;
                *) usage_error "--landmark-ids must be on or off, got '$1'" ;;
            esac
            shift ;;
        --detection-prob) needs_value "$@"; check_number "$arg" "$1" 0 1; DETECTION_PROB=$1; shift ;;
        --clutter-rate) needs_value "$@"; check_number "$arg" "$1" 0 1000; CLUTTER_RATE=$1; shift ;;
        --params)
            needs_value "$@"
            [[ -f $1 && -r $1 ]] || usage_error "--params: no readable file '$1'"
            PARAMS_FILE=$(cd "$(dirname "$1")" && pwd)/$(basename "$1"); shift ;;
        --realtime)
            REALTIME=1.0
            if (( $# )) && { [[ $inline_value == 1 ]] || is_number "$1"; }; then
                check_number "$arg" "$1" 0.01 1000; REALTIME=$1; shift
            fi ;;
        --summary) needs_value "$@"; check_path "$arg" "$1"; SUMMARY=$1; shift ;;
        --domain-id) needs_value "$@"; check_number "$arg" "$1" 0 232 int; DOMAIN_ID=$1; shift ;;
        --record)
            RECORD=1
            if (( $# )) && [[ $inline_value == 1 || $1 != -* ]]; then
                check_path "$arg" "$1"; RECORD_PATH=$1; shift
            fi ;;
        --foxglove)
            FOXGLOVE_PORT=8765
            if (( $# )) && { [[ $inline_value == 1 ]] || is_int "$1"; }; then
                check_number "$arg" "$1" 1 65535 int; FOXGLOVE_PORT=$1; shift
            fi ;;
        --respawn) RESPAWN=1 ;;
        --netns) needs_value "$@"; NETNS=$1; shift ;;
        --trace-steps) needs_value "$@"; check_path "$arg" "$1"; TRACE_DIR=$1; shift ;;
        *) usage_error "unknown argument '$arg'" ;;
    esac
done

[[ -n $WORLD_FILE && -n $MAP_SIZE$LANDMARKS ]] \
    && usage_error "--world gives the map size and the landmarks: drop --map-size and --landmarks"
is_int "$EVALUATOR_END_GRACE_S" \
    || usage_error "EM_EVALUATOR_END_GRACE_S expects a whole number of seconds, got '$EVALUATOR_END_GRACE_S'"
is_int "$RESPAWN_CONFIRM_S" \
    || usage_error "EM_RESPAWN_CONFIRM_S expects a whole number of seconds, got '$RESPAWN_CONFIRM_S'"
if [[ -n $RECORD && ! -f "$EM_REPO_ROOT/${RECORD_MODULE//.//}.py" ]]; then
    usage_error "--record needs em-record ($RECORD_MODULE), which this checkout does not have"
fi
if [[ ! -f "$EM_REPO_ROOT/${NODES//.//}/robot_node.py" ]]; then
    echo "$PROG: error: the robot node ($NODES.robot_node) is missing from this checkout" >&2
    exit 1
fi

# -- environment and effective parameters ------------------------------------------------------
"$EM_REPO_ROOT/launch_scripts/setup_env.sh" || { echo "$PROG: error: set-up failed" >&2; exit 1; }
em_activate
PYTHON="$EM_VENV/bin/python"

OVERRIDES=()
[[ -n $ROBOTS ]] && OVERRIDES+=(-p "world.num_robots:=$ROBOTS")
[[ -n $SEED ]] && OVERRIDES+=(-p "run.seed:=$SEED")
[[ -n $PLANNER ]] && OVERRIDES+=(-p "planner.name:=$PLANNER")
[[ -n $MAP_SIZE ]] && OVERRIDES+=(-p "world.width_m:=$(as_double "$MAP_SIZE")"
                                  -p "world.height_m:=$(as_double "$MAP_SIZE")")
[[ -n $CELL_SIZE ]] && OVERRIDES+=(-p "map.cell_size_m:=$(as_double "$CELL_SIZE")")
[[ -n $LANDMARKS ]] && OVERRIDES+=(-p "world.num_landmarks:=$LANDMARKS")
[[ -n $WORLD_FILE ]] && OVERRIDES+=(-p "world.file:=$(as_string "$WORLD_FILE")")
[[ -n $UNTIL ]] && OVERRIDES+=(-p "run.until_explored:=$(as_double "$UNTIL")")
[[ -n $COMM_RANGE ]] && OVERRIDES+=(-p "links.range_m:=$(as_double "$COMM_RANGE")")
[[ -n $COMM_LOSS ]] && OVERRIDES+=(-p "links.loss_probability:=$(as_double "$COMM_LOSS")")
[[ -n $COMM_LATENCY ]] && OVERRIDES+=(-p "links.latency_s:=$(as_double "$COMM_LATENCY")")
[[ -n $COMM_BANDWIDTH ]] && OVERRIDES+=(
    -p "links.bandwidth_bytes_per_s:=$(as_double "$COMM_BANDWIDTH")")
[[ -n $LANDMARK_IDS ]] && OVERRIDES+=(-p "sensors.landmark_ids:=$LANDMARK_IDS")
[[ -n $DETECTION_PROB ]] && OVERRIDES+=(
    -p "sensors.detection_probability:=$(as_double "$DETECTION_PROB")")
[[ -n $CLUTTER_RATE ]] && OVERRIDES+=(-p "sensors.clutter_rate:=$(as_double "$CLUTTER_RATE")")

# Check the file with the overrides as the nodes will read them (and that the world can be
# built), and learn the values the run's names need: "<robots> <seed> <planner>", then (with a
# world file, --world or world.file) one line per world parameter the file sets, which every
# node gets. Errors are printed to stdout (captured; exit 3 for a --planner that names no
# installed planner, a bad argument); warnings (deprecated parameters) go to stderr.
RESOLVED=$("$PYTHON" - "$PARAMS_FILE" "${OVERRIDES[@]}" <<'PY'
import json
import sys

import yaml

from em_exploration_ros.core.params_yaml import ParamsFileError, load_params, nest_dotted
from em_exploration_ros.core.planner_registry import installed_planner_names
from em_exploration_ros.core.world.world_file import (params_for_world, read_world_file,
                                                      world_for_params)

path, args = sys.argv[1], sys.argv[2:]
values = {}
for flag, assignment in zip(args[::2], args[1::2]):
    name, value = assignment.split(":=", 1)
    if value in ("true", "false"):
        values[name] = value == "true"
    else:
        values[name] = value if name == "planner.name" else yaml.safe_load(value) if name == "world.file" else float(value) if "." in value or "e" in value else int(value)
planner, installed = values.get("planner.name"), installed_planner_names()
if planner is not None and planner not in installed:
    print(f"unknown planner '{planner}' (installed: {' '.join(installed)})")
    sys.exit(3)
try:
    params = load_params(path)
    params = params.replace(**nest_dotted(values)) if values else params
    if params.world.file:
        params = params_for_world(params, read_world_file(params.world.file), params.world.file,
                                  values.get("world.num_robots"))
    world_for_params(params)
except (ParamsFileError, ValueError, RuntimeError) as error:
    print(error)
    sys.exit(1)
print(params.world.num_robots, params.run.seed, params.planner.name)
if params.world.file:
    for name in ("file", "width_m", "height_m", "num_landmarks", "landmark_radius_m", "num_robots"):
        print(f"world.{name}:={json.dumps(getattr(params.world, name))}")
PY
)
case $? in
    0) ;;
    3) usage_error "$RESOLVED" ;;  # --planner names no installed planner
    *) echo "$PROG: error: invalid parameters: $RESOLVED" >&2; exit 2 ;;
esac
{ read -r NUM_ROBOTS RUN_SEED RUN_PLANNER; mapfile -t WORLD_SETTINGS; } <<<"$RESOLVED"
for setting in "${WORLD_SETTINGS[@]}"; do OVERRIDES+=(-p "$setting"); done
# The run's identity, carried by every project message its nodes publish: a node drops, with
# a WARN naming the other run, what another run on the same domain publishes (a domain held
# by a live run is refused below; a run started by hand, or a stale process, is not held).
# Unique per run: the start time [ns] mixed with this shell's pid, as a positive int64.
RUN_ID=$(( ($(date +%s%N) ^ ($$ << 40)) & 0x7fffffffffffffff ))
OVERRIDES+=(-p "run_id:=$RUN_ID")
if [[ -n $NETNS ]]; then
    for host in world $(seq -f "robot_%g" 0 $(( NUM_ROBOTS - 1 ))); do
        ip netns exec "$NETNS$host" true 2>/dev/null \
            || usage_error "--netns: cannot run in network namespace '$NETNS$host' (missing, or not root)"
    done
fi

STAMP=$(date +%Y%m%d-%H%M%S)
RUN_NAME="${STAMP}_seed${RUN_SEED}_${RUN_PLANNER}"
SUMMARY=${SUMMARY:-"$EM_REPO_ROOT/runs/$RUN_NAME/summary.json"}
[[ -d $(dirname "$SUMMARY") ]] || SUMMARY_DIR_MADE=1
mkdir -p "$(dirname "$SUMMARY")" 2>/dev/null || usage_error "--summary: cannot create the folder of '$SUMMARY'"
SUMMARY="$(cd "$(dirname "$SUMMARY")" && pwd)/$(basename "$SUMMARY")"
[[ -n ${SUMMARY_DIR_MADE:-} ]] && MADE_FOR_THE_RUN=("$(dirname "$SUMMARY")")
SUMMARY_STEM=$(basename "$SUMMARY")
MAP_PNG="$(dirname "$SUMMARY")/${SUMMARY_STEM%.*}_map.png"
LOG_DIR="$(dirname "$SUMMARY")/logs"
STATE_DIR="$(dirname "$SUMMARY")/state"  # the robots' stream journals, read after a restart
if [[ -n $RECORD ]]; then
    RECORD_PATH=${RECORD_PATH:-"$EM_REPO_ROOT/bags/$RUN_NAME"}
    mkdir -p "$(dirname "$RECORD_PATH")" 2>/dev/null \
        || usage_error "--record: cannot create the folder of '$RECORD_PATH'"
fi
# The folders the run writes into exist before the outputs are checked: a recording must not
# go where one of them is (it would fail only once the team has started). A log folder that
# cannot be made is refused after the check, which says better why for an unwritable folder.
mkdir -p "$LOG_DIR/ros" "$STATE_DIR" 2>/dev/null
MADE_FOR_THE_RUN=("$LOG_DIR/ros" "$LOG_DIR" "$STATE_DIR" "${MADE_FOR_THE_RUN[@]}")
if [[ -n $TRACE_DIR ]]; then
    [[ -d $TRACE_DIR ]] || MADE_FOR_THE_RUN=("$TRACE_DIR" "${MADE_FOR_THE_RUN[@]}")
    mkdir -p "$TRACE_DIR" 2>/dev/null || usage_error "--trace-steps: cannot create '$TRACE_DIR'"
    compgen -G "$TRACE_DIR/*.trace" >/dev/null \
        && usage_error "--trace-steps: '$TRACE_DIR' already holds traces of another run"
    TRACE_DIR=$(cd "$TRACE_DIR" && pwd)
fi
# Every output file must be writable before anything runs (a read-only folder would
# otherwise lose the run at its end).
OUTPUTS=(--summary "$SUMMARY" --summary "$MAP_PNG")
[[ -n $RECORD ]] && OUTPUTS+=(--record "$RECORD_PATH")
if ! PROBLEM=$("$PYTHON" - "${OUTPUTS[@]}" 2>&1 <<'PY'
import sys

from em_exploration_ros.core.output_paths import output_path_problem

for flag, path in zip(sys.argv[1::2], sys.argv[2::2]):
    problem = output_path_problem(path, flag)
    if problem:
        print(problem)
        sys.exit(1)
PY
); then
    usage_error "$PROBLEM"
fi
[[ -d $LOG_DIR/ros ]] || usage_error "--summary: cannot create the log folder '$LOG_DIR'"
[[ -d $STATE_DIR ]] || usage_error "--summary: cannot create the state folder '$STATE_DIR'"
if [[ -n $DOMAIN_ID ]]; then
    export ROS_DOMAIN_ID=$DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
else
    em_pick_ros_domain || exit 1
fi
# Two runs in one domain would take each other's messages: a domain a live run holds is
# refused, whether it was given (--domain-id) or chosen (a chooser that skips held domains).
RUN_LOCK_TEXT="run_team.sh pid $$, seed $RUN_SEED, run folder $(dirname "$SUMMARY")"
em_hold_run_lock "$ROS_DOMAIN_ID" "$RUN_LOCK_TEXT" \
    || usage_error "ROS_DOMAIN_ID $ROS_DOMAIN_ID is in use by another run of this project" \
        "(${EM_RUN_LOCK_HOLDER:-holder unknown}); give another --domain-id, or none for a free one"
rm -f "$SUMMARY" "$MAP_PNG" "$LOG_DIR"/*.log  # logs are appended to (a respawned robot's too)
rm -f "$STATE_DIR"/robot_*.journal "$STATE_DIR"/robot_*.journal.new  # another run's streams
if [[ -n $NETNS ]]; then  # hosts apart: discovery by multicast on the subnet, no shared memory
    export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET FASTDDS_BUILTIN_TRANSPORTS=UDPv4
fi
export ROS_LOG_DIR="$LOG_DIR/ros" PYTHONUNBUFFERED=1 RCUTILS_LOGGING_BUFFERED_STREAM=1 \
    RCUTILS_COLORIZED_OUTPUT=0

# -- processes -------------------------------------------------------------------------------
PIDS=() NAMES=()

# start NAME ARGS...: run "python ARGS" in its own session (so its own process group); with
# --netns, robot_<i> in namespace PREFIXrobot_<i> and everything else in PREFIXworld (ip netns
# exec runs the command in the same process, so the PID is still the group's). A restarted
# process keeps off its dead predecessor's Fast DDS participant id by itself
# (em_exploration_ros/nodes/participant_id.py).
start() {
    local name=$1 host=()
    shift
    if [[ -n $NETNS ]]; then
        [[ $name == robot_* ]] && host=(ip netns exec "$NETNS$name") \
            || host=(ip netns exec "${NETNS}world")
    fi
    local command=("$@")
    if [[ -n $TRACE_DIR && ( $name == world || $name == evaluator || $name == robot_* ) ]]; then
        command=(-m "$TRACE_MODULE" run --out "$TRACE_DIR/$name.trace" "${@:2}")
    fi
    setsid "${host[@]}" "$PYTHON" "${command[@]}" >>"$LOG_DIR/$name.log" 2>&1 </dev/null &
    PIDS+=("$!")
    NAMES+=("$name")
}

group_alive() { kill -0 -- "-$1" 2>/dev/null; }

# Wait until no process group of ours is alive, at most $1 seconds; 0 if none is left.
wait_groups() {
    local deadline=$(( SECONDS + $1 )) pid alive
    while :; do
        alive=0
        for pid in "${PIDS[@]}"; do group_alive "$pid" && alive=1; done
        (( alive )) || return 0
        (( SECONDS < deadline )) || return 1
        sleep 0.2
    done
}

# SIGINT every group (nodes finish their work), then SIGTERM, then SIGKILL what is left. A
# stopped process (SIGSTOP, Ctrl-Z) is continued after the SIGINT, so that it can act on it.
stop_all() {
    local pid signal
    for signal in INT TERM KILL; do
        for pid in "${PIDS[@]}"; do
            group_alive "$pid" || continue
            kill "-$signal" -- "-$pid" 2>/dev/null
            [[ $signal == INT ]] && kill -CONT -- "-$pid" 2>/dev/null
        done
        case $signal in
            INT) wait_groups "$STOP_GRACE_S" && break ;;
            TERM) wait_groups "$KILL_GRACE_S" && break ;;
            KILL) wait_groups "$KILL_GRACE_S" ;;
        esac
    done
    wait 2>/dev/null
}

# The lines a ROS user pastes into a second terminal to see this team (ros2 topic list, rviz2):
# a ROS 2 Jazzy install with this venv's packages added (docs/topics.md), then the ROS
# environment the run's processes have.
print_second_terminal() {
    local site variable exports=export
    site=$(compgen -G "$EM_VENV/lib/python3*/site-packages" | head -n 1)
    echo "$PROG: to see the team from a second terminal (ROS 2 Jazzy; docs/topics.md), paste:"
    echo "source /opt/ros/jazzy/setup.bash"
    # shellcheck disable=SC2016  # $AMENT_PREFIX_PATH and $PYTHONPATH: the second terminal's
    printf 'export AMENT_PREFIX_PATH=$AMENT_PREFIX_PATH:%q PYTHONPATH=$PYTHONPATH:%q\n' \
        "$EM_VENV" "$site"
    for variable in ROS_DISTRO ROS_DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE RMW_IMPLEMENTATION \
            FASTRTPS_DEFAULT_PROFILES_FILE FASTDDS_BUILTIN_TRANSPORTS; do
        [[ -n ${!variable:-} ]] && exports+=" $variable=$(printf '%q' "${!variable}")"
    done
    echo "$exports"
}

report_results() {
    [[ -f $SUMMARY ]] && echo "$PROG: summary: $SUMMARY" && "$PYTHON" - "$SUMMARY" <<'PY' \
        | sed "s/^/$PROG: /"
import json, sys
from em_exploration_ros.core.evaluation.association_stats import association_line
from em_exploration_ros.core.evaluation.summary import activity_line
try:
    data = json.loads(open(sys.argv[1], encoding="utf-8").read())
    print(activity_line(data))
    if data.get("association"):
        print(association_line(data["association"]))
except (OSError, ValueError, KeyError, TypeError) as error:
    print(f"summary unreadable: {error}")
PY
    [[ -f $MAP_PNG ]] && echo "$PROG: map:     $MAP_PNG"
    echo "$PROG: logs:    $LOG_DIR"
    [[ -n $RECORD && -d $RECORD_PATH ]] && echo "$PROG: bag:     $RECORD_PATH"
    [[ -n $RECORDING_PROBLEM ]] && echo "$PROG: recording incomplete: $RECORDING_PROBLEM"
    return 0
}

# shellcheck disable=SC2317  # called through the traps below
# A signal while the run is being stopped (a second Ctrl-C, or a TERM after the INT from a
# supervisor) kills what is left at once; by default it ended this shell in the middle of
# stop_all and left the remaining nodes running with no one to stop them.
kill_all_now() {
    trap '' INT TERM HUP
    local pid
    for pid in "${PIDS[@]}"; do kill -KILL -- "-$pid" 2>/dev/null; done
    wait_groups "$KILL_GRACE_S"
    echo "$PROG: stopped at once (a signal while stopping); the last log lines may be missing" >&2
    exit "$1"
}

# After the first signal, or once the run is being stopped, a signal kills what is left at once.
arm_kill_all_now() {
    trap 'kill_all_now 130' INT
    trap 'kill_all_now 143' TERM
    trap 'kill_all_now 129' HUP
}

# shellcheck disable=SC2317  # called through the traps below
on_signal() {
    arm_kill_all_now
    echo "$PROG: stopping ($1)" >&2
    [[ -n ${TAIL_PID:-} ]] && kill "$TAIL_PID" 2>/dev/null
    stop_all
    report_results
    exit "$2"
}
trap 'on_signal interrupted 130' INT
trap 'on_signal terminated 143' TERM
# A closed terminal or a lost SSH connection: the nodes, each in its own session, get no
# SIGHUP of their own and would run on with no one to stop them.
trap 'on_signal "hung up" 129' HUP

# shellcheck disable=SC2317  # called through the trap below
# The last guard: whatever else ends this shell (an error of the script itself, such as an
# unbound variable, or a signal it does not handle, such as SIGALRM from `timeout -s ALRM` or
# SIGUSR1) stops the nodes first; each runs in its own session and would run on for good.
on_unexpected_exit() {
    local pid
    for pid in "${PIDS[@]}"; do
        group_alive "$pid" || continue
        echo "$PROG: error: ended unexpectedly with nodes running; stopping them" >&2
        arm_kill_all_now
        stop_all
        return
    done
}
trap on_unexpected_exit EXIT

COMMON=(--ros-args --params-file "$PARAMS_FILE" "${OVERRIDES[@]}")
SIM_LIMIT=()
[[ -n $MAX_SIM_TIME ]] && SIM_LIMIT=(-p "max_sim_time_s:=$(as_double "$MAX_SIM_TIME")")
if [[ -n $REALTIME ]]; then
    CLOCK=(-p clock_mode:=realtime -p "realtime_factor:=$(as_double "$REALTIME")")
    MODE="real time x$REALTIME"
else
    CLOCK=(-p clock_mode:=lockstep)
    MODE=lockstep
fi

echo "$PROG: $NUM_ROBOTS robots, planner $RUN_PLANNER, seed $RUN_SEED, $MODE," \
     "ROS_DOMAIN_ID=$ROS_DOMAIN_ID; logs in $LOG_DIR"
em_clean_shared_memory "$PROG"
print_second_terminal
if [[ -n $RECORD ]]; then
    start record -m "$RECORD_MODULE" -o "$RECORD_PATH" --ros-args -p use_sim_time:=true
fi
if [[ -n $FOXGLOVE_PORT ]]; then
    start foxglove -m "$FOXGLOVE_MODULE" --port "$FOXGLOVE_PORT" --ros-args -p use_sim_time:=true
    echo "$PROG: Foxglove: open a Foxglove WebSocket connection to ws://127.0.0.1:$FOXGLOVE_PORT" \
         "(layout: config/foxglove_layout.json)"
fi
# start_evaluator: the evaluator's process; a restart (--respawn) uses the same command line.
start_evaluator() {
    start evaluator -m "$NODES.evaluator_node" "${COMMON[@]}" -p use_sim_time:=true \
        -p "summary_path:=$(as_string "$SUMMARY")" -p "map_png_path:=$(as_string "$MAP_PNG")" \
        "${SIM_LIMIT[@]}"
}
start_evaluator
EVALUATOR_PID=${PIDS[-1]}
WAIT_FOR=(-p wait_for_evaluator:=true)
# The robots wait for the recorder too: volatile topics keep nothing for a late subscriber.
ROBOT_WAIT_FOR=()
if [[ -n $RECORD ]]; then
    WAIT_FOR+=(-p wait_for_recorder:=true)
    ROBOT_WAIT_FOR=(-p wait_for_recorder:=true)
fi
# A team lost at once (every robot wedged) is restarted, not ended: the world waits for it.
[[ -n $RESPAWN ]] && WAIT_FOR+=(-p lost_team_wait_s:=60.0)
start world -m "$NODES.world_node" "${COMMON[@]}" "${CLOCK[@]}" "${WAIT_FOR[@]}" \
    "${SIM_LIMIT[@]}"
# start_robot ID: robot ID's process; a restart (--respawn) uses the same command line.
start_robot() {
    start "robot_$1" -m "$NODES.robot_node" --ros-args -r "__ns:=/robot_$1" \
        -p "robot_id:=$1" -p use_sim_time:=true -p "state_dir:=$(as_string "$STATE_DIR")" \
        --params-file "$PARAMS_FILE" "${OVERRIDES[@]}" "${ROBOT_WAIT_FOR[@]}"
}
for (( robot = 0; robot < NUM_ROBOTS; robot++ )); do
    start_robot "$robot"
done

# The evaluator's log on the terminal (progress lines) until it exits.
tail -n +1 -F --pid="$EVALUATOR_PID" "$LOG_DIR/evaluator.log" 2>/dev/null &
TAIL_PID=$!

# A robot that dies leaves its teammates to finish (the world stops waiting for it after
# its liveliness lease or robot_timeout_s); with --respawn it is restarted (respawn_robot).
# The Foxglove bridge is only a viewer, and the recorder only records: the team goes on
# without either (a recorder that stopped early is reported: exit code 6 and the summary's
# "recording"). The world dying ends the run.
FAILED="" RECORDING_PROBLEM="" EVALUATOR_LOST=""
# The world's log line when it steps over for good, and when this script saw it [s].
STEPPED_OVER_LINE="stepping over at step" STEPPED_OVER_AT=""
declare -A REPORTED=() RESPAWNS=() STARTED_AT=() LOST_SEEN=() SEEN_BEFORE=() REJOINED_BEFORE=()

# respawn_robot INDEX WHY: SIGKILL robot INDEX's process group (if alive) and start the same
# command line again; it rejoins the team (the world takes it back, its teammates re-send
# its stream).
respawn_robot() {
    local index=$1 why=$2 name=${NAMES[$1]} pid=${PIDS[$1]}
    local robot=${name#robot_}
    if (( ${RESPAWNS[$robot]:-0} >= MAX_RESPAWNS )); then
        echo "$PROG: warning: $name $why; restarted $MAX_RESPAWNS times already, left down" >&2
        REPORTED[$pid]=1
        return
    fi
    RESPAWNS[$robot]=$(( ${RESPAWNS[$robot]:-0} + 1 ))
    echo "$PROG: warning: $name $why; restarting it (respawn ${RESPAWNS[$robot]})" >&2
    group_alive "$pid" && kill -KILL -- "-$pid" 2>/dev/null
    wait "$pid" 2>/dev/null
    REPORTED[$pid]=1
    start_robot "$robot"
    # The new process takes the old one's place in the lists.
    PIDS[$index]=${PIDS[-1]}
    unset 'PIDS[-1]' 'NAMES[-1]'
    STARTED_AT[$robot]=$SECONDS
    SEEN_BEFORE[$robot]=$(seen_count "$robot")
    REJOINED_BEFORE[$robot]=$(rejoined_count "$robot")
}

# lost_count ROBOT: how many times the world has reported robot ROBOT lost so far.
lost_count() { grep -c "robot $1 lost:" "$LOG_DIR/world.log" 2>/dev/null; }
# seen_count ROBOT: how many times the world has seen robot ROBOT's liveliness asserted.
seen_count() { grep -c "robot $1: liveliness asserted" "$LOG_DIR/world.log" 2>/dev/null; }
# rejoined_count ROBOT: how many times the world has taken robot ROBOT back after it was lost.
rejoined_count() { grep -c "robot $1 rejoined at step" "$LOG_DIR/world.log" 2>/dev/null; }
# lost_before_rejoining ROBOT: whether the world's newest "lost" line about ROBOT comes before
# it took the restarted process back, or it has not yet (in the log's order: a process that
# rejoins within a second has both lines between two looks of this script).
lost_before_rejoining() {
    awk -v lost="robot $1 lost:" -v back="robot $1 rejoined at step" \
        -v before="${REJOINED_BEFORE[$1]}" '
        index($0, back) && ++rejoins == before + 1 { first_back = NR }
        index($0, lost) { last_lost = NR }
        END { exit !(first_back == 0 || last_lost < first_back) }' "$LOG_DIR/world.log"
}

# evaluator_ended_the_run: whether the evaluator, which has exited, ended the run (its code
# in EVALUATOR_CODE: 0, 3, 4 or 5); if not (killed, crashed) and --respawn is given, it is
# restarted with the same command line (at most MAX_RESPAWNS times): it reads back what the
# run needs (the world's ground truth from step 0, the robots' estimates and answers from
# their transient-local writers, their streams by asking for them) and ends the run as the
# first process would have.
evaluator_ended_the_run() {
    local index
    wait "$EVALUATOR_PID"
    EVALUATOR_CODE=$?
    [[ $EVALUATOR_CODE == [0345] || -z $RESPAWN ]] && return 0
    (( ${RESPAWNS[evaluator]:-0} < MAX_RESPAWNS )) || return 0
    RESPAWNS[evaluator]=$(( ${RESPAWNS[evaluator]:-0} + 1 ))
    echo "$PROG: warning: the evaluator $(exit_status_text "$EVALUATOR_CODE"); restarting it" \
        "(respawn ${RESPAWNS[evaluator]})" >&2
    wait "$TAIL_PID" 2>/dev/null
    start_evaluator
    for index in "${!PIDS[@]}"; do  # the new process takes the old one's place in the lists
        [[ ${PIDS[$index]} == "$EVALUATOR_PID" ]] || continue
        PIDS[$index]=${PIDS[-1]}
        unset 'PIDS[-1]' 'NAMES[-1]'
        break
    done
    EVALUATOR_PID=${PIDS[$index]} EVALUATOR_CODE=""
    tail -n 0 -F --pid="$EVALUATOR_PID" "$LOG_DIR/evaluator.log" 2>/dev/null &
    TAIL_PID=$!
    return 1
}

EVALUATOR_CODE=""
while kill -0 "$EVALUATOR_PID" 2>/dev/null || ! evaluator_ended_the_run; do
    for index in "${!PIDS[@]}"; do
        pid=${PIDS[$index]}
        [[ $pid == "$EVALUATOR_PID" || -n ${REPORTED[$pid]:-} ]] && continue
        name=${NAMES[$index]}
        if ! kill -0 "$pid" 2>/dev/null; then
            wait "$pid"
            status=$?
            REPORTED[$pid]=1
            if [[ $name == robot_* ]]; then
                if [[ -n $RESPAWN ]]; then
                    respawn_robot "$index" "exited with code $status"
                    continue
                fi
                echo "$PROG: warning: $name exited with code $status; the team goes on" \
                    "without it (see $LOG_DIR/$name.log)" >&2
                continue
            fi
            if [[ $name == record ]]; then
                RECORDING_PROBLEM="em-record exited with code $status"
                last_line=$(grep "^em-record:" "$LOG_DIR/record.log" 2>/dev/null | tail -n 1)
                [[ -n $last_line ]] && RECORDING_PROBLEM+=": ${last_line#em-record: }"
                echo "$PROG: warning: the recording stopped early; the team goes on" \
                    "($RECORDING_PROBLEM; see $LOG_DIR/record.log)" >&2
                continue
            fi
            if [[ $name == foxglove ]]; then
                echo "$PROG: warning: em-foxglove exited with code $status; the run goes on" \
                    "without the live view (see $LOG_DIR/$name.log)" >&2
                continue
            fi
            FAILED="$name exited early with code $status (see $LOG_DIR/$name.log)"
            break 2
        fi
        if [[ -n $RESPAWN && $name == robot_* ]]; then
            robot=${name#robot_}
            lost=$(lost_count "$robot")
            # (A first start has no earlier process: a fast team can lose a robot to a wedge
            # within RESPAWN_GRACE_S of the run's start, and it must be restarted. A "lost"
            # line after the world took the new process back is about the new one.)
            if [[ -n ${STARTED_AT[$robot]:-} ]] \
                    && (( SECONDS - STARTED_AT[$robot] < RESPAWN_GRACE_S )) \
                    && lost_before_rejoining "$robot"; then
                LOST_SEEN[$robot]=$lost
            elif (( lost > ${LOST_SEEN[$robot]:-0} )); then
                LOST_SEEN[$robot]=$lost
                respawn_robot "$index" "is alive but lost to the world (wedged or silent)"
                continue
            fi
            if [[ -n ${SEEN_BEFORE[$robot]:-} ]] \
                    && (( SECONDS - STARTED_AT[$robot] >= RESPAWN_CONFIRM_S )); then
                if (( $(seen_count "$robot") > SEEN_BEFORE[$robot] )); then
                    unset 'SEEN_BEFORE[$robot]'  # its new process is up
                else
                    why="was restarted $RESPAWN_CONFIRM_S s ago and the world has not seen"
                    respawn_robot "$index" "$why it alive (wedged in its start-up)"
                fi
            fi
        fi
    done
    # Once the world has stepped over, the evaluator ends the run; if it does not (wedged, or
    # stopped), nothing else would.
    if [[ -z $STEPPED_OVER_AT ]]; then
        grep -q -F "$STEPPED_OVER_LINE" "$LOG_DIR/world.log" 2>/dev/null && STEPPED_OVER_AT=$SECONDS
    elif (( SECONDS - STEPPED_OVER_AT >= EVALUATOR_END_GRACE_S )); then
        state=$(ps -o stat= -p "$EVALUATOR_PID" 2>/dev/null)
        [[ $state == T* ]] && state="it is stopped (SIGSTOP or Ctrl-Z)" || state="wedged?"
        FAILED="the evaluator has not ended the run $EVALUATOR_END_GRACE_S s after the world"
        FAILED+=" stepped over ($state; see $LOG_DIR/evaluator.log)"
        break
    fi
    sleep 0.5 &
    wait $!
done

if [[ -z $FAILED ]]; then
    if [[ -n $EVALUATOR_CODE ]]; then
        CODE=$EVALUATOR_CODE
    else
        wait "$EVALUATOR_PID"
        CODE=$?
    fi
    wait "$TAIL_PID" 2>/dev/null
    # 0 done, 3 the world or the robots stopped publishing, 4 stalled, 5 every live robot
    # finished below the goal while robots were lost: the run's outcomes.
    if [[ $CODE != [0345] ]]; then
        FAILED="the evaluator $(exit_status_text "$CODE") (see $LOG_DIR/evaluator.log)"
        # While the run goes on, em-evaluator keeps the summary so far (stop reason
        # "evaluator lost: ..."); it is what is left of a run whose evaluator died (exit 7).
        if grep -q '"stop_reason": "evaluator lost: ' "$SUMMARY" 2>/dev/null; then
            FAILED+="; the team is stopped and the summary so far kept"
            EVALUATOR_LOST=1
        fi
    fi
fi
arm_kill_all_now
if [[ -n $FAILED ]]; then
    echo "$PROG: error: $FAILED" >&2
    CODE=1
    [[ -n $EVALUATOR_LOST ]] && CODE=7
fi
stop_all
if [[ -n $RECORD && -f $SUMMARY ]]; then
    "$PYTHON" -m em_exploration_ros.tools.summary_recording "$SUMMARY" "$RECORD_PATH" \
        "$RECORDING_PROBLEM" || echo "$PROG: warning: could not note the recording in $SUMMARY" >&2
fi
if [[ -n $RECORDING_PROBLEM && $CODE == 0 ]]; then
    CODE=6
fi
report_results
exit "$CODE"
