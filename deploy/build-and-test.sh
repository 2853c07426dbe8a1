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
# ccache: a rerun compiles only what changed. No working directory in the hash: Makefiles run the
# compiler from each target's folder.
export CCACHE_NOHASHDIR=1
launcher=(-DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
# CMake's default generator (Unix Makefiles), the one `cmake -S . -B b && cmake --build b` uses:
# building everything with it is also the check that the plain CMake habit works (Makefiles,
# unlike Ninja, do not create the folders of generated files; issue 33). A folder configured
# earlier keeps its generator (-G is given only to a new one).
generator=()
[ -f "$build_dir/CMakeCache.txt" ] || generator=(-G "Unix Makefiles")
# -g1 (line tables): what a failing test's stack trace needs. Full -g made the gRPC-heavy
# translation units compile and link far slower (server_main.cc: 163 s against 266 s on the
# loaded machine) for variable information nobody reads in a test run; configure your own
# build folder with -g to debug.
cmake -S . -B "$build_dir" "${generator[@]}" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DDECIMA_WERROR=ON \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O2 -g1 -DNDEBUG" \
  -DCMAKE_C_FLAGS_RELWITHDEBINFO="-O2 -g1 -DNDEBUG" \
  -DDECIMA_SANITIZE="${DECIMA_SANITIZE:-OFF}" "${launcher[@]}"
cmake --build "$build_dir" -j "$jobs"
ctest --test-dir "$build_dir" --output-on-failure -j "$jobs" --timeout 900
