#!/usr/bin/env bash
# Set everything up, then train live: K lockstep sim+policy pairs (chains of 2..10 joints) in namespaces
# /swimmer0.. plus morph-train --live, all ROS 2 processes in a private network namespace
# (scripts/in_netns.sh: DDS discovery needs multicast). Options go to the bring-up (trainer.live.bringup;
# --help lists them with their defaults), options after -- to morph-train; relative paths are taken from
# the folder it runs in, e.g.
#   bash scripts/live.sh --pairs 4 --out runs/live --max-updates 50
#   bash scripts/live.sh --pairs 4 --out runs/live --resume -- --num-steps 512
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
module_help "$0" trainer.live.bringup "--out DIR [options] [-- MORPH-TRAIN OPTIONS]" "$@"
bash "$root/scripts/setup.sh"
export MORPH_PROG="bash scripts/live.sh"  # the bring-up's errors name this script
exec bash "$root/scripts/in_netns.sh" "$root/.venv/bin/python" -m trainer.live.bringup "$@"
