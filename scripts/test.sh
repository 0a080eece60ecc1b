#!/usr/bin/env bash
# Sets everything up (Python environment with PyTorch, Rust build) and runs
# every test of the project.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
# nextest runs tests in parallel processes: give each one libtorch thread
# and no OpenMP busy-waiting, or oversubscribed spinning threads slow the
# training tests down tenfold on a 2-core machine.
export OMP_WAIT_POLICY=PASSIVE
# The value the CLI would add and re-execute itself for (src/main.rs): set
# here, each of the tests' hundreds of CLI runs loads libtorch once, not twice.
export GOMP_SPINCOUNT=10000
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# Each test runs in its own process under nextest: libtorch's random
# generator is process-global, and tests that check bit-exact determinism
# must not share it with tests running in parallel.
# Headless Chromium for the browser test of `flashmat view` (tests/viewer.rs):
# Debian's package, installed once when missing (the test skips, saying so,
# only where it cannot be installed).
bash scripts/install-chromium.sh >/dev/null || true
# HEIC/HEIF and AVIF photos (the `heif` feature, src/io/heif.rs) link the
# system libheif: Debian's libheif-dev, installed once when missing. Where
# it cannot be installed the tests run without the feature, saying so; CI
# (.ci/run sets FLASHMAT_REQUIRE_HEIF=1) fails instead.
# RAW photos (the `raw` feature, src/io/raw.rs: rawler, pure Rust) are
# always on here.
features=(--features raw)
export FLASHMAT_CARGO_FEATURES=raw
if bash scripts/install-libheif.sh >/dev/null; then
  features=(--features heif,raw)
  # The Python package's extension is built with them too (scripts/test_python.sh).
  export FLASHMAT_CARGO_FEATURES=heif,raw
elif [ "${FLASHMAT_REQUIRE_HEIF:-0}" = 1 ]; then
  echo "test: libheif-dev is required here (FLASHMAT_REQUIRE_HEIF=1) and could not be installed" >&2
  exit 1
else
  echo "test: no libheif-dev: testing without HEIC/AVIF support (the heif feature)" >&2
fi
rust_rc=0
if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --all-targets ${features[@]+"${features[@]}"} --no-fail-fast 2>&1 || rust_rc=$?
else
  cargo test --all-targets ${features[@]+"${features[@]}"} -- --test-threads=1 2>&1 || rust_rc=$?
fi
# The Python package (the extension and the Mitsuba 3 plugin; pytest): a
# fresh environment, pip install of this checkout; mitsuba, maturin and
# libllvm19 are installed once.
python_rc=0
bash scripts/test_python.sh 2>&1 || python_rc=$?
# The GPU campaign's steps on the CPU (tiny preset, about 4 minutes on 2 cores).
# It runs the tests' dev build of the binary (a release build would take
# CI minutes).
campaign_rc=0
FLASHMAT_DRY_RUN_BIN="$(realpath -m "${CARGO_TARGET_DIR:-target}")/debug/flashmat" \
  bash scripts/gpu-train.sh --cpu-dry-run 2>&1 || campaign_rc=$?
# A GPU job takes at most 64 MiB: the tracked tree stays within 32 MiB so
# the binary and a model to resume from fit beside it.
gate_rc=0
python3 scripts/test_campaign_gate.py 2>&1 || gate_rc=$?
size_rc=0
bash scripts/check-size.sh || size_rc=$?
echo "rust tests exit $rust_rc, python tests exit $python_rc, GPU campaign dry run exit $campaign_rc, CPU campaign gate tests exit $gate_rc, tree size check exit $size_rc"
[ "$rust_rc" = 0 ] && [ "$python_rc" = 0 ] && [ "$campaign_rc" = 0 ] && [ "$gate_rc" = 0 ] && [ "$size_rc" = 0 ]
