#!/usr/bin/env bash
# Set everything up, then learn from bags alone: rounds of recording episodes with the current policy
# (sim + sampling policy + morph-record, as ROS 2 processes) and one PPO update from the round's bag
# (morph-train --from-bags), in a private network namespace (scripts/in_netns.sh: DDS discovery needs
# multicast). Options go to trainer.bags.rounds, e.g.
#   bash scripts/bag_rounds.sh --rounds 20 --out runs/bag-rounds --deadline-minutes 40 -- --compile false
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
module_help "$0" trainer.bags.rounds "--rounds N --out DIR [options] [-- MORPH-TRAIN OPTIONS]" "$@"
cd "$root"
bash scripts/setup.sh
export MORPH_PROG="bash scripts/bag_rounds.sh"
exec bash scripts/in_netns.sh .venv/bin/python -m trainer.bags.rounds "$@"
