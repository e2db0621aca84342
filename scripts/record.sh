#!/usr/bin/env bash
# Set everything up, then record episodes of the sampling policy on the simulated swimmer into a
# rosbag2 bag: sim (lockstep, as fast as possible) + policy (deterministic:=false, publishes
# policy_info) + morph-record, as three ROS 2 processes in a private network namespace
# (scripts/in_netns.sh: DDS discovery needs multicast). Options go to the bring-up
# (trainer.bags.record_bringup; --help lists them with their defaults); relative paths are taken from the
# folder it runs in, e.g.
#   bash scripts/record.sh --out bags/run1 --episodes 10 --joints 6 --storage mcap
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
module_help "$0" trainer.bags.record_bringup "--out DIR [options]" "$@"
bash "$root/scripts/setup.sh"
export MORPH_PROG="bash scripts/record.sh"  # the bring-up's errors name this script
exec bash "$root/scripts/in_netns.sh" "$root/.venv/bin/python" -m trainer.bags.record_bringup "$@"
