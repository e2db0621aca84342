#!/usr/bin/env bash
# Run a command in a private network namespace whose loopback carries
# multicast, so DDS discovery works and never leaves this machine.
#   bash scripts/in_netns.sh COMMAND [ARGS...]   e.g. bash scripts/in_netns.sh .venv/bin/python -m pytest tests/x.py
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/help.sh"
script_help "$0" "COMMAND [ARGS...]" "${1:-}"
if [ $# -eq 0 ]; then
    echo "in_netns.sh: give the command to run (--help says more)" >&2
    exit 2
fi
exec unshare -rn bash -c '
    ip link set lo up
    ip link set lo multicast on
    ip route add 224.0.0.0/4 dev lo
    exec "$@"' in_netns "$@"
