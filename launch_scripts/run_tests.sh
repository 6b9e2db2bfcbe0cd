#!/usr/bin/env bash
# Run the test suite: bring the environment up to date (setup_env.sh), then pytest with the
# venv's Python in an isolated ROS 2 domain. Arguments go to pytest, with paths relative to the
# repository root, e.g.
#   launch_scripts/run_tests.sh tests/test_msgs_serialization.py -k Keyframe
# Exits with pytest's exit code.
set -euo pipefail

# shellcheck source=launch_scripts/_common.sh
source "$(dirname "${BASH_SOURCE[0]}")/_common.sh"

"$EM_REPO_ROOT/launch_scripts/setup_env.sh"

em_activate
# A ROS domain held for this run only (its lock stays open in pytest, which replaces this
# shell), and discovery restricted to this host.
em_pick_ros_domain
echo "tests: ROS_DOMAIN_ID=$ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=$ROS_AUTOMATIC_DISCOVERY_RANGE"
# Shared-memory files of processes killed before (earlier runs' tests kill some on purpose).
em_clean_shared_memory tests

cd "$EM_REPO_ROOT"
exec "$EM_VENV/bin/python" -m pytest "$@"
