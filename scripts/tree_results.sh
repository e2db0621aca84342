#!/usr/bin/env bash
# Reproduce docs/results.md "Trees": compensated and fixed clipping x SEEDS seeds at the paper configuration
# (1M steps each) on chains of 2..10 joints plus random trees of 3..10 joints, two runs at a time, then
# evaluate every 24th checkpoint (and the last) on chains of 2..10, the unseen 15, 20 and 40, and named trees.
# Runs scripts/rules_results.sh with those options (an interrupted script resumes where it stopped).
#   bash scripts/tree_results.sh [SEEDS=5] [OUT=runs_trees]
#   EXTRA="--anneal-lr true" bash scripts/tree_results.sh 5 runs_trees_anneal
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
seeds=${1:-5}
out=${2:-runs_trees}
# Named trees of 5..9 joints; none is named in training (the random family may draw one now and then).
named="y:1x2,y:2x2,star:3x1,star:3x2,star:4x2,comb:3,comb:4,comb:5"
RULES="compensated fixed" EXTRA="--bodies 2-10,random:3-10 ${EXTRA:-}" \
    EVAL="--lengths 2 3 4 5 6 7 8 9 10 15 20 40 --bodies $named ${EVAL:-}" \
    bash scripts/rules_results.sh "$seeds" "$out"
