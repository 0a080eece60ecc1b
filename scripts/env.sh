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

# The CUDA toolkit headers that the PyTorch wheels leave out (crt/, CCCL),
# for build.rs to compile the NCCL half of src/dist/shim.cpp (distributed
# training on GPUs, docs/DISTRIBUTED.md): a one-time 19 MB download beside
# the environment, only where torch is a CUDA build. Without them flashmat
# builds distributed training for the CPU (Gloo) only.
FLASHMAT_CUDA_MM="$("$FLASHMAT_VENV/bin/python" -c 'import torch; print(torch.version.cuda or "")')"
FLASHMAT_CUDA_HEADERS="$FLASHMAT_CACHE/cuda-headers-$FLASHMAT_CUDA_MM/nvidia/cu${FLASHMAT_CUDA_MM%%.*}/include"
if [ -n "$FLASHMAT_CUDA_MM" ] && [ ! -e "$FLASHMAT_CUDA_HEADERS/crt/host_config.h" ]; then
  echo "flashmat: fetching the CUDA $FLASHMAT_CUDA_MM crt and CCCL headers into $FLASHMAT_CACHE (one-time, 19 MB)" >&2
  "$FLASHMAT_VENV/bin/pip" install --quiet --no-deps --target "$FLASHMAT_CACHE/cuda-headers-$FLASHMAT_CUDA_MM" \
    "nvidia-cuda-crt==$FLASHMAT_CUDA_MM.*" "nvidia-cuda-cccl==$FLASHMAT_CUDA_MM.*" >&2 \
    || echo "flashmat: could not fetch them; distributed training builds for the CPU (Gloo) only" >&2
fi
if [ -e "$FLASHMAT_CUDA_HEADERS/crt/host_config.h" ]; then
  export FLASHMAT_CUDA_HEADERS
else
  unset FLASHMAT_CUDA_HEADERS
fi

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
