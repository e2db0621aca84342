#!/usr/bin/env bash
# Set everything up, then run the whole test suite (lint, unit, ROS integration).
# Arguments go to pytest, e.g. bash scripts/test.sh tests/test_live.py -x ("-- --help" for pytest's help).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
script_help "$0" "[PYTEST ARGS]" "${1:-}"
[ "${1:-}" = "--" ] && shift
cd "$root"
bash scripts/setup.sh
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# Integration tests start real nodes on real DDS: keep them in a private netns.
# --durations: the slowest tests in every CI log, where the suite's time budget (CONTRIBUTING.md) is kept.
bash scripts/in_netns.sh .venv/bin/python -m pytest --durations=25 "$@"
