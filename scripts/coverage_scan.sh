#!/usr/bin/env bash
# The covered-photo check (`capture::coverage`, issue 85) on the 50 held-out
# materials: synthetic phone photos of the frame (examples/frame_photos.rs,
# 5 photos, 1200x900) through `flashmat capture`, clean and with a grey card
# over the left part of the opening in photo 1. Prints one line a material
# (clean: refused or not; carded: the refusal) and the counts.
#
#   bash scripts/coverage_scan.sh [WORK=/tmp/flashmat-coverage] [PHOTOS=5] [MATERIALS="0..49"]
#
# About 12 s a material to render the photos (once), 2 s a capture.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
WORK="${1:-/tmp/flashmat-coverage}"
PHOTOS="${2:-5}"
MATERIALS="${3:-$(seq -s ' ' 0 49)}"
BIN=target/release/flashmat
PY="${FLASHMAT_PYTHON:-$HOME/.cache/flashmat/venv/bin/python}"
export OMP_NUM_THREADS=1 RAYON_NUM_THREADS=1
cargo build --release --quiet --bin flashmat --example frame_photos
mkdir -p "$WORK"
clean_refused=0 carded_named=0 n=0
for m in $MATERIALS; do
  d="$WORK/m$m"
  [ -f "$d/IMG_04.jpg" ] || target/release/examples/frame_photos "$d" 5 "$m" 1200 >/dev/null 2>&1
  rm -rf "$WORK/case" && mkdir -p "$WORK/case"
  mapfile -t photos < <(ls "$d"/IMG_*.jpg | head -n "$PHOTOS")
  clean=$("$BIN" capture "${photos[@]}" --flash-offset 8,0 -o "$WORK/case/clean" 2>&1 | grep '^error' || true)
  cp "${photos[@]}" "$WORK/case/"
  "$PY" - "$d/IMG_01.jpg" "$WORK/case/IMG_01.jpg" <<'EOF'
import sys
import numpy as np
from PIL import Image
im = Image.open(sys.argv[1])
a = np.array(im)
h, w = a.shape[:2]
s = int(0.2 * h)  # the opening spans about 0.4 of these photos' height, around the middle
a[h // 2 - s:h // 2 + s, w // 2 - s:w // 2] = 90
Image.fromarray(a).save(sys.argv[2], quality=92, exif=im.info.get("exif", b""))
EOF
  mapfile -t carded < <(ls "$WORK"/case/IMG_*.jpg)
  said=$("$BIN" capture "${carded[@]}" --flash-offset 8,0 -o "$WORK/case/carded" 2>&1 | grep '^error' || true)
  n=$((n + 1))
  [ -z "$clean" ] || clean_refused=$((clean_refused + 1))
  case "$said" in *"IMG_01.jpg: "*"of the opening is flat"*) carded_named=$((carded_named + 1)) ;; esac
  echo "m$m | clean: ${clean:-accepted} | carded: ${said:-accepted}"
done
echo "materials $n, photos $PHOTOS: clean captures refused $clean_refused, carded photo named $carded_named"
