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
# Usage: scripts/demo.sh [PHOTO ...] [-- extra estimate options]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
cargo build --release --quiet
FLASHMAT=target/release/flashmat
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
for photo in "${photos[@]}"; do
    [ -e "$photo" ] || continue
    name=$(basename "${photo%.*}")
    dir=out/$name
    mkdir -p "$dir"
    echo "== $photo"
    $FLASHMAT estimate "$photo" -o "$dir/material.nmat" "${fov[@]}" "$@"
    $FLASHMAT show "$dir/material.nmat" -o "$dir/grid.png"
    $FLASHMAT relight "$dir/material.nmat" --orbit "$FRAMES" -o "$dir/orbit.gif"
    $FLASHMAT view "$dir/material.nmat" -o "$dir/material.html"
done
echo "done in $((SECONDS - start)) s: out/<photo>/{material.nmat,grid.png,orbit.gif,material.html}"
