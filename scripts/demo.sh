#!/usr/bin/env bash
# Sets everything up (Python environment with PyTorch, release build) and runs
# flashmat's main job, writing pictures to out/.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
cargo build --release --quiet
FLASHMAT=target/release/flashmat
mkdir -p out
$FLASHMAT svbrdf preview procedural --count 8 -o out/procedural-preview.png
$FLASHMAT render --svbrdf procedural:7 --light 1.5,1,3 --view 0,0,4.010781 -o out/render-side-light.png
$FLASHMAT render --svbrdf procedural:7 -o out/render-colocated.exr
echo "pictures in out/: procedural-preview.png, render-side-light.png, render-colocated.exr"
