#!/usr/bin/env bash
# Set everything up, then run the main job: the MuJoCo sim node and the GNN
# policy node (shipped model) as two ROS 2 processes on a 6-joint swimmer, in
# lockstep for 30 s of sim time, and print the swim speed.
# ROS 2 discovery needs multicast, which a sandbox or CI runner often lacks:
# the nodes run in a private network namespace whose loopback carries it
# (scripts/in_netns.sh), which also keeps the demo's DDS traffic off any network.
# Options go to the bring-up, e.g. --joints 10 --seconds 60 --checkpoint PATH;
# --bodies y:2x2 swims a branched swimmer (a body spec, docs/bodies.md) and
# --model-file PATH runs your own robot's MJCF (docs/your_robot.md) instead of a chain;
# --bodies centipede:5 walks a centipede of 5 leg pairs with the shipped centipede policy
# (docs/centipedes.md).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
module_help "$0" morph_policy_node.bringup "[--joints N | --bodies SPEC | --model-file PATH] [--seconds S] [--checkpoint PATH]" "$@"
cd "$root"
bash scripts/setup.sh
export MORPH_PROG="bash scripts/demo.sh"  # the bring-up's errors name this script
exec bash scripts/in_netns.sh .venv/bin/python -m morph_policy_node.bringup "$@"
