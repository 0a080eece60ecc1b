# Source this file: creates (once) and activates flashmat's Python environment
# (PyTorch 2.11.0 from PyPI, whose libtorch the `tch` crate links against).
# The environment lives in a per-user cache outside the clone so fresh clones,
# CI runs and worktrees share it: ${FLASHMAT_CACHE:-~/.cache/flashmat}/venv.
FLASHMAT_CACHE="${FLASHMAT_CACHE:-$HOME/.cache/flashmat}"
FLASHMAT_VENV="$FLASHMAT_CACHE/venv"
FLASHMAT_TORCH_VERSION="2.11.0"

flashmat_setup_venv() {
  if [ -x "$FLASHMAT_VENV/bin/python" ] && \
     "$FLASHMAT_VENV/bin/python" -c "import torch,sys; sys.exit(0 if torch.__version__.startswith('$FLASHMAT_TORCH_VERSION') else 1)" 2>/dev/null; then
    return 0
  fi
  echo "flashmat: creating Python environment in $FLASHMAT_VENV (torch==$FLASHMAT_TORCH_VERSION, one-time, a few minutes)" >&2
  mkdir -p "$FLASHMAT_CACHE"
  python3 -m venv "$FLASHMAT_VENV" || return 1
  "$FLASHMAT_VENV/bin/pip" install --quiet --upgrade pip || return 1
  "$FLASHMAT_VENV/bin/pip" install --quiet "torch==$FLASHMAT_TORCH_VERSION" numpy || return 1
}

flashmat_setup_venv || { echo "flashmat: could not create the Python environment" >&2; return 1 2>/dev/null || exit 1; }

export PATH="$FLASHMAT_VENV/bin:$PATH"
export LIBTORCH_USE_PYTORCH=1
export PYTHON_SYS_EXECUTABLE="$FLASHMAT_VENV/bin/python"
FLASHMAT_TORCH_LIB="$("$FLASHMAT_VENV/bin/python" -c 'import torch,os; print(os.path.join(os.path.dirname(torch.__file__),"lib"))')"
export FLASHMAT_TORCH_LIB
export LD_LIBRARY_PATH="$FLASHMAT_TORCH_LIB${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

# The checkout whose models/ and assets/ flashmat reads (`bundled_root`):
# this one, whichever checkout built the binary. Clones that share one
# CARGO_TARGET_DIR share their binaries (cargo does not rebuild for another
# checkout of the same sources), and a binary otherwise reads the files of
# the checkout that built it.
FLASHMAT_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export FLASHMAT_ROOT

# The release binary the scripts run: cargo's, wherever a shared
# CARGO_TARGET_DIR puts it (a relative one read from the checkout, as the
# scripts run cargo there, whatever folder sourced this file).
FLASHMAT_RELEASE_BIN="$(cd "$FLASHMAT_ROOT" && realpath -m "${CARGO_TARGET_DIR:-target}")/release/flashmat"
export FLASHMAT_RELEASE_BIN
