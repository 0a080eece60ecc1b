#!/usr/bin/env bash
# flashmat's main job. Sets everything up (Python environment with PyTorch,
# release build), then turns every bundled flash photo in examples/photos/
# into a neural material with the bundled model and writes, for each photo,
# to out/<photo>/:
#   material.nmat  the neural material (flashmat relight/show, Mitsuba plugin)
#   grid.png       input | neural map norm | neural map PCA | identity render,
#                  and the material under four lights
#   orbit.gif      a light circling the material
#   material.html  the material live in a browser (flashmat view; open it by
#                  double-click: the mouse moves the light)
#   out/large-3x2/ a large 3:2 photo estimated at full resolution (timed)
# Usage: scripts/demo.sh [PHOTO ...] [-- extra estimate options]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
# HEIC/AVIF photos (a phone's own) need libheif: installed once when
# missing; without it they are refused with the way to convert them.
features=(--features raw)
bash scripts/install-libheif.sh >/dev/null && features=(--features heif,raw)
cargo build --release --quiet ${features[@]+"${features[@]}"}
FLASHMAT="$FLASHMAT_RELEASE_BIN"
FRAMES=${FLASHMAT_ORBIT_FRAMES:-24}

photos=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do photos+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
if [ ${#photos[@]} -eq 0 ]; then
    photos=(examples/photos/*.png examples/photos/*.jpg)
fi

# The bundled photos are already cropped to the material: no FOV crop,
# unless the options say otherwise.
fov=(--fov 28)
for arg in "$@"; do [[ "$arg" == --fov* ]] && fov=(); done

start=$SECONDS
# Per photo, how well the material gives it back (estimate's last line):
# the identity render's brightness and R / G / B over the photo's.
summary=()
for photo in "${photos[@]}"; do
    [ -e "$photo" ] || continue
    name=$(basename "${photo%.*}")
    dir=out/$name
    mkdir -p "$dir"
    echo "== $photo"
    $FLASHMAT estimate "$photo" -o "$dir/material.nmat" "${fov[@]}" "$@" 2>&1 | tee "$dir/estimate.log"
    check=$(sed -n 's/.*identity render over the photo: //p' "$dir/estimate.log" | tail -n 1)
    summary+=("$(printf '%-24s %s' "$name" "${check:-(no pixel to compare)}")")
    $FLASHMAT show "$dir/material.nmat" -o "$dir/grid.png"
    $FLASHMAT relight "$dir/material.nmat" --orbit "$FRAMES" -o "$dir/orbit.gif"
    $FLASHMAT view "$dir/material.nmat" -o "$dir/material.html"
done
echo "done in $((SECONDS - start)) s: out/<photo>/{material.nmat,grid.png,orbit.gif,material.html}"
if [ ${#summary[@]} -gt 0 ]; then
    echo "identity render over each photo (unclipped pixels; 1.00 is the photo, beyond 0.9-1.1 trust it less):"
    printf '  %s\n' "${summary[@]}"
fi

# One large non-square photo, as phones take them: a 3:2 flash render of a
# held-out material (1536x1024, 8-bit), estimated at full resolution as a
# 1024x1536 material (the shorter side spans [-1, 1]), then relit.
# FLASHMAT_DEMO_LARGE=0 skips it; FLASHMAT_DEMO_LARGE=2048 uses a 3072x2048
# photo (M_est then runs layer by layer over tiles under --max-memory 8G).
large=${FLASHMAT_DEMO_LARGE:-1024}
if [ "$large" != 0 ] && [ ${#photos[@]} -gt 0 ]; then
    dir=out/large-3x2
    mkdir -p "$dir"
    echo "== $dir: a $((large * 3 / 2))x$large photo at full resolution"
    $FLASHMAT render --svbrdf procedural-test:7 --size $((large * 3 / 2)) --rows "$large" -o "$dir/photo.png"
    t=$SECONDS
    $FLASHMAT estimate "$dir/photo.png" --fov 28 --size "$large" -o "$dir/material.nmat"
    $FLASHMAT relight "$dir/material.nmat" --light 1.5,1,2.5 -o "$dir/relit.png"
    echo "large 3:2 example: estimate + relight in $((SECONDS - t)) s: $dir/{photo.png,material.nmat,relit.png}"
fi
