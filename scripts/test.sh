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
# -n: one worker per core (MORPH_TEST_WORKERS to change it, 0 for one process): many tests wait on real
# time (paced nodes, DDS) while others compute, so the workers overlap them (CONTRIBUTING.md, "The suite's
# time"). Each worker runs in a DDS domain of its own (conftest.py).
workers=${MORPH_TEST_WORKERS:-$(nproc)}
bash scripts/in_netns.sh .venv/bin/python -m pytest -n "$workers" --durations=25 "$@"
