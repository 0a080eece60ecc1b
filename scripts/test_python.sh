#!/usr/bin/env bash
# Tests of the Mitsuba 3 plugin (python/flashmat_mitsuba): sets up mitsuba,
# pytest and LLVM (scripts/mitsuba_env.sh, idempotent), installs the package
# from this checkout into flashmat's venv and runs python/tests.
# Extra arguments go to pytest (e.g. -k scalar).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/mitsuba_env.sh
PY="$FLASHMAT_VENV/bin/python"
t0=$(date +%s)
if "$PY" -c "import setuptools, wheel" 2>/dev/null; then
  "$PY" -m pip install --quiet --no-deps --no-build-isolation --force-reinstall .
else
  "$PY" -m pip install --quiet --no-deps --force-reinstall .
fi
rm -rf build python/*.egg-info
t1=$(date +%s)
echo "test_python: package installed in $((t1 - t0)) s" >&2
# Run from python/tests so the installed package (not the source folder) is imported.
cd python/tests
set +e
"$PY" -m pytest -q -p no:cacheprovider "$@" .
rc=$?
set -e
echo "test_python: pytest finished in $(( $(date +%s) - t1 )) s (exit $rc)" >&2
# Exit code 5 = no tests collected: a failure here.
[ "$rc" = 5 ] && { echo "test_python: no tests were collected" >&2; exit 1; }
exit "$rc"
