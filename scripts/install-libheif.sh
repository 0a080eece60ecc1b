#!/usr/bin/env bash
# Installs Debian's `libheif-dev` (and `pkg-config`) when pkg-config finds
# no libheif 1.14 or newer: the `heif` cargo feature (HEIC/HEIF and AVIF
# photos, src/io/heif.rs) links it. On Debian 12 (libheif 1.15) the HEVC
# and AV1 decoders and encoders are built in; where libheif has them as
# plugins (Debian 13 and later) those are installed too. Needs root and
# apt-get; exits 1 (with a message) when it cannot install. Prints the
# libheif version on success.
set -euo pipefail
found() {
  command -v pkg-config >/dev/null 2>&1 && pkg-config --atleast-version=1.14 libheif 2>/dev/null && pkg-config --modversion libheif
}
found && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  export DEBIAN_FRONTEND=noninteractive
  echo "install-libheif: installing Debian's libheif-dev (once)" >&2
  packages=(libheif-dev pkg-config)
  install() {
    local extra=()
    # Plugin packages exist from libheif 1.16 on: decoders (libde265, dav1d)
    # for reading, encoders (x265, aom) for the tests' own photos.
    for p in libheif-plugin-libde265 libheif-plugin-dav1d libheif-plugin-x265 libheif-plugin-aomenc; do
      apt-cache show "$p" >/dev/null 2>&1 && extra+=("$p")
    done
    apt-get install -y -q "${packages[@]}" ${extra[@]+"${extra[@]}"} >/dev/null 2>&1
  }
  install || { apt-get update -q >/dev/null 2>&1 && install; } || true
fi
found && exit 0
echo "install-libheif: no libheif 1.14 or newer for pkg-config, and it could not be installed (needs root and apt-get; or install libheif-dev yourself)" >&2
exit 1
