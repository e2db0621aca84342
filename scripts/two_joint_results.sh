#!/usr/bin/env bash
# Why does the 2-joint chain stay at 20-45? (docs/results.md, "The 2-joint chain".) Hypothesis: the
# discount. Swimmer's reward is forward speed, and a gait pays off only over many steps; gamma = 0.98
# (the paper's) looks ~50 steps ahead. Train on 2 joints alone with gamma 0.98, 0.999 and 0.9999, and on
# the paper's 2..10 mix with 0.9999, SEEDS seeds each, two runs at a time, then evaluate deterministically.
# About 15 min on 2 cores for 2 seeds (2026-12-02).
#   bash scripts/two_joint_results.sh [SEEDS=2] [OUT=runs_two_joint] [STEPS=500000]
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
seeds=${1:-2}
out=${2:-runs_two_joint}
export STEPS=${3:-500000}
bash scripts/setup.sh
mkdir -p "$out"
for s in $(seq 1 "$seeds"); do
    for g in 0.98 0.999 0.9999; do echo "only2-g$g $s --gamma $g --min-joints 2 --max-joints 2"; done
    echo "mix-g0.9999 $s --gamma 0.9999"
done | xargs -P 2 -L 1 bash -c '
    run="$0/$1-s$2"
    shift 2
    if [ -f "$run/state.safetensors" ]; then resume=--resume; else resume=; fi
    .venv/bin/morph-train --rule compensated --seed "${run##*-s}" --total-timesteps "$STEPS" --out "$run" \
        --progress-bar false $resume "$@" > "$run.log" 2>&1 && echo "done $run"' "$out"
ls -d "$out"/only2-*-s*/ | xargs -P 2 -I{} .venv/bin/morph-eval --run {} --stride 12 --episodes 10 --lengths 2
ls -d "$out"/mix-*-s*/ | xargs -P 2 -I{} .venv/bin/morph-eval --run {} --stride 12 --episodes 10 --lengths 2 3 6 10
.venv/bin/python - "$out"/*-s*/ <<'PY' | tee "$out/summary.md"
import sys
from trainer.runs import load_run
from trainer.summary import late_means, training_marks
print("| run | gamma | trained | last 10 updates | late eval per length (from half the steps on) |")
print("|---|---:|---|---:|---|")
for d in sys.argv[1:]:
    run = load_run(d)
    cfg = run.config
    late = " ".join(f"{n}:{r:.1f}" for n, r in sorted(late_means(run).items()))
    lengths = f"{cfg['min_joints']}..{cfg['max_joints']}"
    print(f"| {run.dir.name} | {cfg['gamma']} | {lengths} | {training_marks(run)['last']:.0f} | {late} |")
PY
