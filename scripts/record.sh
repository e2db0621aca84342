#!/usr/bin/env bash
# Set everything up, then record episodes of the sampling policy on the simulated swimmer into a
# rosbag2 bag: sim (lockstep, as fast as possible) + policy (deterministic:=false, publishes
# policy_info) + morph-record, as three ROS 2 processes in a private network namespace
# (scripts/in_netns.sh: DDS discovery needs multicast). Options go to the bring-up, e.g.
#   bash scripts/record.sh --out bags/run1 --episodes 10 --joints 6 --storage mcap
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
bash scripts/setup.sh
exec bash scripts/in_netns.sh .venv/bin/python -m trainer.record_bringup "$@"
