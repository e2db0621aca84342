#!/usr/bin/env bash
# Reproduce docs/results.md's "Learning live over DDS": live training from an untrained policy with K=4
# lockstep sim+policy pairs (scripts/live.sh) against the simulator trainer at the same env-step count,
# SEEDS seeds of STEPS steps each (paper configuration otherwise), then the curves side by side.
#   bash scripts/live_results.sh [SEEDS=3] [STEPS=300000] [OUT=runs/live-vs-sim]   # docs/results.md: OUT=runs/live-lr0.003
#   LIVE_EXTRA="--learning-rate 0.01" bash scripts/live_results.sh 3 300000 runs/live-lr0.01   # more live-trainer options
# A run already finished is skipped; an interrupted one resumes.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$root/scripts/help.sh"
script_help "$0" "[SEEDS] [STEPS] [OUT]" "$@"
if [ $# -gt 3 ] || ! [[ "${1:-3}" =~ ^[1-9][0-9]*$ && "${2:-300000}" =~ ^[1-9][0-9]*$ ]]; then
    echo "live_results.sh: SEEDS and STEPS must be positive integers, then OUT a folder; got: $* (--help says more)" >&2
    exit 2
fi
cd "$root"
seeds=${1:-3}
steps=${2:-300000}
out=${3:-runs/live-vs-sim}
bash scripts/setup.sh
mkdir -p "$out"
finished() { [ -f "$1/progress.csv" ] && .venv/bin/python -c "import csv, sys
rows = list(csv.DictReader(open('$1/progress.csv')))
sys.exit(0 if rows and int(rows[-1]['global_step']) >= $steps else 1)"; }
for s in $(seq 1 "$seeds"); do
    run="$out/live-s$s"
    if finished "$run"; then continue; fi
    resume=(); [ -f "$run/state.safetensors" ] && resume=(--resume)
    # shellcheck disable=SC2086  # LIVE_EXTRA holds several options
    bash scripts/live.sh --pairs 4 --out "$run" "${resume[@]}" -- --seed "$s" --total-timesteps "$steps" \
        ${LIVE_EXTRA:-} > "$run.log" 2>&1
    echo "done $run"
done
for s in $(seq 1 "$seeds"); do echo "$s"; done | xargs -P 2 -I{} bash -c '
    run="$0/simulator-s{}"
    if [ -f "$run/state.safetensors" ]; then resume=--resume; else resume=; fi
    .venv/bin/morph-train --seed {} --total-timesteps "$1" --out "$run" --progress-bar false $resume \
        > "$run.log" 2>&1 && echo "done $run"' "$out" "$steps"
.venv/bin/python -m trainer.live.compare "$out"/live-s*/ --simulator "$out"/simulator-s*/ --plot docs/figures/live
