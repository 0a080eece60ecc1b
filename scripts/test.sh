#!/usr/bin/env bash
# Sets everything up (Python environment with PyTorch, Rust build) and runs
# every test of the project.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
cargo test --all-targets 2>&1
