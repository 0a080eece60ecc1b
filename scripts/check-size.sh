#!/usr/bin/env bash
# Fails when the tracked tree (what `git ls-files` lists) grows past
# 32 MiB, naming the largest files. A GPU job receives at most 64 MiB: the
# tree, the release binary (about 9 MB) and a model to resume from (11 MB).
set -euo pipefail
cd "$(dirname "$0")/.."
LIMIT=$((32 * 1024 * 1024))
total=$(git ls-files -z | xargs -0 du -cb | tail -n 1 | cut -f1)
if [ "$total" -gt "$LIMIT" ]; then
  echo "tracked tree is $total bytes, over the limit of $LIMIT (32 MiB); the largest files:" >&2
  git ls-files -z | xargs -0 du -b | sort -rn | head -n 10 >&2
  exit 1
fi
echo "tracked tree: $total bytes of $LIMIT ($((100 * total / LIMIT))%)"
