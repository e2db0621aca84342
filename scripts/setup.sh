#!/usr/bin/env bash
# Create the project venv at .venv and install the five workspace packages
# editable, with the core's learning part (morph_core[learn]: torch, PyG,
# TensorBoard; a robot installs the nodes without it), every version pinned by
# constraints.txt. Re-running is a no-op
# unless constraints.txt, requirements-dev.txt or a setup.py changed.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
script_help "$0" "(no options; PYTHON=python3.11 picks the interpreter)" "$@"
if [ $# -gt 0 ]; then
    echo "setup.sh: takes no arguments, got: $* (--help says what it does)" >&2
    exit 2
fi
cd "$root"
python=${PYTHON:-python3}
if ! "$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "setup: need Python 3.11 (the ROS 2 Jazzy wheels are built for it); got $("$python" --version)" >&2
    exit 1
fi
stamp=.venv/.installed
want=$(cat constraints.txt requirements-dev.txt ros2_ws/src/*/setup.py scripts/install_nodes.sh | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
    exit 0
fi
echo "setup: installing into .venv (once; about a minute)" >&2
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade "pip>=24"
# setuptools' notes from each editable install (a screenful in all) ask nothing of whoever sets up: the
# "Editable installation" caveat (a folder named like a package may shadow it) and that
# morph_policy_node/models, read from the source tree, is no listed package. Other warnings still show.
quiet="ignore:Editable installation,ignore:Package 'morph_policy_node.models' is absent"
PYTHONWARNINGS="$quiet" .venv/bin/python -m pip install --quiet -c constraints.txt -r requirements-dev.txt \
    -e "ros2_ws/src/morph_core[learn]" -e ros2_ws/src/morph_ros_util -e ros2_ws/src/swimmer_sim_node \
    -e ros2_ws/src/morph_policy_node -e "ros2_ws/src/trainer[onnx,ray]"
# A robot's wheels: ROS (the PyPI wheels above) and the nodes' dependencies, with the build tools, for
# tests/test_robot_install.py, which installs the nodes into a fresh venv inside the tests' network
# namespace, where no registry is reachable.
rm -rf .venv/robot-wheels
ros=$(grep -E '^ros-' requirements-dev.txt)
# shellcheck disable=SC2086  # one requirement per word
.venv/bin/python -m pip wheel --quiet -c constraints.txt -w .venv/robot-wheels $ros setuptools wheel
PYTHONWARNINGS="$quiet" bash scripts/install_nodes.sh .venv/bin/python --wheels .venv/robot-wheels
echo "$want" > "$stamp"
