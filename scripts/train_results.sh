#!/usr/bin/env bash
# Reproduce docs/results.md: both clip modes x SEEDS seeds at the paper configuration
# (1M steps each), two runs at a time (one per core), then evaluate every 24th
# checkpoint (and the last) deterministically and plot. About 45 min on 2 cores
# for 5 seeds (~4 min per run, two at a time, then ~10 min of evaluation).
#   bash scripts/train_results.sh [SEEDS=5] [OUT=runs]
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
seeds=${1:-5}
out=${2:-runs}
bash scripts/setup.sh
mkdir -p "$out"
for s in $(seq 1 "$seeds"); do for m in compensated fixed; do echo "$m $s"; done; done |
    xargs -P 2 -L 1 bash -c '
        run="$0/$1-s$2"
        if [ -f "$run/state.safetensors" ]; then resume=--resume; else resume=; fi
        .venv/bin/morph-train --rule "$1" --seed "$2" --out "$run" --progress-bar false $resume \
            > "$run.log" 2>&1 && echo "done $run"' "$out"
ls -d "$out"/*-s*/ | xargs -P 2 -I{} .venv/bin/morph-eval --run {} --stride 24 --episodes 10
.venv/bin/morph-eval --run "$out"/*-s*/ --eval false --plots docs/figures/results
