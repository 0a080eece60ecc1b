#!/usr/bin/env bash
# Installs Debian's `chromium` when no Chromium is on PATH: tests/viewer.rs
# drives it headless (software WebGL2 via SwiftShader) to check the pages
# of `flashmat view`. Needs root and apt-get; exits 1 (with a message) when
# it cannot install. Prints the browser's path on success.
set -euo pipefail
find_browser() {
  for b in "${FLASHMAT_CHROMIUM:-}" chromium chromium-browser google-chrome; do
    [ -n "$b" ] && command -v "$b" 2>/dev/null && return 0
  done
  return 1
}
find_browser && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  export DEBIAN_FRONTEND=noninteractive
  echo "install-chromium: installing Debian's chromium (once)" >&2
  apt-get install -y -q chromium >/dev/null 2>&1 ||
    { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1; } || true
fi
find_browser && exit 0
echo "install-chromium: no chromium on PATH and it could not be installed (needs root and apt-get)" >&2
exit 1
