#!/usr/bin/env bash
# The GPU training campaign in time-boxed chunks (docs/GPU.md has the
# sequence). Each GPU job gets a copy of the repository, runs one command
# for at most 10 minutes and returns only the files under $OUT; its disk may
# be gone before the next job. So:
#
#   here:   bash scripts/gpu-train.sh stage
#             builds the release binary and copies it, with the model to
#             resume from (when there is one), into .gpu/ (git-ignored;
#             the job carries it)
#   GPU:    bash scripts/gpu-train.sh chunk [MINUTES]
#             first chunk on a machine: CUDA smoke test (stops the campaign
#             with one line if it fails); then trains for MINUTES (default
#             8.5), resuming from the machine's checkpoint when the disk is
#             still there, else warm-starting from .gpu/resume.safetensors,
#             else from scratch; writes model.safetensors (f16 export),
#             log.jsonl, losses.png and chunk.md (recipe, steps/s,
#             samples/s, GPU busy fraction, losses) to $OUT
#   here:   cp <files_at>/model.safetensors .gpu/resume.safetensors
#   GPU:    bash scripts/gpu-train.sh verdict
#             scores the newest model (the machine's run, else
#             .gpu/resume.safetensors) against the bundled one on the 50
#             held-out materials (128 configurations); writes
#             verdict/verdict.md, verdict/summary.md and the two methods'
#             CSVs to $OUT (and candidate.safetensors when run alone)
#   GPU:    bash scripts/gpu-train.sh final [MINUTES]
#             a last chunk at a fifth of the learning rate (the decay that
#             collects a constant-rate run's gain, reports/bundled-10400.md;
#             FLASHMAT_GPU_FINAL_LR), then the verdict: 8 files, a job's limit
#
#   GPU:    bash scripts/gpu-train.sh frozen [MINUTES]
#             the two halves fine-tuned alone, side by side on the one GPU
#             (M_est against the frozen renderer, the renderer against the
#             frozen M_est), from .gpu/resume.safetensors or the bundled
#             model; writes estimator.safetensors and renderer.safetensors
#             (each run's late exports averaged), frozen.md (with their
#             and their means' scores, on the GPU) and frozen.tgz
#
#   GPU:    bash scripts/gpu-train.sh frozen-chain [MINUTES_A] [MINUTES_B]
#             two frozen jobs in one call (one machine start): the first into
#             $OUT/a, unscored; the second from its estimator.safetensors
#             into $OUT/b, scored against the first's starting model, so
#             b/renderer.safetensors is M_est trained, then a renderer
#             trained for it (8 files, a job's limit)
#
#   GPU:    bash scripts/gpu-train.sh distill [MINUTES]
#             issue 48's lever (reports/highlights-experiments.md, section 5):
#             a per-pixel teacher trained with lobe samples draws the moved
#             highlights from the true maps; M_est (from .gpu/resume.safetensors
#             or the bundled model) learns its codes against its frozen
#             renderer. The teacher is .gpu/teacher.safetensors when carried,
#             else trained first on the device (FLASHMAT_GPU_DISTILL_TEACHER_*);
#             writes model.safetensors (the late exports averaged),
#             teacher.safetensors (when trained here), distill.md (steps/s,
#             code error, the moved-highlight and exposure tables against the
#             starting model) and distill.tgz
#
#   here:   OUT=DIR bash scripts/gpu-train.sh settle MODEL [MINUTES]
#             after the GPU jobs, on this CPU: MODEL's renderer alone at the
#             small recipe (one co-located output of four, 64x64), which
#             brought the near-black matte highlight of a GPU renderer run
#             back within 2x (reports/gpu-campaign-2026-11-26/); writes
#             DIR/settled.safetensors and DIR/uniform.md (the check to judge
#             it by); run it again to continue from its checkpoint
#
#   GPU:    bash scripts/gpu-train.sh bench
#             issue 49's side-by-side benchmark, the first thing a GPU job
#             does (docs/GPU.md): flashmat's training step (paper preset at
#             both paper recipes and at 8 x 4; the compact GPU recipe; at
#             --precision tf32 and bf16) and
#             inference (256, 1024, 2048 within 32 GiB), each against the
#             authors' PyTorch step in the same job where `stage` staged
#             their code (FLASHMAT_REF_DIR: a copy of their repository ->
#             .gpu/ref, with ../shared/bench/ref_bench.py -> .gpu/bench);
#             writes bench.md (the tables) and bench.log to $OUT
#
#   bash scripts/gpu-train.sh --cpu-dry-run
#             the same steps on the CPU with the tiny preset (smoke test,
#             chunks with a resume from the export and from the checkpoint,
#             verdict), in a temporary folder; part of the test command
#
# The recipe is set by environment variables (defaults: the GPU recipe).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"

# The bundled model's preset (compact with 8 direction frequencies,
# reports/frequencies.md).
PRESET="${FLASHMAT_GPU_PRESET:-compact-f8}"
CROP="${FLASHMAT_GPU_CROP:-128}"
BATCH="${FLASHMAT_GPU_BATCH:-8}"
OUTPUTS="${FLASHMAT_GPU_OUTPUTS:-8}"
LR="${FLASHMAT_GPU_LR:-3e-4}"
FINAL_LR="${FLASHMAT_GPU_FINAL_LR:-6e-5}"
WARMUP="${FLASHMAT_GPU_WARMUP:-200}"
BANK="${FLASHMAT_GPU_BANK:-4000}"
SEED="${FLASHMAT_GPU_SEED:-1}"
CONFIGS="${FLASHMAT_GPU_CONFIGS:-128}"
# The frozen-halves job (frozen): hemisphere outputs per material (with one
# co-located), learning rate, checkpoint (= export) interval, CPU threads
# per run (two runs share the machine's 16 cores).
HEMISPHERE="${FLASHMAT_GPU_HEMISPHERE:-2}"
FROZEN_LR="${FLASHMAT_GPU_FROZEN_LR:-5e-5}"
FROZEN_EVERY="${FLASHMAT_GPU_FROZEN_EVERY:-200}"
FROZEN_THREADS="${FLASHMAT_GPU_FROZEN_THREADS:-8}"
# Co-located outputs of the frozen job's 8 (docs/GPU.md: more may hold the
# near-black highlight that every fine-tune pushed past 2x).
FROZEN_COLOCATED="${FLASHMAT_GPU_FROZEN_COLOCATED:-1}"
# More `flashmat train` options for the frozen job's M_est run only, e.g.
# "--shift-weight 0.25 --shift-scale-free" (reports/shift-consistency.md).
read -r -a FROZEN_ESTIMATOR_EXTRA <<<"${FLASHMAT_GPU_FROZEN_ESTIMATOR_EXTRA:-}"
# Scoring the frozen job's models on the GPU before they come back (0: off),
# the configurations per held-out material and each evaluation's time limit.
FROZEN_SCORE="${FLASHMAT_GPU_FROZEN_SCORE:-1}"
FROZEN_CONFIGS="${FLASHMAT_GPU_FROZEN_CONFIGS:-16}"
FROZEN_SCORE_SECONDS="${FLASHMAT_GPU_FROZEN_SCORE_SECONDS:-150}"
# The model the frozen job's models are scored and averaged against (default:
# the one it started from; the bundled model when a second job in the same
# call starts from the first's estimator).
FROZEN_SCORE_AGAINST="${FLASHMAT_GPU_FROZEN_SCORE_AGAINST:-}"
# M_est's upsampling kept checkerboard-free (reports/checkerboard.md: level
# held-out LPIPS, no 2x2 pattern); 0 for the paper's free kernels.
CHECKERBOARD_FREE="${FLASHMAT_GPU_CHECKERBOARD_FREE:-1}"
# Co-located outputs per material (docs/TRAINING.md, reports/frequencies.md;
# 0: "reflect" only, as the first campaign trained).
COLOCATED="${FLASHMAT_GPU_COLOCATED:-0}"
# Moved-highlight outputs per material (--moved-highlight-outputs, issue 48:
# the photo's camera, the light moved so the mirror highlight lands on the
# material; reports/highlights-experiments.md; 0: as the campaigns before
# 2026-11-27 trained).
MOVED="${FLASHMAT_GPU_MOVED:-0}"
# Weight of the lobe term (--lobe-weight, issue 48: L1 at random pixels
# under lights inside their true GGX lobe; reports/highlights-experiments.md)
# in the campaign and the frozen job; 0: as the campaigns before 2026-11-27.
LOBE="${FLASHMAT_GPU_LOBE:-0}"
# Share of dark procedural materials (--dark-share, issue 53: most real
# materials are darker than the families' colours; 0: the paper's data, as
# the campaigns before 2026-11-27 trained).
DARK_SHARE="${FLASHMAT_GPU_DARK_SHARE:-0.25}"
# Share of saturated procedural materials (--saturated-share, issue 69: a
# full hue with a near-black channel; the bundled model adds blue where real
# photos have almost none; 0: as the campaigns before 2026-12-04 trained).
SATURATED_SHARE="${FLASHMAT_GPU_SATURATED_SHARE:-0.1}"
# Curriculum (docs/TRAINING.md): the committed teacher (trained on the CPU,
# models/MODEL.md; FLASHMAT_GPU_TEACHER= turns the curriculum off), or
# teacher steps on the device before a fresh start; then the teacher-code
# term's weight and the step where it has faded out.
TEACHER_FILE="${FLASHMAT_GPU_TEACHER-$ROOT/models/teacher-$PRESET.safetensors}"
TEACHER_STEPS="${FLASHMAT_GPU_TEACHER_STEPS:-0}"
TEACHER_PIXELS="${FLASHMAT_GPU_TEACHER_PIXELS:-65536}"
CODE_WEIGHT="${FLASHMAT_GPU_CODE_WEIGHT:-1}"
CODE_UNTIL="${FLASHMAT_GPU_CODE_UNTIL:-20000}"
# The distill job (issue 48): the teacher's preset (its M_est layout must be
# the starting model's: compact for the bundled compact-f8), its steps and
# lobe share when trained on the device (6,500 steps at 0.5 made the CPU
# teacher T3: lobe 1.08, rest 1.11 from the true maps), its dark floor
# (--dark-floor: 0.01 took the dark metals T3 drew 2.4x too bright to
# 0.6-1.0, reports/highlights-experiments.md section 9), M_est's learning
# rate, the code term's weight (constant) and its glossy pixels' extra
# weight (--code-gloss-weight; 4 drew the most lobe of the CPU runs at
# crop 128, reports/highlights-experiments.md section 5, E12).
DISTILL_PRESET="${FLASHMAT_GPU_DISTILL_PRESET:-compact}"
DISTILL_TEACHER_STEPS="${FLASHMAT_GPU_DISTILL_TEACHER_STEPS:-6500}"
DISTILL_TEACHER_LOBE="${FLASHMAT_GPU_DISTILL_TEACHER_LOBE:-0.5}"
DISTILL_TEACHER_DARK="${FLASHMAT_GPU_DISTILL_TEACHER_DARK:-0.01}"
DISTILL_LR="${FLASHMAT_GPU_DISTILL_LR:-3e-4}"
DISTILL_CODE_WEIGHT="${FLASHMAT_GPU_DISTILL_CODE_WEIGHT:-1}"
DISTILL_CODE_GLOSS="${FLASHMAT_GPU_DISTILL_CODE_GLOSS:-4}"
# With FLASHMAT_GPU_DISTILL_PRESET=compact-g (M_est writes GGX values behind
# the teacher's frozen encoder; the teacher and a compact-g start carried,
# docs/GPU.md), the weight of the L1 on those values (--ggx-value-weight;
# 0: none; 4 took one CPU run's ghost from 1.78 to 1.32 at equal steps,
# not repeated at twice the steps; reports/highlights-experiments.md
# section 8).
DISTILL_VALUE_WEIGHT="${FLASHMAT_GPU_DISTILL_VALUE_WEIGHT:-0}"
# M_est's gradient norm clipped to this (--grad-clip; 0: none). The compact-g
# student against T4 diverged on the CPU after single gradients 50-3,000x the
# median; 2x the median of the first steps (22.76 on the CPU) kept it
# (section 10). The distill report prints the norms to choose it by.
DISTILL_GRAD_CLIP="${FLASHMAT_GPU_DISTILL_GRAD_CLIP:-0}"
# Share of the student's input photos taken as a phone takes them
# (--phone-inputs; 0: the exact co-located render). On the CPU (section 11,
# two seeds) it cost no photo fit and raised the lobe at equal steps:
# +0.03-0.07 on the exact photos, +0.05-0.06 on phone photos.
DISTILL_PHONE="${FLASHMAT_GPU_DISTILL_PHONE:-0.5}"
# The student's crop: 256, the size the held-out photos are estimated at.
# On the CPU (section 12, three runs at equal time) it drew the lobe at
# 0.33-0.42 against 0.20-0.27 at crop 128.
DISTILL_CROP="${FLASHMAT_GPU_DISTILL_CROP:-256}"
DEVICE="${FLASHMAT_GPU_DEVICE:-cuda}"
# What the networks compute in (flashmat train --precision): tf32 until
# the side-by-side benchmark (bench) has measured bf16 on the card.
PRECISION="${FLASHMAT_GPU_PRECISION:-tf32}"
# The machine's disk, where a chunk's run folder outlives the job while the
# machine stays warm.
WORK="${FLASHMAT_GPU_WORK:-/tmp/flashmat-gpu}"
BIN="${FLASHMAT_GPU_BIN:-$ROOT/.gpu/flashmat}"
RESUME_MODEL="${FLASHMAT_GPU_RESUME:-$ROOT/.gpu/resume.safetensors}"
# The teacher a warm start needs (brought back by the chunk that trained it).
CARRIED_TEACHER="${FLASHMAT_GPU_CARRIED_TEACHER:-$ROOT/.gpu/teacher.safetensors}"
# Without a carried teacher, distill learns the committed teacher for every
# GGX material (models/MODEL.md), the CPU campaign's; FLASHMAT_GPU_COMMITTED_TEACHER=
# (empty) trains one on the device instead.
COMMITTED_TEACHER="${FLASHMAT_GPU_COMMITTED_TEACHER-$ROOT/models/teacher-any-ggx.safetensors}"
EVAL_EXTRA=()

die() { echo "gpu-train: $*" >&2; exit 1; }

# The binary built here runs against the GPU machine's own libtorch.
use_machine_libtorch() {
  export FLASHMAT_ROOT="$ROOT"
  local torch_lib="${FLASHMAT_TORCH_LIB:-}"
  if [ -z "$torch_lib" ]; then
    local py
    for py in /opt/torch/.venv/bin/python python3; do
      torch_lib="$("$py" -c 'import torch,os; print(os.path.join(os.path.dirname(torch.__file__),"lib"))' 2>/dev/null)" && break
    done
  fi
  [ -n "$torch_lib" ] && [ -d "$torch_lib" ] || die "no libtorch found (set FLASHMAT_TORCH_LIB to a torch/lib folder)"
  export LD_LIBRARY_PATH="$torch_lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  [ -x "$BIN" ] || die "no flashmat binary at $BIN (run 'bash scripts/gpu-train.sh stage' before the job and carry .gpu)"
}

# The training options; $1: a teacher file for the curriculum's code term, or empty.
recipe() {
  local teacher=() constraint=()
  [ -n "${1:-}" ] && teacher=(--teacher "$1" --code-weight "$CODE_WEIGHT" --code-until "$CODE_UNTIL")
  [ "$CHECKERBOARD_FREE" = 1 ] && constraint=(--checkerboard-free)
  [ "$COLOCATED" != 0 ] && constraint+=(--colocated-outputs "$COLOCATED")
  [ "$DARK_SHARE" != 0 ] && constraint+=(--dark-share "$DARK_SHARE")
  [ "$SATURATED_SHARE" != 0 ] && constraint+=(--saturated-share "$SATURATED_SHARE")
  [ "$MOVED" != 0 ] && constraint+=(--moved-highlight-outputs "$MOVED")
  [ "$LOBE" != 0 ] && constraint+=(--lobe-weight "$LOBE")
  echo --preset "$PRESET" --ldr --crop "$CROP" --batch "$BATCH" --outputs "$OUTPUTS" --lr "$LR" \
    --warmup-steps "$WARMUP" --straight-through-output --bank "$BANK" --seed "$SEED" \
    --steps 100000000 --checkpoint-every 500 --preview-every 1000 "${teacher[@]}" "${constraint[@]}"
}

gpu_info() {
  if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
  else
    echo "no nvidia-smi (CPU run)"
  fi
}

smoke() {
  if [ -f "$WORK/smoke-passed" ]; then
    echo "gpu-train: smoke test already passed on this machine"
    return 0
  fi
  echo "gpu-train: smoke test on $DEVICE ($(gpu_info))"
  local smoke_preset="$PRESET"
  "$BIN" bench smoke --device "$DEVICE" --preset "$smoke_preset" --crop 64 --steps 2 \
    || die "smoke test failed on $DEVICE: no training time spent (see the lines above)"
  mkdir -p "$WORK" && touch "$WORK/smoke-passed"
}

# Samples the GPU's busy fraction once a second until killed.
start_util_sampler() {
  UTIL_PID=""
  if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits -l 1 >"$1" 2>/dev/null &
    UTIL_PID=$!
  fi
}

chunk() {
  local minutes="${1:-8.5}" out="${OUT:?set OUT to the folder that comes back}"
  use_machine_libtorch
  mkdir -p "$WORK" "$out"
  smoke
  local run="$WORK/run" how teacher=""
  local args=(--minutes "$minutes" --export-dir "$out" --device "$DEVICE" --precision "$PRECISION")
  # CHUNK_LR (the final chunk): a new learning rate from this chunk's first step.
  local resume_lr=()
  [ -n "${CHUNK_LR:-}" ] && resume_lr=(--lr "$CHUNK_LR")
  local first_step=0
  start_util_sampler "$WORK/gpu-util.csv"
  local t0; t0=$(date +%s)
  if [ -f "$run/checkpoint.safetensors" ]; then
    how="resumed from the machine's checkpoint"
    first_step=$(tail -n 1 "$run/log.jsonl" 2>/dev/null | sed -n 's/.*"step":\([0-9]*\).*/\1/p')
    teacher=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1])).get("teacher", ""))' "$run/config.json")
    "$BIN" train --resume "$run" "${resume_lr[@]}" "${args[@]}"
  elif [ -f "$RESUME_MODEL" ]; then
    how="warm start from $(basename "$RESUME_MODEL") (carried in .gpu/: the last chunk's export, or the model a campaign continues; no checkpoint on this machine's disk)"
    rm -rf "$run"
    if [ "$TEACHER_STEPS" -gt 0 ]; then
      [ -f "$CARRIED_TEACHER" ] || die "the curriculum's warm start needs the teacher: copy the first chunk's teacher.safetensors to $CARRIED_TEACHER"
      teacher="$CARRIED_TEACHER"
    elif [ -n "$TEACHER_FILE" ] && [ -f "$TEACHER_FILE" ]; then
      teacher="$TEACHER_FILE"
    fi
    # shellcheck disable=SC2046
    "$BIN" train --out "$run" --warm-start "$RESUME_MODEL" $(LR="${CHUNK_LR:-$LR}" recipe "$teacher") "${args[@]}"
  else
    how="fresh start"
    rm -rf "$run" "$WORK/teacher"
    if [ "$TEACHER_STEPS" -gt 0 ]; then
      how="fresh start after $TEACHER_STEPS teacher steps"
      "$BIN" train-teacher --preset "$PRESET" --out "$WORK/teacher" --steps "$TEACHER_STEPS" \
        --pixels "$TEACHER_PIXELS" --seed "$SEED" --device "$DEVICE"
      teacher="$WORK/teacher/teacher.safetensors"
      cp "$teacher" "$out/teacher.safetensors"
    elif [ -n "$TEACHER_FILE" ] && [ -f "$TEACHER_FILE" ]; then
      how="fresh start with the teacher $(basename "$TEACHER_FILE")"
      teacher="$TEACHER_FILE"
    fi
    # shellcheck disable=SC2046
    "$BIN" train --out "$run" $(recipe "$teacher") "${args[@]}"
  fi
  local t1; t1=$(date +%s)
  [ -n "$UTIL_PID" ] && kill "$UTIL_PID" 2>/dev/null || true
  cp "$run/log.jsonl" "$out/"
  [ -f "$run/losses.png" ] && cp "$run/losses.png" "$out/"
  chunk_summary "$how" "$((t1 - t0))" "$run/log.jsonl" "$WORK/gpu-util.csv" "${first_step:-0}" >"$out/chunk.md"
  echo "- recipe: \`flashmat train $(recipe "${teacher:-}")\`" >>"$out/chunk.md"
  [ -n "${CHUNK_LR:-}" ] && echo "- learning rate of this chunk: $CHUNK_LR (the final decay)" >>"$out/chunk.md"
  [ -f "$WORK/teacher/log.jsonl" ] && echo "- teacher (curriculum stage 1): \`$(grep held_out "$WORK/teacher/log.jsonl" | tail -n 1)\`" >>"$out/chunk.md"
  [ -f "$run/colour.jsonl" ] && echo "- uniform-colour check at the last checkpoint (targets: chromaticity error below 0.03, near-black highlight within 2x): \`$(tail -n 1 "$run/colour.jsonl")\`" >>"$out/chunk.md"
  cat "$out/chunk.md"
}

# chunk.md: steps of this chunk, throughput, GPU busy fraction, losses.
chunk_summary() {
  python3 - "$@" "$BATCH" "$OUTPUTS" "$CROP" "$(gpu_info)" <<'EOF'
import json, sys
how, wall, log, util, first, batch, outputs, crop, gpu = sys.argv[1:]
steps = [json.loads(l) for l in open(log) if l.strip()]
mine = [s for s in steps if s["step"] > int(first or 0)]
train_s = sum(s["seconds"] for s in mine)
n = len(mine)
busy = []
try:
    for line in open(util):
        parts = [p.strip() for p in line.split(",")]
        if parts and parts[0].isdigit():
            busy.append(float(parts[0]))
except FileNotFoundError:
    pass
last = mine[-100:] or steps[-100:]
mean = lambda k: sum(s[k] for s in last) / max(1, len(last))
print(f"# Chunk ({how})\n")
print(f"- GPU: {gpu}")
print(f"- steps {mine[0]['step'] if mine else '-'} to {mine[-1]['step'] if mine else '-'} ({n} steps), {wall} s of wall time, {train_s:.0f} s inside steps")
if n and train_s > 0:
    print(f"- {n / train_s:.2f} steps/s, {n * int(batch) / train_s:.1f} materials/s, {n * int(batch) * (1 + int(outputs)) / train_s:.0f} renders/s at {crop}x{crop}")
print(f"- GPU busy: {sum(busy) / len(busy):.0f}% (mean of {len(busy)} one-second samples)" if busy else "- GPU busy: not sampled (no nvidia-smi)")
print(f"- last 100 steps: L1 {mean('l1'):.4f}, LPIPS {mean('lpips'):.3f}, renderer L1 {mean('l1_render'):.4f}, skipped {sum(1 for s in last if s['skipped'])}")
EOF
}

# Mean LPIPS per case of each candidate's CSV (`flashmat eval`) against the
# first's, paired over the materials both scored: mean (difference, materials
# better), and whether it is better in all three cases. $1: base CSV; $2...:
# candidates.
paired_table() {
  python3 - "$@" <<'EOF'
import csv, os, sys
def load(path):
    rows = {}
    for r in csv.DictReader(open(path)):
        rows.setdefault(r["case"], {})[r["material"]] = float(r["lpips"])
    return rows
name = lambda path: os.path.splitext(os.path.basename(path))[0]
base = load(sys.argv[1])
print(f"| model | Reflect | Identity | Hemisphere | better than {name(sys.argv[1])} in all three |")
print("|---|---|---|---|---|")
for path in sys.argv[2:]:
    new, cells, better = load(path), [], True
    for case in ["reflect", "identity", "hemisphere"]:
        mats = sorted(set(new.get(case, {})) & set(base.get(case, {})))
        if not mats:
            cells.append("-")
            better = False
            continue
        a = sum(new[case][m] for m in mats) / len(mats)
        b = sum(base[case][m] for m in mats) / len(mats)
        wins = sum(new[case][m] < base[case][m] for m in mats)
        cells.append(f"{a:.3f} ({a - b:+.3f}, {wins} of {len(mats)})")
        better &= a < b
    print(f"| {name(path)} | {' | '.join(cells)} | {'yes' if better else 'no'} |")
EOF
}

# M_est alone against the frozen renderer (reports/colour.md's E3 recipe) and
# the renderer alone against the frozen M_est (reports/frozen.md), side by
# side: one run keeps the GPU about 45% busy, the two about 70%
# (reports/gpu-campaign-2026-11-25/). Each run's later half of exports is
# averaged (the CPU runs' lesson: late-checkpoint means beat the last one).
# Averages the later half of a run's exports (sorted by step) into $2;
# LATE_EXPORTS keeps their file names for the report.
average_late_exports() {
  local exports
  mapfile -t exports < <(ls "$1"/step-*.safetensors | sort -V)
  LATE_EXPORTS=("${exports[@]:$(( ${#exports[@]} / 2 ))}")
  "$BIN" average "${LATE_EXPORTS[@]}" -o "$2"
  LATE_EXPORTS=("${LATE_EXPORTS[@]##*/}")
}

# The model a job starts from: the carried one (.gpu/resume.safetensors or
# $FLASHMAT_GPU_RESUME), else the bundled model.
start_model() {
  if [ -f "$RESUME_MODEL" ]; then echo "$RESUME_MODEL"; else echo "$ROOT/models/flashmat.safetensors"; fi
}

# A device job's start (JOB MINUTES OUT DIR): MINUTES checked before any GPU
# time is spent, the machine's libtorch, the smoke test, DIR made afresh.
begin_device_job() {
  [[ "$2" =~ ^[0-9]+([.][0-9]+)?$ ]] || die "$1: MINUTES must be a number, not '$2'"
  use_machine_libtorch
  mkdir -p "$WORK" "$3"
  smoke
  rm -rf "$4" && mkdir -p "$4"
}

frozen() {
  local minutes="${1:-5.5}" out="${OUT:?set OUT to the folder that comes back}" dir="$WORK/frozen" base
  begin_device_job frozen "$minutes" "$out" "$dir"
  base=$(start_model)
  local common=(--preset "$PRESET" --ldr --warm-start "$base" --crop "$CROP" --batch "$BATCH" --outputs "$OUTPUTS"
    --colocated-outputs "$FROZEN_COLOCATED" --hemisphere-outputs "$HEMISPHERE" --lr "$FROZEN_LR" --warmup-steps 50
    --straight-through-output --checkerboard-free --adv-weight 0 --lpips-weight 0.1 --chroma-weight 1 --lobe-weight "$LOBE"
    --bank "$BANK" --steps 100000000 --minutes "$minutes" --checkpoint-every "$FROZEN_EVERY"
    --preview-every 1000000 --keep-exports --device "$DEVICE" --precision "$PRECISION" --threads "$FROZEN_THREADS")
  start_util_sampler "$dir/gpu-util.csv"
  local t0; t0=$(date +%s)
  "$BIN" train --out "$dir/estimator" "${common[@]}" --freeze-renderer --frozen-bn-from 0 --colour-augment 0.6 \
    "${FROZEN_ESTIMATOR_EXTRA[@]}" --seed "$((SEED + 20))" --export-dir "$dir/estimator-exports" >"$dir/estimator.log" 2>&1 &
  local estimator_pid=$!
  "$BIN" train --out "$dir/renderer" "${common[@]}" --freeze-estimator \
    --seed "$((SEED + 21))" --export-dir "$dir/renderer-exports" >"$dir/renderer.log" 2>&1 &
  local renderer_pid=$!
  local failed=""
  wait "$estimator_pid" || failed="estimator"
  wait "$renderer_pid" || failed+="${failed:+ and }renderer"
  local t1; t1=$(date +%s)
  [ -n "$UTIL_PID" ] && kill "$UTIL_PID" 2>/dev/null || true
  [ -z "$failed" ] || die "frozen: training failed ($failed): $(grep -h -m 1 '^error' "$dir"/estimator.log "$dir"/renderer.log | head -n 1)"
  local half
  {
    echo "# Frozen halves side by side (warm start from $(basename "$base"))"
    echo
    echo "- GPU: $(gpu_info); $((t1 - t0)) s of wall time for both runs"
  } >"$out/frozen.md"
  for half in estimator renderer; do
    average_late_exports "$dir/$half-exports" "$out/$half.safetensors"
    python3 - "$dir/$half/log.jsonl" "$half" "$BATCH" >>"$out/frozen.md" <<'EOF'
import json, sys
steps = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
seconds = sum(s["seconds"] for s in steps)
last = steps[-100:]
key = "l1" if sys.argv[2] == "estimator" else "l1_render"
print(f"- {sys.argv[2]} alone: steps {steps[0]['step']} to {steps[-1]['step']}, {len(steps) / seconds:.2f} steps/s "
      f"({len(steps) * int(sys.argv[3]) / seconds:.1f} materials/s), last 100 steps' L1 {sum(s[key] for s in last) / len(last):.4f}")
EOF
    echo "  - averaged: ${LATE_EXPORTS[*]}" >>"$out/frozen.md"
    [ -f "$dir/$half/colour.jsonl" ] && echo "  - uniform-colour check at its last checkpoint: \`$(tail -n 1 "$dir/$half/colour.jsonl")\`" >>"$out/frozen.md"
  done
  {
    [ -s "$dir/gpu-util.csv" ] && awk -F, '$1 ~ /^ *[0-9]/ { s += $1; n++ } END { if (n) printf "- GPU busy: %.0f%% (mean of %d samples)\n", s / n, n }' "$dir/gpu-util.csv"
    echo "- recipe: \`flashmat train ${common[*]}\` with \`--freeze-renderer --frozen-bn-from 0 --colour-augment 0.6${FROZEN_ESTIMATOR_EXTRA[*]:+ ${FROZEN_ESTIMATOR_EXTRA[*]}} --seed $((SEED + 20))\` (estimator) or \`--freeze-estimator --seed $((SEED + 21))\` (renderer); the later half of each run's exports averaged (\`flashmat average\`)"
  } >>"$out/frozen.md"
  [ "$FROZEN_SCORE" = 1 ] && frozen_scores "${FROZEN_SCORE_AGAINST:-$base}" "$dir" "$out"
  tar czf "$out/frozen.tgz" -C "$dir" --exclude='*.safetensors' --exclude=previews .
  cat "$out/frozen.md"
}

# Two frozen jobs in one call: the renderer retrained for a new M_est gained
# more than more M_est steps did (reports/gpu-campaign-2026-11-25/), and one
# call saves a machine start (reports/gpu-campaign-2026-11-26/).
frozen_chain() {
  local first="${1:-2.5}" second="${2:-1.8}" out="${OUT:?set OUT to the folder that comes back}"
  # Both checked before the first job spends GPU time.
  [[ "$first" =~ ^[0-9]+([.][0-9]+)?$ && "$second" =~ ^[0-9]+([.][0-9]+)?$ ]] \
    || die "frozen-chain: MINUTES_A and MINUTES_B must be numbers, not '$first' and '$second'"
  local start
  start=$(start_model)
  local staged="$WORK/chain-start.safetensors"
  mkdir -p "$WORK" && cp "$start" "$staged"
  FLASHMAT_GPU_RESUME="$staged" FLASHMAT_GPU_FROZEN_SCORE=0 OUT="$out/a" bash "$ROOT/scripts/gpu-train.sh" frozen "$first"
  FLASHMAT_GPU_RESUME="$out/a/estimator.safetensors" FLASHMAT_GPU_FROZEN_SCORE_AGAINST="$staged" OUT="$out/b" \
    bash "$ROOT/scripts/gpu-train.sh" frozen "$second"
}

# Issue 48's lever: M_est learns the codes of a teacher whose renderer draws
# moved highlights (reports/highlights-experiments.md, section 5).
distill() {
  local minutes="${1:-4}" out="${OUT:?set OUT to the folder that comes back}" dir="$WORK/distill" teacher="$CARRIED_TEACHER" base how
  begin_device_job distill "$minutes" "$out" "$dir"
  base=$(start_model)
  local t0; t0=$(date +%s)
  if [ -f "$teacher" ]; then
    how="the carried teacher $(basename "$teacher")"
  elif [ -f "$COMMITTED_TEACHER" ]; then
    # The CPU campaign's teacher (issue 86): the capture path's renderer too.
    teacher="$COMMITTED_TEACHER"
    how="the committed teacher $(basename "$teacher")"
  else
    "$BIN" train-teacher --preset "$DISTILL_PRESET" --out "$dir/teacher" --steps "$DISTILL_TEACHER_STEPS" \
      --pixels "$TEACHER_PIXELS" --lobe-share "$DISTILL_TEACHER_LOBE" --dark-floor "$DISTILL_TEACHER_DARK" --seed "$SEED" --device "$DEVICE" >"$dir/teacher.log" 2>&1 \
      || die "distill: the teacher failed: $(grep -m 1 '^error' "$dir/teacher.log")"
    teacher="$dir/teacher/teacher.safetensors"
    cp "$teacher" "$out/teacher.safetensors"
    how="trained here, $DISTILL_TEACHER_STEPS steps at lobe share $DISTILL_TEACHER_LOBE, dark floor $DISTILL_TEACHER_DARK, $TEACHER_PIXELS pixels a step, $(($(date +%s) - t0)) s; $(grep held_out "$dir/teacher/log.jsonl" | tail -n 1)"
  fi
  local args=(--preset "$DISTILL_PRESET" --ldr --teacher "$teacher" --code-weight "$DISTILL_CODE_WEIGHT" --code-gloss-weight "$DISTILL_CODE_GLOSS" --warm-start "$base"
    --freeze-renderer --adv-weight 0 --crop "$DISTILL_CROP" --batch "$BATCH" --outputs "$OUTPUTS" --colocated-outputs "$FROZEN_COLOCATED"
    --lr "$DISTILL_LR" --warmup-steps 50 --straight-through-output --checkerboard-free --lpips-weight 0.1 --chroma-weight 1
    --dark-share "$DARK_SHARE" --bank "$BANK" --steps 100000000 --minutes "$minutes" --checkpoint-every "$FROZEN_EVERY"
    --preview-every 1000000 --keep-exports --device "$DEVICE" --precision "$PRECISION" --seed "$((SEED + 30))")
  [ "$SATURATED_SHARE" = 0 ] || args+=(--saturated-share "$SATURATED_SHARE")
  [ "$DISTILL_VALUE_WEIGHT" = 0 ] || args+=(--ggx-value-weight "$DISTILL_VALUE_WEIGHT")
  [ "$DISTILL_GRAD_CLIP" = 0 ] || args+=(--grad-clip "$DISTILL_GRAD_CLIP")
  [ "$DISTILL_PHONE" = 0 ] || args+=(--phone-inputs "$DISTILL_PHONE")
  start_util_sampler "$dir/gpu-util.csv"
  local t1; t1=$(date +%s)
  "$BIN" train --out "$dir/run" "${args[@]}" --export-dir "$dir/exports" >"$dir/train.log" 2>&1 \
    || die "distill: training failed: $(grep -m 1 '^error' "$dir/train.log")"
  local t2; t2=$(date +%s)
  [ -n "$UTIL_PID" ] && kill "$UTIL_PID" 2>/dev/null || true
  average_late_exports "$dir/exports" "$out/model.safetensors"
  {
    echo "# Distill: M_est learns the teacher's codes against its frozen renderer (from $(basename "$base"))"
    echo
    echo "- GPU: $(gpu_info); teacher: $how; M_est: $((t2 - t1)) s"
    python3 - "$dir/run/log.jsonl" "$BATCH" <<'PY'
import json, sys
steps = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
seconds = sum(s["seconds"] for s in steps)
first, last = steps[:100], steps[-100:]
mean = lambda rows, k: sum(r[k] for r in rows) / len(rows)
print(f"- steps {steps[0]['step']} to {steps[-1]['step']}, {len(steps) / seconds:.2f} steps/s ({len(steps) * int(sys.argv[2]) / seconds:.1f} materials/s); "
      f"code error (relative L1) {mean(first, 'code'):.3f} -> {mean(last, 'code'):.3f}, L1 {mean(first, 'l1'):.4f} -> {mean(last, 'l1'):.4f} (first and last 100 steps)")
if all("ggx_values" in s for s in first + last):
    print(f"- GGX values' error (L1) {mean(first, 'ggx_values'):.4f} -> {mean(last, 'ggx_values'):.4f} (first and last 100 steps)")
norms = sorted(s.get("grad_norm_est", 0.0) for s in steps)
if norms[-1] > 0:
    print(f"- M_est's gradient norm (before any clip): median {norms[len(norms) // 2]:.3g}, largest {norms[-1]:.3g}")
PY
    echo "- averaged: ${LATE_EXPORTS[*]}"
    [ -s "$dir/gpu-util.csv" ] && awk -F, '$1 ~ /^ *[0-9]/ { s += $1; n++ } END { if (n) printf "- GPU busy: %.0f%% (mean of %d samples)\n", s / n, n }' "$dir/gpu-util.csv"
    [ -f "$dir/run/colour.jsonl" ] && echo "- checks at the last checkpoint (moved highlights on the six glossiest, uniform colour): \`$(tail -n 1 "$dir/run/colour.jsonl")\`"
    echo "- recipe: \`flashmat train ${args[*]}\`"
  } >"$out/distill.md"
  cp "$base" "$dir/start.safetensors"
  if timeout "$FROZEN_SCORE_SECONDS" "$BIN" eval --model "$out/model.safetensors" --model "$dir/start.safetensors" --dataset procedural-test \
    --cases identity --ldr-input --device "$DEVICE" -o "$dir/held-out" "${EVAL_EXTRA[@]}" >"$dir/held-out.log" 2>&1; then
    { echo; sed -n '/^## LPIPS/,$p' "$dir/held-out/summary.md"; } >>"$out/distill.md"
  else
    echo "- held-out scores: not finished in ${FROZEN_SCORE_SECONDS} s (\`held-out.log\` in distill.tgz)" >>"$out/distill.md"
  fi
  tar czf "$out/distill.tgz" -C "$dir" --exclude='*.safetensors' --exclude=previews .
  cat "$out/distill.md"
}

# The frozen job's two models, and each one's mean with the starting model
# (the mean brought the near-black highlight back within 2x,
# reports/gpu-campaign-2026-11-25/), scored on the GPU against the starting
# model: held-out LPIPS (FLASHMAT_GPU_FROZEN_CONFIGS configurations) and the
# uniform-colour check, into frozen.md. Each evaluation is time-boxed so the
# models come back whatever happens. $1: starting model; $2: work folder; $3: $OUT.
frozen_scores() {
  local base="$1" dir="$2" out="$3"
  cp "$base" "$dir/start.safetensors"
  "$BIN" average "$base" "$out/estimator.safetensors" -o "$dir/estimator-mean.safetensors"
  "$BIN" average "$base" "$out/renderer.safetensors" -o "$dir/renderer-mean.safetensors"
  local models=("$out/estimator.safetensors" "$dir/estimator-mean.safetensors" "$out/renderer.safetensors" "$dir/renderer-mean.safetensors" "$dir/start.safetensors")
  local args=() m
  for m in "${models[@]}"; do args+=(--model "$m"); done
  if timeout "$FROZEN_SCORE_SECONDS" "$BIN" eval "${args[@]}" --dataset procedural-test --configs "$FROZEN_CONFIGS" --ldr-input \
    --device "$DEVICE" -o "$dir/held-out" "${EVAL_EXTRA[@]}" >"$dir/held-out.log" 2>&1; then
    {
      echo
      echo "Held-out LPIPS ($FROZEN_CONFIGS configurations, 8-bit photos; mean (paired difference, materials better) against the starting model):"
      echo
      paired_table "$dir/held-out/start.csv" "$dir/held-out/"{estimator,estimator-mean,renderer,renderer-mean}.csv
    } >>"$out/frozen.md"
  else
    echo "- held-out scores: not finished in ${FROZEN_SCORE_SECONDS} s (\`held-out.log\` in frozen.tgz)" >>"$out/frozen.md"
  fi
  if timeout "$FROZEN_SCORE_SECONDS" "$BIN" eval --uniform "${args[@]}" --device "$DEVICE" -o "$dir/uniform" >"$dir/uniform.log" 2>&1; then
    { echo; grep -h '^## Uniform-colour check: \|^Mean chromaticity' "$dir/uniform/uniform.md"; } >>"$out/frozen.md"
  fi
}

verdict() {
  local out="${OUT:?set OUT to the folder that comes back}" keep_model="${1:-yes}"
  use_machine_libtorch
  mkdir -p "$WORK" "$out"
  local candidate="$WORK/candidate.safetensors"
  if [ -f "$WORK/run/checkpoint.safetensors" ]; then
    "$BIN" export --run "$WORK/run" -o "$candidate"
  elif [ -f "$RESUME_MODEL" ]; then
    cp "$RESUME_MODEL" "$candidate"
  else
    die "no model to judge: neither a run on this machine nor $RESUME_MODEL"
  fi
  local bundled="$ROOT/models/flashmat.safetensors"
  rm -rf "$WORK/eval"
  # 8-bit (clamped) photos: the recipe trains an 8-bit model (--ldr), and the
  # issue's protocol scores an 8-bit model on 8-bit photos.
  "$BIN" eval --model "$candidate" --model "$bundled" --dataset procedural-test --configs "$CONFIGS" \
    --ldr-input --device "$DEVICE" -o "$WORK/eval" "${EVAL_EXTRA[@]}" >/dev/null
  mkdir -p "$out/verdict"
  cp "$WORK/eval/summary.md" "$WORK/eval/candidate.csv" "$WORK/eval/flashmat.csv" "$out/verdict/"
  [ "$keep_model" = yes ] && cp "$candidate" "$out/candidate.safetensors"
  {
    echo "# Verdict: candidate against the bundled model (LPIPS, lower is better)"
    echo
    paired_table "$WORK/eval/flashmat.csv" "$WORK/eval/candidate.csv"
    echo
  } >"$out/verdict/verdict.md"
  if grep -q '| yes |$' "$out/verdict/verdict.md"; then
    echo "VERDICT: the candidate is better in all three cases: bundle it (docs/GPU.md, step 5)." >>"$out/verdict/verdict.md"
  else
    echo "VERDICT: the candidate is not better in all three cases: keep the bundled model." >>"$out/verdict/verdict.md"
  fi
  cat "$out/verdict/verdict.md"
}

# The CPU step after a campaign: the renderer alone at the recipe that made
# the 41,607-step model from the GPU's G5B (models/MODEL.md). Worth it when a
# GPU renderer run pushed the near-black matte highlight past 2x; it cost
# Reflect on a model that was within it (reports/gpu-campaign-2026-11-26-night/).
settle() {
  local model="${1:-}" minutes="${2:-28}" out="${OUT:?set OUT to the folder for the settled model}"
  [ -f "$model" ] || die "settle: no model file '$model' (usage: OUT=DIR gpu-train.sh settle MODEL [MINUTES])"
  [[ "$minutes" =~ ^[0-9]+([.][0-9]+)?$ ]] || die "settle: MINUTES must be a number, not '$minutes'"
  source scripts/env.sh
  local bin
  bin="$(flashmat_bin)" || exit 1
  mkdir -p "$out"
  "$bin" train --preset "$PRESET" --ldr --out "$out/run" --warm-start "$model" --crop "${FLASHMAT_SETTLE_CROP:-64}" \
    --outputs 4 --colocated-outputs 1 --batch 2 --lr 5e-5 --warmup-steps 50 --straight-through-output --checkerboard-free \
    --freeze-estimator --adv-weight 0 --lpips-weight 0.1 --chroma-weight 1 --pixel-sampling inverse-norm \
    --steps 100000000 --minutes "$minutes" --checkpoint-every "${FLASHMAT_SETTLE_EVERY:-250}" --seed 1 \
    --threads "${FLASHMAT_SETTLE_THREADS:-1}" --export-dir "$out/exports" --preview-every 1000000 \
    || die "settle: training failed (the lines above)"
  cp "$out/exports/model.safetensors" "$out/settled.safetensors"
  "$bin" eval --uniform --model "$out/settled.safetensors" ${FLASHMAT_SETTLE_UNIFORM_SIZE:+--size "$FLASHMAT_SETTLE_UNIFORM_SIZE"} -o "$out/uniform-check" \
    || die "settle: the uniform check failed (the lines above)"
  cp "$out/uniform-check/uniform.md" "$out/uniform.md"
  echo "gpu-train: settled $out/settled.safetensors; its uniform check (both near-black highlights within 2x is the bundling bound):"
  grep -h '^Mean chromaticity\|| near-black | identity |' "$out/uniform.md"
}

stage() {
  source scripts/env.sh
  cargo build --release --bin flashmat
  mkdir -p .gpu
  cp "$FLASHMAT_RELEASE_BIN" .gpu/flashmat
  # A campaign continues the bundled model (the first campaign's lesson,
  # docs/GPU.md) unless a resume model is already staged or FLASHMAT_GPU_FRESH=1;
  # a preset of fewer direction frequencies than the bundled model's
  # (compact-f8, BUNDLED_PRESET in src/infer/mod.rs), otherwise the same,
  # continues it cut to them.
  if [ ! -f "$RESUME_MODEL" ] && [ "${FLASHMAT_GPU_FRESH:-0}" != 1 ]; then
    if [ "$PRESET" = compact-f8 ]; then
      cp models/flashmat.safetensors "$RESUME_MODEL"
    else
      cargo run --release --example truncate_frequencies -- models/flashmat.safetensors "$PRESET" "$RESUME_MODEL"
    fi
  fi
  # The authors' code for the side-by-side benchmark (bench): their .py
  # files and models/ (about 140 KB), never committed; FLASHMAT_REF_DIR is
  # a copy of their repository (docs/GPU.md says how to get one).
  if [ -n "${FLASHMAT_REF_DIR:-}" ]; then
    [ -f "$FLASHMAT_REF_DIR/prl_main_train.py" ] || die "FLASHMAT_REF_DIR=$FLASHMAT_REF_DIR is not a copy of the authors' repository"
    rm -rf .gpu/ref && mkdir -p .gpu/ref .gpu/bench
    tar -c -C "$FLASHMAT_REF_DIR" --exclude=./.git --exclude=./demo_images --exclude=./data --exclude='*.ipynb' . | tar -x -C .gpu/ref
    cp "${FLASHMAT_REF_BENCH:-$ROOT/../shared/bench/ref_bench.py}" .gpu/bench/ref_bench.py
    echo "staged the authors' code in .gpu/ref and ref_bench.py in .gpu/bench (for bench)"
  fi
  local size; size=$(git ls-files -z | xargs -0 du -cb | tail -n 1 | cut -f1)
  local extra; extra=$(du -cb .gpu | tail -n 1 | cut -f1)
  echo "staged .gpu/ ($((extra / 1048576)) MiB; tracked tree $((size / 1048576)) MiB; a job takes at most 64 MiB)"
  [ -f "$RESUME_MODEL" ] && echo "chunks will warm-start from $RESUME_MODEL when the machine's disk is gone" || true
}

# Issue 49's side-by-side benchmark (docs/GPU.md). The shapes are the
# paper's recipes (crop 192, 2 x 8; crop 256, 2 x 4), the batch the authors'
# f32 step cannot fit (crop 256, 8 x 4) and the compact GPU recipe; inference
# at 256, 1024 and 2048 under a 32 GiB budget. BENCH_* override them (the dry run).
bench() {
  local out="${OUT:?set OUT to the folder that comes back}"
  use_machine_libtorch
  mkdir -p "$out" "$WORK"
  rm -f "$WORK"/bench-*.md
  local steps="${BENCH_STEPS:-8}" sizes="${BENCH_SIZES:-256,1024,2048}"
  local paper="${BENCH_PAPER_PRESET:-paper}" compact="${BENCH_COMPACT:-$PRESET 128 8 8}"
  read -r -a train_shapes <<<"${BENCH_TRAIN_SHAPES:-192:2:8 256:2:4 256:8:4}"
  local side=() amp=()
  if [ -f "$ROOT/.gpu/ref/prl_main_train.py" ] && [ -f "$ROOT/.gpu/bench/ref_bench.py" ]; then
    side=(--reference "$ROOT/.gpu/ref" --ref-bench "$ROOT/.gpu/bench/ref_bench.py")
    amp=(--amp)
    # The machine's own PyTorch runs the authors' code.
    [ -x /opt/torch/.venv/bin/python ] && export FLASHMAT_PYTHON=/opt/torch/.venv/bin/python
  else
    echo "bench: the authors' code is not staged (.gpu/ref, .gpu/bench): flashmat's numbers only" >&2
  fi
  : >"$out/bench.md"
  local n=0 shape crop batch outputs precision first=1
  read -r -a precisions <<<"${BENCH_PRECISIONS:-tf32 bf16}"
  for precision in "${precisions[@]}"; do
    # The authors' step once, beside the first precision's rows.
    local with=()
    [ "$first" = 1 ] && with=("${side[@]}" "${amp[@]}")
    for shape in "${train_shapes[@]}"; do
      IFS=: read -r crop batch outputs <<<"$shape"
      n=$((n + 1))
      "$BIN" bench train --device "$DEVICE" --preset "$paper" --precision "$precision" --crop "$crop" --batch "$batch" \
        --outputs "$outputs" --steps "$steps" "${with[@]}" --report "$WORK/bench-$n.md" >>"$out/bench.log" 2>&1 \
        || echo "bench train $paper $precision crop $crop $batch x $outputs failed: $(tail -n 1 "$out/bench.log")" >>"$out/bench.md"
      [ -f "$WORK/bench-$n.md" ] && { cat "$WORK/bench-$n.md"; echo; } >>"$out/bench.md"
    done
    read -r preset crop batch outputs <<<"$compact"
    n=$((n + 1))
    "$BIN" bench train --device "$DEVICE" --preset "$preset" --precision "$precision" --crop "$crop" --batch "$batch" \
      --outputs "$outputs" --steps "$steps" --report "$WORK/bench-$n.md" >>"$out/bench.log" 2>&1 \
      || echo "bench train $preset $precision failed: $(tail -n 1 "$out/bench.log")" >>"$out/bench.md"
    [ -f "$WORK/bench-$n.md" ] && { cat "$WORK/bench-$n.md"; echo; } >>"$out/bench.md"
    first=0
  done
  "$BIN" bench infer --device "$DEVICE" --preset "$paper" --size "$sizes" --max-memory 32G --runs 3 \
    "${side[@]}" "${amp[@]}" --report "$WORK/bench-infer.md" >>"$out/bench.log" 2>&1 \
    || echo "bench infer failed: $(tail -n 1 "$out/bench.log")" >>"$out/bench.md"
  [ -f "$WORK/bench-infer.md" ] && cat "$WORK/bench-infer.md" >>"$out/bench.md"
  cat "$out/bench.md"
}

# The binary the dry run and settle run: FLASHMAT_DRY_RUN_BIN, one already
# built (scripts/test.sh passes the tests' dev build, sparing CI a release
# build of everything), else the release build, built when missing.
flashmat_bin() {
  if [ -n "${FLASHMAT_DRY_RUN_BIN:-}" ]; then
    [ -x "$FLASHMAT_DRY_RUN_BIN" ] || die "FLASHMAT_DRY_RUN_BIN '$FLASHMAT_DRY_RUN_BIN' is not an executable file"
    echo "$FLASHMAT_DRY_RUN_BIN"
    return
  fi
  [ -x "$FLASHMAT_RELEASE_BIN" ] || cargo build --release --bin flashmat >&2 || die "the release build of flashmat failed"
  echo "$FLASHMAT_RELEASE_BIN"
}

# The whole campaign on the CPU with the tiny preset, in a temporary folder.
cpu_dry_run() {
  DRY_RUN_DIR=$(mktemp -d)
  trap 'rm -rf "$DRY_RUN_DIR"' EXIT
  local tmp="$DRY_RUN_DIR"
  source scripts/env.sh
  local bin
  bin="$(flashmat_bin)" || exit 1
  export FLASHMAT_GPU_DEVICE=cpu FLASHMAT_GPU_PRESET=tiny FLASHMAT_GPU_CROP=32 FLASHMAT_GPU_BATCH=2 \
    FLASHMAT_GPU_OUTPUTS=2 FLASHMAT_GPU_COLOCATED=1 FLASHMAT_GPU_MOVED=1 FLASHMAT_GPU_LOBE=0.1 FLASHMAT_GPU_BANK=6 FLASHMAT_GPU_WARMUP=2 FLASHMAT_GPU_CONFIGS=2 \
    FLASHMAT_GPU_WORK="$tmp/machine" FLASHMAT_GPU_BIN="$bin" \
    FLASHMAT_GPU_RESUME="$tmp/resume.safetensors" FLASHMAT_TORCH_LIB="$FLASHMAT_TORCH_LIB" \
    FLASHMAT_GPU_TEACHER_STEPS=20 FLASHMAT_GPU_TEACHER_PIXELS=1024 FLASHMAT_GPU_CARRIED_TEACHER="$tmp/teacher.safetensors"
  local self="$ROOT/scripts/gpu-train.sh"
  echo "== chunk 1 (fresh start: teacher, then flashmat with the teacher's codes)"
  OUT="$tmp/out1" bash "$self" chunk 0.15
  [ -f "$tmp/out1/model.safetensors" ] || die "dry run: chunk 1 brought back no model"
  [ -f "$tmp/out1/teacher.safetensors" ] || die "dry run: chunk 1 brought back no teacher"
  cp "$tmp/out1/teacher.safetensors" "$tmp/teacher.safetensors"
  local steps1; steps1=$(tail -n 1 "$tmp/out1/log.jsonl" | sed -n 's/.*"step":\([0-9]*\).*/\1/p')
  echo "== chunk 2 (the machine's disk is gone: warm start from chunk 1's export, step $steps1)"
  cp "$tmp/out1/model.safetensors" "$tmp/resume.safetensors"
  rm -rf "$tmp/machine"
  OUT="$tmp/out2" bash "$self" chunk 0.15
  local first2; first2=$(head -n 1 "$tmp/out2/log.jsonl" | sed -n 's/.*"step":\([0-9]*\).*/\1/p')
  [ "$first2" = "$((steps1 + 1))" ] || die "dry run: chunk 2 started at step $first2, expected $((steps1 + 1))"
  echo "== final (the disk is still there: resume from the checkpoint; verdict on 2 materials, 2 configurations, 64x64)"
  FLASHMAT_GPU_EVAL_EXTRA="--limit 2 --size 64" OUT="$tmp/out3" bash "$self" final 0.05
  grep -q "resumed from the machine's checkpoint" "$tmp/out3/chunk.md" || die "dry run: the final chunk did not resume from the checkpoint"
  python3 -c 'import json,sys; lr=json.loads(open(sys.argv[1]).readlines()[-1])["lr"]; sys.exit(0 if abs(lr-float(sys.argv[2]))<=1e-6*float(sys.argv[2]) else 1)' \
    "$tmp/out3/log.jsonl" "$FINAL_LR" || die "dry run: the final chunk did not train at FLASHMAT_GPU_FINAL_LR ($FINAL_LR)"
  grep -q '"checkerboard_free": true' "$tmp/machine/run/config.json" || die "dry run: the run was not started with --checkerboard-free"
  grep -q '"dark_share": 0.25' "$tmp/machine/run/config.json" || die "dry run: the run was not started with --dark-share 0.25"
  grep -q '"saturated_share": 0.1' "$tmp/machine/run/config.json" || die "dry run: the run was not started with --saturated-share 0.1"
  grep -q '"moved_highlight_outputs": 1' "$tmp/machine/run/config.json" || die "dry run: the run was not started with --moved-highlight-outputs 1"
  grep -q '"weight_lobe": 0.1' "$tmp/machine/run/config.json" || die "dry run: the run was not started with --lobe-weight 0.1"
  grep -q "^VERDICT: " "$tmp/out3/verdict/verdict.md" || die "dry run: no verdict"
  for f in model.safetensors log.jsonl losses.png chunk.md; do
    [ -f "$tmp/out2/$f" ] || die "dry run: chunk 2 brought back no $f"
  done
  local n; n=$(find "$tmp/out3" -type f | wc -l)
  [ "$n" -le 8 ] || die "dry run: the final job brings back $n files (a job returns at most 8)"
  echo "== side-by-side benchmark (flashmat's rows; the authors' where staged)"
  BENCH_STEPS=1 BENCH_SIZES=64 BENCH_PAPER_PRESET=tiny BENCH_COMPACT="tiny 32 2 2" BENCH_TRAIN_SHAPES="32:2:2" BENCH_PRECISIONS="bf16" \
    OUT="$tmp/bench" bash "$self" bench >/dev/null
  for row in "| training step, tiny, crop 32, 2 x 2, bf16 |" "| training step, tiny, crop 32, 2 x 2, bf16, flashmat's previous step |" "| M_est forward, tiny, 64x64 |" "| relit frame, tiny, 64x64 |"; do
    grep -qF "$row" "$tmp/bench/bench.md" || die "dry run: bench.md has no row '$row'"
  done
  echo "== frozen halves side by side, two jobs chained (from the final chunk's export)"
  cp "$tmp/out3/model.safetensors" "$tmp/resume.safetensors"
  FLASHMAT_GPU_HEMISPHERE=1 FLASHMAT_GPU_FROZEN_EVERY=2 FLASHMAT_GPU_FROZEN_THREADS=1 FLASHMAT_GPU_FROZEN_CONFIGS=1 \
    FLASHMAT_GPU_FROZEN_ESTIMATOR_EXTRA="--shift-weight 0.1 --shift-pixels 4 --shift-scale-free" \
    FLASHMAT_GPU_EVAL_EXTRA="--limit 2 --size 64" OUT="$tmp/out4" bash "$self" frozen-chain 0.1 0.1
  local job
  for job in a b; do
    for f in estimator.safetensors renderer.safetensors frozen.md frozen.tgz; do
      [ -f "$tmp/out4/$job/$f" ] || die "dry run: the frozen chain's job $job brought back no $f"
    done
    grep -q "estimator alone: steps" "$tmp/out4/$job/frozen.md" && grep -q "renderer alone: steps" "$tmp/out4/$job/frozen.md" \
      || die "dry run: job $job's frozen.md lacks a run's steps"
  done
  grep -q '"shift_scale_free": true' "$tmp/machine/frozen/estimator/config.json" && grep -q -- "--shift-scale-free --seed" "$tmp/out4/b/frozen.md" \
    || die "dry run: the frozen job's M_est run did not take FLASHMAT_GPU_FROZEN_ESTIMATOR_EXTRA"
  grep -q "warm start from estimator.safetensors" "$tmp/out4/b/frozen.md" || die "dry run: the chain's second job did not start from the first's estimator"
  grep -q '^| renderer-mean | ' "$tmp/out4/b/frozen.md" && grep -q '^## Uniform-colour check: start' "$tmp/out4/b/frozen.md" \
    || die "dry run: the chain's frozen.md lacks the held-out or the uniform scores"
  grep -q '^Held-out LPIPS' "$tmp/out4/a/frozen.md" && die "dry run: the chain's first job was scored (it should save that time)"
  cmp -s "$tmp/machine/frozen/start.safetensors" "$tmp/resume.safetensors" \
    || die "dry run: the chain's second job was not scored against the chain's starting model"
  n=$(find "$tmp/out4" -type f | wc -l)
  [ "$n" -le 8 ] || die "dry run: the frozen chain brings back $n files (a job returns at most 8)"
  echo "== distill: a teacher trained with lobe samples, then M_est alone learning its codes"
  FLASHMAT_GPU_DISTILL_PRESET=tiny FLASHMAT_GPU_DISTILL_CROP=32 FLASHMAT_GPU_DISTILL_TEACHER_STEPS=20 FLASHMAT_GPU_CARRIED_TEACHER="$tmp/no-teacher" FLASHMAT_GPU_COMMITTED_TEACHER= FLASHMAT_GPU_DISTILL_GRAD_CLIP=5 \
    FLASHMAT_GPU_FROZEN_EVERY=2 FLASHMAT_GPU_EVAL_EXTRA="--limit 2 --size 64" OUT="$tmp/out6" bash "$self" distill 0.1
  for f in model.safetensors teacher.safetensors distill.md distill.tgz; do
    [ -f "$tmp/out6/$f" ] || die "dry run: distill brought back no $f"
  done
  grep -q "lobe share 0.5" "$tmp/out6/distill.md" || die "dry run: distill's teacher was not trained with lobe samples"
  grep -q '"freeze_renderer": true' "$tmp/machine/distill/run/config.json" && grep -q '"weight_code": 1' "$tmp/machine/distill/run/config.json" \
    && grep -q '"code_gloss_weight": 4' "$tmp/machine/distill/run/config.json" \
    || die "dry run: distill did not train M_est alone with the code term, glossy pixels weighted"
  grep -q '"phone_inputs": 0.5' "$tmp/machine/distill/run/config.json" || die "dry run: distill's inputs were not phone photos (FLASHMAT_GPU_DISTILL_PHONE)"
  grep -q '"saturated_share": 0.1' "$tmp/machine/distill/run/config.json" || die "dry run: distill did not draw saturated materials (FLASHMAT_GPU_SATURATED_SHARE)"
  grep -q '"grad_clip": 5' "$tmp/machine/distill/run/config.json" && grep -q "M_est's gradient norm (before any clip): median" "$tmp/out6/distill.md" \
    || die "dry run: distill did not clip at FLASHMAT_GPU_DISTILL_GRAD_CLIP or report the gradient norms"
  grep -q '^## Moved highlights' "$tmp/out6/distill.md" && grep -q 'code error (relative L1)' "$tmp/out6/distill.md" \
    || die "dry run: distill.md lacks the code error or the moved-highlight table"
  echo "== settle the chain's renderer on the CPU"
  FLASHMAT_SETTLE_CROP=32 FLASHMAT_SETTLE_EVERY=2 FLASHMAT_SETTLE_UNIFORM_SIZE=32 OUT="$tmp/out5" \
    bash "$self" settle "$tmp/out4/b/renderer.safetensors" 0.05
  [ -f "$tmp/out5/settled.safetensors" ] && grep -q '^Mean chromaticity' "$tmp/out5/uniform.md" \
    || die "dry run: settle brought no model or no uniform check"
  grep -q '"freeze_estimator": true' "$tmp/out5/run/config.json" && grep -q '"colocated_outputs": 1' "$tmp/out5/run/config.json" \
    || die "dry run: settle did not train the renderer alone with one co-located output"
  echo "gpu-train: CPU dry run passed"
}

if [ -n "${FLASHMAT_GPU_EVAL_EXTRA:-}" ]; then
  read -r -a EVAL_EXTRA <<<"$FLASHMAT_GPU_EVAL_EXTRA"
fi

case "${1:-}" in
  stage) stage ;;
  bench) bench ;;
  chunk) shift; chunk "$@" ;;
  verdict) verdict yes ;;
  final) shift; CHUNK_LR="$FINAL_LR" chunk "$@"; verdict no ;;
  frozen) shift; frozen "$@" ;;
  frozen-chain) shift; frozen_chain "$@" ;;
  settle) shift; settle "$@" ;;
  distill) shift; distill "$@" ;;
  --cpu-dry-run) cpu_dry_run ;;
  *) die "usage: gpu-train.sh stage | chunk [MINUTES] | verdict | final [MINUTES] | frozen [MINUTES] | frozen-chain [MINUTES_A] [MINUTES_B] | settle MODEL [MINUTES] | distill [MINUTES] | --cpu-dry-run" ;;
esac
