#!/usr/bin/env bash
# Set everything up, then run the main job on its embedded defaults.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
bash scripts/setup.sh
exec .venv/bin/morph-gait "$@"
