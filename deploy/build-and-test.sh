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
# ccache: objects compiled once are reused by the second build below and by the next run.
# Absolute paths (no base dir) and no working directory in the hash: Ninja runs the compiler
# from the build folder, Makefiles from each target's folder, so paths made relative to it
# differ between the two builds and nothing would be shared. The objects that include
# generated headers (proto/, server/, client/) still differ by their build folder.
export CCACHE_BASEDIR="" CCACHE_NOHASHDIR=1
launcher=(-DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DDECIMA_WERROR=ON \
  -DDECIMA_SANITIZE="${DECIMA_SANITIZE:-OFF}" "${launcher[@]}"
cmake --build "$build_dir" -j "$jobs"
# The plain CMake habit works too: the default generator (Unix Makefiles), which unlike Ninja
# does not create the folders of generated files. Only the server and the CLI, to keep it cheap.
if [ "${DECIMA_SANITIZE:-OFF}" = "OFF" ]; then
  cmake -S . -B "$build_dir-make" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DDECIMA_WERROR=ON \
    "${launcher[@]}"
  cmake --build "$build_dir-make" -j "$jobs" --target decima-server decima
fi
ctest --test-dir "$build_dir" --output-on-failure -j "$jobs" --timeout 900
