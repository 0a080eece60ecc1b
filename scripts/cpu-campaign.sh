#!/usr/bin/env bash
# The single-photo model, trained on the CPU across sessions (issue 86):
# M_est learns the codes of the committed teacher for every GGX material
# (models/teacher-any-ggx.safetensors: lobes drawn), from the teacher's
# renderer (frozen in stages A and B, trained since stage C), one thread,
# exports every few minutes. docs/TRAINING.md ("The CPU campaign").
#
#   bash scripts/cpu-campaign.sh run [MINUTES]    # resume the run, or start it; MINUTES of one thread (default 60)
#   bash scripts/cpu-campaign.sh export [FILE]    # the run's last exports averaged (default: $CAMPAIGN/student.safetensors)
#   bash scripts/cpu-campaign.sh curve            # the run's learning curve so far (code error against CPU hours)
#   bash scripts/cpu-campaign.sh gate MODEL [--replace]   # MODEL against the bundled model: gate.md; --replace bundles it when it passes
#
# Where it stands: $FLASHMAT_CACHE/campaign (default ~/.cache/flashmat/campaign):
# run/ (the train run: resumed when this machine still has it), exports/
# (its checkpoints' exports), adapter.safetensors (the start), gate/.
# Without run/, a new run starts from $CAMPAIGN/continue.safetensors (a
# model put there by hand: a GPU distill job's), else from
# models/campaign.safetensors when the tree holds one (the last committed
# export; Adam's state starts afresh: the recipe warms up 50 steps), else
# from the bundled model with its head fitted linearly to the teacher's
# codes (examples/code_adapter.rs). A student is 10.6 MB: it fits the
# tracked tree's 32 MiB only in place of the bundled model, so until one
# passes the gate a new machine starts from the adapter.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
source scripts/env.sh
export OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=10000

CAMPAIGN="${FLASHMAT_CAMPAIGN:-${FLASHMAT_CACHE:-$HOME/.cache/flashmat}/campaign}"
TEACHER="${FLASHMAT_CAMPAIGN_TEACHER:-$ROOT/models/teacher-any-ggx.safetensors}"
COMMITTED="$ROOT/models/campaign.safetensors"
BUNDLED="$ROOT/models/flashmat.safetensors"
BIN="${FLASHMAT_BIN:-$ROOT/target/release/flashmat}"
# The gate's dry run (the plumbing on a few small materials and photos):
# FLASHMAT_GATE_EVAL_EXTRA="--limit 2 --size 64" FLASHMAT_GATE_PHOTOS="examples/photos/IMG_6950.png".
# Exports every this many steps: about 5 minutes of one thread at crop 256.
EVERY="${FLASHMAT_CAMPAIGN_EVERY:-25}"

die() { echo "cpu-campaign: $*" >&2; exit 1; }

build() {
  [ -x "$BIN" ] || cargo build --release --quiet || die "the build failed"
}

# The recipe: E12's (reports/highlights-experiments.md section 5: the code
# term with glossy pixels weighted 4x, renderer frozen) at crop 256 (section
# 12: more lobe than crop 128 at equal time) with half the inputs phone
# photos (section 11). Stage B (from step 46,506 on): the code term at 0.25
# and LPIPS at 1. Stage A (code 1, LPIPS 0.1) moved the highlights (ghost
# 2.08 -> 1.51, lobe 0.18 -> 0.37) but its code error stalled at 0.58 after
# 3 CPU hours with Identity LPIPS at 0.258 (bundled 0.115): the code term
# was 0.6 of a 0.7 loss, the photo's own render 0.07
# (reports/campaign/eval-46506.md). Stage B stalled too (Identity 0.159,
# ghost 1.89 at step 48,164), so stage C (from step 48,164 on) changes the
# model: the renderer, until then the teacher's frozen copy, trains with
# M_est (the paper's alternating steps), so that it learns to render the
# codes M_est can write from one photo. In 287 steps it took Identity LPIPS
# 0.159 -> 0.139, the ghost 1.89 -> 1.64 and the rest 1.15 -> 1.02, but the
# lobe back to the bundled model's (0.44 -> 0.20): trained on the output
# renders alone, the renderer forgets the lobes (reports/campaign/eval-48451.md).
# Stage D (next): the teacher of 2026-12-07 (compact-f8h), M_est from stage
# C, the renderer trained with a small lobe term (--lobe-weight 0.02, half
# the lights in the lobe), which holds the teacher's lobes (E3 of
# reports/highlights-experiments.md: lobe 0.16 -> 0.50 at weight 0.02).
# FLASHMAT_CAMPAIGN_CODE_WEIGHT, FLASHMAT_CAMPAIGN_LPIPS_WEIGHT,
# FLASHMAT_CAMPAIGN_RENDERER (trained or frozen) and
# FLASHMAT_CAMPAIGN_LOBE_WEIGHT set them for a new run.
# The student's preset is its teacher's: it starts from the teacher's renderer.
teacher_preset() {
  python3 - "$TEACHER" 2>/dev/null <<'EOF' || die "$TEACHER is not a teacher file (no preset in its header); models/MODEL.md has the committed teacher's recipe"
import json, struct, sys
with open(sys.argv[1], "rb") as f:
    header = json.loads(f.read(struct.unpack("<Q", f.read(8))[0]))
print(json.loads(header["__metadata__"]["teacher_config"])["model"]["name"])
EOF
}

# $1: the student's preset (teacher_preset's, read once by run).
recipe() {
  local renderer=()
  case "${FLASHMAT_CAMPAIGN_RENDERER:-trained}" in
    trained) renderer=(--lobe-weight "${FLASHMAT_CAMPAIGN_LOBE_WEIGHT:-0.02}" --lobe-share 0.5) ;;
    frozen) renderer=(--freeze-renderer) ;;
  esac
  echo --preset "$1" --ldr --teacher "$TEACHER" --code-weight "${FLASHMAT_CAMPAIGN_CODE_WEIGHT:-0.25}" --code-gloss-weight 4 "${renderer[@]}" \
    --crop 256 --outputs 4 --colocated-outputs 1 --batch 2 --lr 3e-4 --warmup-steps 50 --straight-through-output \
    --checkerboard-free --adv-weight 0 --lpips-weight "${FLASHMAT_CAMPAIGN_LPIPS_WEIGHT:-1}" --chroma-weight 1 --phone-inputs 0.5 \
    --steps 100000000 --checkpoint-every "$EVERY" --keep-exports --preview-every 1000000 --seed 13 --threads 1
}

start_model() {
  local model
  for model in "$CAMPAIGN/continue.safetensors" "$COMMITTED"; do
    if [ -f "$model" ]; then
      echo "$model"
      return
    fi
  done
  local adapter="$CAMPAIGN/adapter.safetensors"
  if [ ! -f "$adapter" ]; then
    echo "cpu-campaign: fitting the bundled model's head to the teacher's codes (one time, about 2 minutes)" >&2
    cargo run --release --quiet --example code_adapter -- "$BUNDLED" "$TEACHER" "$adapter.tmp" 96 128 >&2 \
      || die "the code adapter failed"
    mv "$adapter.tmp" "$adapter"
  fi
  echo "$adapter"
}

run() {
  local minutes="${1:-60}"
  [[ "$minutes" =~ ^[0-9]+([.][0-9]+)?$ ]] || die "MINUTES must be a number, not '$minutes'"
  [ -f "$TEACHER" ] || die "no teacher at $TEACHER (models/MODEL.md: the teacher for every GGX material)"
  case "${FLASHMAT_CAMPAIGN_RENDERER:-trained}" in
    trained|frozen) ;;
    *) die "FLASHMAT_CAMPAIGN_RENDERER is trained or frozen, not '$FLASHMAT_CAMPAIGN_RENDERER'" ;;
  esac
  build
  mkdir -p "$CAMPAIGN/exports"
  if [ -f "$CAMPAIGN/run/checkpoint.safetensors" ]; then
    echo "cpu-campaign: resuming $CAMPAIGN/run for $minutes minutes" >&2
    # --keep-exports is the run's option, not the recipe's: given again on resume.
    "$BIN" train --resume "$CAMPAIGN/run" --minutes "$minutes" --export-dir "$CAMPAIGN/exports" --keep-exports --threads 1
  else
    local preset start; preset=$(teacher_preset) || exit 1
    start=$(start_model)
    echo "cpu-campaign: a new run from $start for $minutes minutes" >&2
    # shellcheck disable=SC2046
    "$BIN" train --out "$CAMPAIGN/run" --warm-start "$start" $(recipe "$preset") --minutes "$minutes" --export-dir "$CAMPAIGN/exports"
  fi
}

export_student() {
  local out="${1:-$CAMPAIGN/student.safetensors}"
  build
  mapfile -t last < <(ls "$CAMPAIGN"/exports/step-*.safetensors 2>/dev/null | sort -V | tail -n 4)
  [ ${#last[@]} -gt 0 ] || die "no exports in $CAMPAIGN/exports yet (run first)"
  "$BIN" average "${last[@]}" -o "$out"
}

curve() {
  local log="$CAMPAIGN/run/log.jsonl"
  [ -f "$log" ] || die "no run log at $log (run first)"
  python3 - "$log" <<'EOF'
import json, sys
seconds, rows = 0.0, []
for line in open(sys.argv[1]):
    r = json.loads(line)
    seconds += r.get("seconds", 0.0)
    if "code" in r:
        rows.append((r["step"], seconds / 3600, r["code"]))
print("| step | CPU hours | code error (mean of the last 25 steps) |")
print("|---|---|---|")
for i in range(0, len(rows), max(1, len(rows) // 20)):
    window = [c for _, _, c in rows[max(0, i - 24): i + 1]]
    print(f"| {rows[i][0]} | {rows[i][1]:.2f} | {sum(window) / len(window):.3f} |")
EOF
}

gate() {
  local model="${1:?usage: cpu-campaign.sh gate MODEL [--replace]}" replace="${2:-}" out="$CAMPAIGN/gate"
  [ -f "$model" ] || die "no model at $model"
  [ -z "$replace" ] || [ "$replace" = --replace ] || die "the gate takes MODEL and then only --replace, not '$replace'"
  build
  rm -rf "$out" && mkdir -p "$out/photos"
  cp "$model" "$out/candidate.safetensors"
  # The 50 held-out materials: Identity, Reflect and Hemisphere LPIPS at 16
  # configurations and the moved-highlight table, both models in one run.
  # shellcheck disable=SC2086
  "$BIN" eval --model "$BUNDLED" --model "$out/candidate.safetensors" --ldr-input --configs 16 -o "$out/eval" ${FLASHMAT_GATE_EVAL_EXTRA:-}
  # The 13 bundled photos: the identity render's brightness over the photo.
  local photo name which
  for photo in ${FLASHMAT_GATE_PHOTOS:-examples/photos/*}; do
    name=$(basename "${photo%.*}")
    for which in bundled candidate; do
      local m="$BUNDLED"; [ "$which" = candidate ] && m="$out/candidate.safetensors"
      "$BIN" estimate "$photo" --model "$m" --fov 28 -o "$out/photos/$name-$which.nmat" 2>&1 \
        | sed -n "s/.*identity render over the photo: brightness \([0-9.]*\).*/$name $which \1/p" >>"$out/photos/brightness.txt"
    done
  done
  python3 scripts/campaign_gate.py "$out" >"$out/gate.md"
  cat "$out/gate.md"
  if grep -q '^PASS' "$out/gate.md" && [ "$replace" = --replace ]; then
    cp "$out/candidate.safetensors" "$BUNDLED.tmp" && mv "$BUNDLED.tmp" "$BUNDLED"
    echo "cpu-campaign: $model replaced $BUNDLED (record it in models/MODEL.md with $out/gate.md)" >&2
  fi
}

case "${1:-}" in
  run) shift; run "$@" ;;
  export) shift; export_student "$@" ;;
  curve) curve ;;
  gate) shift; gate "$@" ;;
  *) die "usage: cpu-campaign.sh run [MINUTES] | export [FILE] | curve | gate MODEL [--replace]" ;;
esac
