#!/usr/bin/env bash
# End to end: sets up Mitsuba 3 (scripts/mitsuba_env.sh), builds flashmat
# (release) and renders the examples with the plugin from this checkout
# (flashmat.mitsuba is pure Python: imported from python/, no build).
#   examples/mitsuba/run.sh [OUT] [render_examples.py options...]
#   examples/mitsuba/run.sh out/mitsuba --model /path/model.safetensors --res 256 --spp 64
# OUT defaults to out/mitsuba; --model defaults to models/flashmat.safetensors.
set -euo pipefail
cd "$(dirname "$0")/../.."
out="${1:-out/mitsuba}"
[ $# -gt 0 ] && shift
. scripts/mitsuba_env.sh
cargo build --release --quiet
target="${CARGO_TARGET_DIR:-target}"
PY="$FLASHMAT_VENV/bin/python"
PYTHONPATH="$PWD/python${PYTHONPATH:+:$PYTHONPATH}" exec "$PY" examples/mitsuba/render_examples.py "$out" --flashmat "$target/release/flashmat" "$@"
