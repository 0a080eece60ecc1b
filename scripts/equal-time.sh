#!/usr/bin/env bash
# The equal-time study of issue 15 (reports/equal-time.md): trains one
# recipe from scratch (compact preset unless --model-config, LDR photos,
# seed 1, one thread) in segments and exports a model at each mark, so the
# held-out scores can be drawn against the CPU time the run spent.
#
#   scripts/equal-time.sh NAME MARKS -- TRAIN_OPTIONS...
#   scripts/equal-time.sh paper "250 500 1000" -- --crop 64 --outputs 4 --batch 2 --lr 2e-4 --straight-through-output
#
# Runs live in $RUNS (default ~/.cache/flashmat/runs/eqt): NAME/ is the run
# folder, NAME-STEP.safetensors the exported snapshots. Re-running resumes.
set -euo pipefail
cd "$(dirname "$0")/.."
name=$1 marks=$2
shift 2
[ "${1:-}" = "--" ] && shift
runs=${RUNS:-$HOME/.cache/flashmat/runs/eqt}
# cargo's release binary, wherever CARGO_TARGET_DIR puts it (env.sh).
source scripts/env.sh
bin=${FLASHMAT:-$FLASHMAT_RELEASE_BIN}
mkdir -p "$runs"
for mark in $marks; do
    snap="$runs/$name-$mark.safetensors"
    [ -f "$snap" ] && continue
    # --steps is the run's total: each segment ends exactly at its mark
    # (a checkpoint), and an interrupted segment resumes from its last one.
    if [ -f "$runs/$name/checkpoint.safetensors" ]; then
        "$bin" train --resume "$runs/$name" --steps "$mark" --threads 1
    else
        preset=(--preset compact)
        [[ " $* " == *" --model-config "* ]] && preset=()
        "$bin" train "${preset[@]}" --ldr --out "$runs/$name" --steps "$mark" \
            --checkpoint-every 50 --preview-every 0 --seed 1 --threads 1 "$@"
    fi
    "$bin" export --run "$runs/$name" -o "$snap"
done
