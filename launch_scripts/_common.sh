# shellcheck shell=bash disable=SC2034  # the variables below are used by the sourcing scripts
# Shared helpers of the launch scripts; source it, do not run it.
#
#   source "$(dirname "${BASH_SOURCE[0]}")/_common.sh"
#
# Defines the repository paths (EM_REPO_ROOT, EM_VENV, EM_BUILD_DIR) and:
#   em_activate          export the environment of the project's venv (ROS 2 from PyPI wheels)
#   em_pick_ros_domain   choose a ROS_DOMAIN_ID no other run on this machine holds, and hold it
#   em_hold_run_lock     take a domain for one run_team.sh run; refused while another holds it
#   em_pip_freeze [VENV] print "name==version" of every package pip installed in a venv

EM_REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
EM_VENV="$EM_REPO_ROOT/.venv"
EM_BUILD_DIR="$EM_REPO_ROOT/build"

# Directory of the per-domain lock files; tests/conftest.py uses the same one.
EM_DOMAIN_LOCK_DIR="${TMPDIR:-/tmp}/em_exploration_ros-ros-domains"

# Export the environment in which the venv's ROS 2 works, independent of the caller's shell.
# A shell that sourced a full ROS 2 install (/opt/ros/...) would otherwise mix its Python
# packages, libraries and ament prefixes into ours. The venv's ros_wheels_bootstrapper .pth hook
# re-executes every venv Python once with LD_LIBRARY_PATH pointing at the venv's libraries;
# clearing its guard variable makes it do so for the processes started from here.
em_activate() {
    export VIRTUAL_ENV="$EM_VENV"
    export PATH="$EM_VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$EM_VENV"
    export CMAKE_PREFIX_PATH="$EM_VENV"
    export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
    # The distribution of the venv's ROS 2 wheels (ros2 doctor reports a missing one).
    export ROS_DISTRO=jazzy
    # Writers' heartbeat every 100 ms instead of 3 s, participants announced every second
    # instead of every 3 s, and sample buffers freed once taken: see the file, whose memory
    # policy rmw_fastrtps takes only with RMW_FASTRTPS_USE_QOS_FROM_XML=1. A profile the
    # caller chose is kept; one that announces less often than em-world's startup_settle_s
    # (2 s) needs that setting raised past its period (a --params file).
    export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$EM_REPO_ROOT/config/fastdds_profiles.xml}"
    export RMW_FASTRTPS_USE_QOS_FROM_XML="${RMW_FASTRTPS_USE_QOS_FROM_XML:-1}"
    # glibc gives memory freed after a flood back to the system (docs/results.md "Memory
    # under a flood"): two malloc arenas instead of 8 per core (the middleware's threads each
    # kept freed buffers in their own), buffers of 128 kB and more always mapped apart (the
    # default threshold rises to the largest buffer freed, up to 32 MB, after which such
    # buffers stay in the heap) and the heap's free top returned above 128 kB.
    export MALLOC_ARENA_MAX="${MALLOC_ARENA_MAX:-2}" \
        MALLOC_MMAP_THRESHOLD_="${MALLOC_MMAP_THRESHOLD_:-131072}" \
        MALLOC_TRIM_THRESHOLD_="${MALLOC_TRIM_THRESHOLD_:-131072}"
    unset PYTHONPATH PYTHONHOME LD_LIBRARY_PATH COLCON_PREFIX_PATH _ROS_WHEELS_BOOTSTRAP_COMPLETE
    # Planner plugins installed apart (pip install --target DIR; docs/plugins.md): the
    # folders of EM_PLUGIN_PATH (':'-separated) are the processes' PYTHONPATH.
    if [[ -n ${EM_PLUGIN_PATH:-} ]]; then
        export PYTHONPATH="$EM_PLUGIN_PATH"
    fi
}

# Choose a ROS 2 domain for this run and keep it for the life of this shell and its children.
#
# Domains 1..101 (0 is the ROS default and left to other software) are tried in turn, starting
# at one derived from the PID. A domain is taken by holding an exclusive flock on
# $EM_DOMAIN_LOCK_DIR/<id>.lock through a file descriptor that stays open in this shell and is
# inherited by every process started from it, so no two runs on this machine that use this
# scheme share a domain while either is alive. Discovery is also kept on this host
# (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), so runs never see other machines.
em_pick_ros_domain() {
    local first offset id fd
    mkdir -p "$EM_DOMAIN_LOCK_DIR"
    first=$(( $$ % 101 ))
    for (( offset = 0; offset < 101; offset++ )); do
        id=$(( (first + offset) % 101 + 1 ))
        exec {fd}>"$EM_DOMAIN_LOCK_DIR/$id.lock"
        if flock --nonblock "$fd"; then
            export ROS_DOMAIN_ID="$id"
            export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
            return 0
        fi
        exec {fd}>&-
    done
    echo "error: all ROS domains 1..101 are held by other runs (locks in $EM_DOMAIN_LOCK_DIR)" >&2
    return 1
}

# Hold the run lock of ROS domain $1 for the life of this shell and its children, writing
# $2 (who holds it: the run's pid and folder) into it; returns 1 with the holder's text in
# EM_RUN_LOCK_HOLDER when another run of this project (run_team.sh) holds it. It is a lock of
# its own ($EM_DOMAIN_LOCK_DIR/<id>.run.lock), not the free-domain choice's: a test run holds
# its domain's choice lock and starts runs in it, one at a time. Every process of the run
# inherits the descriptor, so a node left running keeps the domain taken.
em_hold_run_lock() {
    local lock="$EM_DOMAIN_LOCK_DIR/$1.run.lock" fd
    mkdir -p "$EM_DOMAIN_LOCK_DIR"
    exec {fd}<>"$lock"
    if ! flock --nonblock "$fd"; then
        EM_RUN_LOCK_HOLDER=$(head -c 1000 "$lock" | tr -d '\0')
        exec {fd}>&-
        return 1
    fi
    truncate -s 0 "$lock" && printf '%s\n' "$2" >"$lock"
    return 0
}

# Remove the Fast DDS shared-memory files in /dev/shm that processes left when they died
# without closing them (killed, crashed): the dead ports of ROS_DOMAIN_ID (whose run lock
# the caller holds) and every dead segment, with em_exploration_ros.tools.shm_leftovers (its
# docstring says why not with `fastdds shm clean`). A running process's files stay. Prints
# "$1: removed the shared-memory files of ..." when there were any, a warning on stderr when
# the removal failed; never fails the caller.
em_clean_shared_memory() {
    local report
    # Not a process of the run: no ROS_DOMAIN_ID of its own (tests find a run's processes by
    # it), the domain as an argument.
    if ! report=$(env -u ROS_DOMAIN_ID "$EM_VENV/bin/python" \
            -m em_exploration_ros.tools.shm_leftovers --domain "${ROS_DOMAIN_ID:-0}" \
            --prog "$1" 2>&1); then
        echo "$1: warning: could not remove Fast DDS's leftover shared-memory files" \
            "($(tail -n 1 <<<"$report"))" >&2
        return 0
    fi
    [[ -z $report ]] || echo "$report"
    return 0
}

# Print "name==version" (PEP 503 normalised names, sorted) of every distribution that pip
# installed in the venv $1 (default: the project's venv). Left out: the project's own local or editable install, and the
# *.egg-info folders that the ROS wheels ship inside site-packages (those are files of other
# wheels, not installed distributions, and have no INSTALLER record).
em_pip_freeze() {
    "${1:-$EM_VENV}/bin/python" - <<'PY'
import importlib.metadata
import json
import re

pins = set()
for dist in importlib.metadata.distributions():
    if (dist.read_text("INSTALLER") or "").strip() != "pip":
        continue
    direct_url = json.loads(dist.read_text("direct_url.json") or "{}")
    if "dir_info" in direct_url:
        continue
    name = re.sub(r"[-_.]+", "-", dist.metadata["Name"]).lower()
    pins.add(f"{name}=={dist.version}")
print("\n".join(sorted(pins)))
PY
}
