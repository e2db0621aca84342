#!/usr/bin/env bash
# Fuzz both nodes with the full count of malformed messages (CI runs 600 each), and the policy node's
# effort_units:=urdf controller with as many descriptions (CI: 2,000), and print the figures
# that docs/robustness.md quotes. Usage: bash scripts/fuzz_nodes.sh [COUNT]   (default 10000)
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/help.sh"
script_help "$0" "[COUNT]" "$@"
if [ $# -gt 1 ] || ! [[ "${1:-10000}" =~ ^[1-9][0-9]*$ ]]; then
    echo "fuzz_nodes.sh: COUNT must be one positive integer, got: $* (--help says more)" >&2
    exit 2
fi
cd "$(dirname "${BASH_SOURCE[0]}")/.."
echo "load before: $(cat /proc/loadavg)"
FUZZ_COUNT="${1:-10000}" bash scripts/in_netns.sh .venv/bin/python -m pytest -q -s -p no:cacheprovider \
    tests/test_fuzz_nodes.py \
    ros2_ws/src/morph_core/test/test_controller.py::test_urdf_units_under_fuzzed_descriptions_and_states
echo "load after: $(cat /proc/loadavg)"
