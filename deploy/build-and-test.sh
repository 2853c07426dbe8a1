#!/usr/bin/env bash
# The README's test command: installs the Debian packages, configures, builds everything
# (warnings as errors) and runs every test through ctest. Exits non-zero on any failure.
# Environment: BUILD_DIR (default build), DECIMA_SANITIZE=ON for an ASan+UBSan build (thread: TSan),
# JOBS (default: all cores).
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
build_dir=${BUILD_DIR:-build}
jobs=${JOBS:-$(nproc)}
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DDECIMA_WERROR=ON \
  -DDECIMA_SANITIZE="${DECIMA_SANITIZE:-OFF}"
cmake --build "$build_dir" -j "$jobs"
ctest --test-dir "$build_dir" --output-on-failure -j "$jobs" --timeout 900
