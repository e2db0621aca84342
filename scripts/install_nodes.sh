#!/usr/bin/env bash
# Install what a robot runs into the Python environment of PYTHON (a venv, or the one a ROS install uses):
# the policy node and the sim node with morph_ros_util and the core's runtime part, not editable, every
# version pinned by constraints.txt. No torch, PyTorch Geometric, TensorBoard or Matplotlib: that is the
# core's learning part (morph_core[learn]), the trainer's, which scripts/setup.sh installs for developers.
# ROS itself is the robot's own (tests/test_robot_install.py uses the PyPI wheels of requirements-dev.txt).
#
#   bash scripts/install_nodes.sh PYTHON [--policy-only] [--from CHECKOUT] [--wheels DIR] [-- PIP_OPTIONS...]
#
# --policy-only  the policy node without the sim node, and so without MuJoCo and Gymnasium
# --from         another checkout's packages, with its constraints (bench/bench_install.py)
# --wheels DIR   instead of installing, put the wheels of the packages' dependencies into DIR, for an install
#                where no registry is reachable (scripts/setup.sh, for tests/test_robot_install.py)
# PIP_OPTIONS    passed to pip install (e.g. --no-index --find-links DIR)
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
script_help "$0" "PYTHON [--policy-only] [--from CHECKOUT] [--wheels DIR] [-- PIP_OPTIONS...]" "$@"
python=${1:?usage: install_nodes.sh PYTHON [--policy-only] [--from CHECKOUT] [--wheels DIR] [-- PIP_OPTIONS...]}
shift
packages=(morph_core morph_ros_util morph_policy_node swimmer_sim_node)
wheels=
while [ $# -gt 0 ]; do
    case $1 in
        --policy-only) packages=(morph_core morph_ros_util morph_policy_node) ;;
        --from) root=$(cd "${2:?--from needs a checkout}" && pwd); shift ;;
        --wheels) wheels=${2:?--wheels needs a directory}; shift ;;
        --) shift; break ;;
        *) echo "install_nodes: unknown option $1" >&2; exit 2 ;;
    esac
    shift
done
# pip builds a local directory in place (build/, *.egg-info): build copies, so the checkout stays as it is.
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
dirs=()
for p in "${packages[@]}"; do
    cp -r "$root/ros2_ws/src/$p" "$work/$p"
    rm -rf "$work/$p"/*.egg-info "$work/$p/build"
    dirs+=("$work/$p")
done
if [ -n "$wheels" ]; then
    "$python" -m pip wheel --quiet -c "$root/constraints.txt" -w "$work/wheels" "${dirs[@]}" "$@"
    mkdir -p "$wheels"
    for w in "$work"/wheels/*.whl; do
        own=
        for p in "${packages[@]}"; do [[ $(basename "$w") == "$p"-* ]] && own=1; done
        [ -n "$own" ] || cp "$w" "$wheels/"  # the packages themselves are built from source when installed
    done
else
    "$python" -m pip install --quiet -c "$root/constraints.txt" "${dirs[@]}" "$@"
fi
