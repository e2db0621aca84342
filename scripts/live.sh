#!/usr/bin/env bash
# Set everything up, then train live: K lockstep sim+policy pairs (chains of 2..10 joints) in namespaces
# /swimmer0.. plus morph-train --live, all ROS 2 processes in a private network namespace
# (scripts/in_netns.sh: DDS discovery needs multicast). Options go to the bring-up, e.g.
#   bash scripts/live.sh --pairs 4 --out runs/live --updates 50
#   bash scripts/live.sh --pairs 4 --out runs/live --resume -- --num-steps 512
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
bash scripts/setup.sh
exec bash scripts/in_netns.sh .venv/bin/python -m trainer.live_bringup "$@"
