# Source this file: sets up (once) what the Mitsuba 3 plugin (python/flashmat/mitsuba)
# needs on top of flashmat's Python environment (scripts/env.sh):
#   - mitsuba 3 (brings drjit) and pytest in $FLASHMAT_VENV
#   - LLVM >= 16 for Dr.Jit's LLVM backend (the distribution's LLVM 15 crashes it):
#     libllvm19 from apt, exported as DRJIT_LIBLLVM_PATH.
# Idempotent: installs only what is missing.
_mitsuba_env_dir="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
. "$_mitsuba_env_dir/env.sh" || return 1 2>/dev/null || exit 1

flashmat_find_llvm() {
  local f
  for f in /usr/lib/llvm-19/lib/libLLVM.so.1 /usr/lib/llvm-19/lib/libLLVM.so /usr/lib/llvm-19/lib/libLLVM-19.so \
           /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 /usr/lib/x86_64-linux-gnu/libLLVM-19.so.1 /usr/lib/x86_64-linux-gnu/libLLVM-19.so; do
    [ -e "$f" ] && { echo "$f"; return 0; }
  done
  ls /usr/lib/llvm-19/lib/libLLVM*.so* 2>/dev/null | head -n1
}

flashmat_setup_mitsuba() {
  if [ -z "$(flashmat_find_llvm)" ]; then
    echo "flashmat: installing libllvm19 for Dr.Jit (apt-get, one-time)" >&2
    if [ "$(id -u)" = 0 ]; then
      apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null || return 1
    else
      sudo apt-get update -qq >/dev/null && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null || return 1
    fi
  fi
  if ! "$FLASHMAT_VENV/bin/python" -c "import mitsuba, drjit, pytest" 2>/dev/null; then
    echo "flashmat: installing mitsuba 3 and pytest into $FLASHMAT_VENV (one-time)" >&2
    "$FLASHMAT_VENV/bin/pip" install --quiet "mitsuba>=3.5,<4" pytest || return 1
  fi
}

flashmat_setup_mitsuba || { echo "flashmat: could not set up Mitsuba 3" >&2; return 1 2>/dev/null || exit 1; }
DRJIT_LIBLLVM_PATH="$(flashmat_find_llvm)"
export DRJIT_LIBLLVM_PATH
