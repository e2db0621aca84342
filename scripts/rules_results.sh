#!/usr/bin/env bash
# Compare the trust-region rules of algo.trust_region at the paper configuration: every rule of the
# table (or RULES="a b ...") x SEEDS seeds, 1M steps each, two runs at a time (one per core), then
# evaluate every 24th checkpoint (and the last) deterministically, plot and summarise. Modelled on
# scripts/train_results.sh (which does fixed and compensated only). About 4-5 min per run, two at a
# time: for the 7 rules and 5 seeds ~80 min of training, then ~35 min of evaluation, on 2 cores.
#   bash scripts/rules_results.sh [SEEDS=5] [OUT=runs_rules]
#   RULES="kl-penalty kl-penalty-per-joint" EXTRA="--kl-target 0.02" bash scripts/rules_results.sh 5 runs_kl
# EXTRA: more morph-train options; EVAL: more morph-eval options, e.g. EVAL="--from-step 500000" for the late
# checkpoints only (half the evaluation time; the tables' late means need no more).
# kl_target (0.01 by default) is the same number for the joint and the per-joint KL rules: the
# per-joint variants equal the joint ones at d = 1 and allow more KL at larger d, as eps*sqrt(d) does.
# An interrupted script can simply be started again: finished runs are skipped, killed ones resume.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
seeds=${1:-5}
out=${2:-runs_rules}
bash scripts/setup.sh
rules=${RULES:-$(.venv/bin/python -c 'from morph_core.algo.trust_region import rule_names; print(*rule_names())')}
export EXTRA=${EXTRA:-}
eval_args=${EVAL:-}
mkdir -p "$out"
for s in $(seq 1 "$seeds"); do for m in $rules; do echo "$m $s"; done; done |
    xargs -P 2 -L 1 bash -c '
        run="$0/$1-s$2"
        if [ -f "$run/state.safetensors" ]; then resume=--resume; else resume=; fi
        # shellcheck disable=SC2086  # EXTRA holds several options
        .venv/bin/morph-train --rule "$1" --seed "$2" --out "$run" --progress-bar false $resume $EXTRA \
            > "$run.log" 2>&1 && echo "done $run"' "$out"
# shellcheck disable=SC2086  # EVAL holds several options
ls -d "$out"/*-s*/ | xargs -P 2 -I{} .venv/bin/morph-eval --run {} --stride 24 --episodes 10 $eval_args
.venv/bin/morph-eval --run "$out"/*-s*/ --eval false --plots "$out/figures"
.venv/bin/python -m trainer.summary --run "$out"/*-s*/ | tee "$out/summary.md"
