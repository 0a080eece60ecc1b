#!/usr/bin/env bash
# Tests of the Python package `flashmat` (python/flashmat: the extension
# built from python/Cargo.toml, and the Mitsuba 3 plugin flashmat.mitsuba):
# sets up mitsuba, pytest and LLVM (scripts/mitsuba_env.sh, idempotent) and
# maturin and matplotlib, then does what a user does, in a fresh virtual
# environment: `pip install --no-build-isolation .` from this checkout and
# pytest python/tests. The fresh environment sees flashmat's environment's
# packages (torch, mitsuba, pytest) through a .pth file instead of
# downloading torch's 3 GB again; flashmat itself is only in the fresh one.
# The extension builds in cargo's dev profile into target/, beside the Rust
# tests' build (set FLASHMAT_PY_PROFILE=release for benchmarks), with the
# `heif` feature where FLASHMAT_CARGO_FEATURES says so (scripts/test.sh).
# Extra arguments go to pytest (e.g. -k scalar).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/mitsuba_env.sh
if ! "$FLASHMAT_VENV/bin/python" -c "import maturin, matplotlib" 2>/dev/null; then
  echo "test_python: installing maturin and matplotlib into $FLASHMAT_VENV (one-time)" >&2
  "$FLASHMAT_VENV/bin/pip" install --quiet "maturin>=1.7,<2" matplotlib
fi
t0=$(date +%s)
fresh="$(mktemp -d)"
trap 'rm -rf "$fresh"' EXIT
python3 -m venv "$fresh/venv"
purelib() { "$1" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])'; }
purelib "$FLASHMAT_VENV/bin/python" > "$(purelib "$fresh/venv/bin/python")/flashmat-base-environment.pth"
export VIRTUAL_ENV="$fresh/venv"
export PATH="$fresh/venv/bin:$PATH"
features="${FLASHMAT_CARGO_FEATURES:+--features $FLASHMAT_CARGO_FEATURES}"
MATURIN_PEP517_ARGS="--profile ${FLASHMAT_PY_PROFILE:-dev} $features" \
  python -m pip install --quiet --no-build-isolation .
t1=$(date +%s)
echo "test_python: package built and installed into a fresh environment in $((t1 - t0)) s" >&2
# Run from python/tests so the installed package (not the source folder) is imported.
cd python/tests
set +e
python -m pytest -q -p no:cacheprovider "$@" .
rc=$?
set -e
echo "test_python: pytest finished in $(( $(date +%s) - t1 )) s (exit $rc)" >&2
# Exit code 5 = no tests collected: a failure here.
[ "$rc" = 5 ] && { echo "test_python: no tests were collected" >&2; exit 1; }
exit "$rc"
