#!/usr/bin/env bash
# Run a command in a private network namespace whose loopback carries
# multicast, so DDS discovery works and never leaves this machine.
set -euo pipefail
exec unshare -rn bash -c '
    ip link set lo up
    ip link set lo multicast on
    ip route add 224.0.0.0/4 dev lo
    exec "$@"' in_netns "$@"
