#!/usr/bin/env bash
# End to end: sets up Mitsuba 3 (scripts/mitsuba_env.sh), builds flashmat
# (release), installs the plugin from this checkout and renders the examples.
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
iso=""; "$PY" -c "import setuptools, wheel" 2>/dev/null && iso="--no-build-isolation"
"$PY" -m pip install --quiet --no-deps $iso --force-reinstall . >/dev/null
rm -rf build python/*.egg-info
exec "$PY" examples/mitsuba/render_examples.py "$out" --flashmat "$target/release/flashmat" "$@"
