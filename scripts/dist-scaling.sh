#!/usr/bin/env bash
# Data-parallel training's speed (docs/DISTRIBUTED.md): the same recipe as
# one plain process, as torchrun world size 1 (the process group's own
# overhead: Gloo on the CPU, NCCL on a GPU) and, on the CPU, as world
# size 2 (Gloo, half the cores each, beside one process on half the
# cores), ROUNDS times in turn (a shared machine's load moves). Prints
# steps/s, samples/s (materials of the global batch a second) and the
# seconds a step spends in collectives, from the runs' log.jsonl (median
# over the steps after the first 3; the last checkpoint's checks are no
# step's).
#   bash scripts/dist-scaling.sh            # CPU: compact, crop 64, --batch 2, 20 steps, 2 rounds
#   DEVICE=cuda CROP=128 BATCH=8 STEPS=100 ROUNDS=1 bash scripts/dist-scaling.sh   # one GPU: NCCL at world 1
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
BIN="${FLASHMAT_BIN:-$FLASHMAT_RELEASE_BIN}"
DEVICE="${DEVICE:-cpu}" PRESET="${PRESET:-compact}" CROP="${CROP:-64}" OUTPUTS="${OUTPUTS:-8}" BATCH="${BATCH:-2}"
STEPS="${STEPS:-20}" ROUNDS="${ROUNDS:-2}" CORES="${CORES:-$(nproc)}"
TORCHRUN="$FLASHMAT_VENV/bin/torchrun"
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT
common=(train --device "$DEVICE" --preset "$PRESET" --crop "$CROP" --outputs "$OUTPUTS" --batch "$BATCH" --steps "$STEPS" --checkpoint-every 1000000 --preview-every 0)
half=$(( CORES / 2 > 0 ? CORES / 2 : 1 ))
echo "$(uname -n), $CORES cores, load $(cut -d' ' -f1-3 /proc/loadavg), $DEVICE; $BIN" >&2
for round in $(seq "$ROUNDS"); do
  OMP_NUM_THREADS="$CORES" "$BIN" "${common[@]}" --threads "$CORES" --out "$out/plain-$round" 2>/dev/null
  OMP_NUM_THREADS="$CORES" "$TORCHRUN" --standalone --nproc-per-node 1 --no-python "$BIN" "${common[@]}" --threads "$CORES" --out "$out/world1-$round" 2>/dev/null
  if [ "$DEVICE" = cpu ]; then
    OMP_NUM_THREADS="$half" "$BIN" "${common[@]}" --threads "$half" --out "$out/half-$round" 2>/dev/null
    OMP_NUM_THREADS="$half" "$TORCHRUN" --standalone --nproc-per-node 2 --no-python "$BIN" "${common[@]}" --threads "$half" --out "$out/world2-$round" 2>/dev/null
  fi
done
"$FLASHMAT_VENV/bin/python" - "$out" "$BATCH" <<'PY'
import json, os, statistics, sys
out, batch = sys.argv[1], int(sys.argv[2])
labels = {"plain": ("one process, all cores", 1), "world1": ("torchrun, world 1, all cores", 1),
          "half": ("one process, half the cores", 1), "world2": ("torchrun, world 2, half the cores each", 2)}
print("| run | global batch | steps/s | samples/s | collectives s/step |")
print("|---|---|---|---|---|")
for name, (label, world) in labels.items():
    secs, sync = [], []
    for d in sorted(os.listdir(out)):
        if d.startswith(name + "-"):
            rows = [json.loads(l) for l in open(os.path.join(out, d, "log.jsonl"))][3:]
            secs += [r["seconds"] for r in rows]
            sync += [r.get("sync_seconds", 0.0) for r in rows]
    if secs:
        s = statistics.median(secs)
        print(f"| {label} | {world * batch} | {1 / s:.3f} | {world * batch / s:.2f} | {statistics.median(sync):.4f} |")
PY
