#!/usr/bin/env bash
# The sanitizer half of CI (.ci/run calls it after build-and-test.sh):
#  - build-asan: AddressSanitizer + UndefinedBehaviorSanitizer, every unit test (ctest -L unit);
#  - build-tsan: ThreadSanitizer, the server and client tests (-L "server|client") and the service
#    end-to-end suites (ServiceE2E, HardeningE2E),
#    with tests/tsan.supp for the Debian libraries that are not instrumented.
# Each in its own build folder. A report fails the run even when it came from a child process a
# test started (decima-server, its job processes, the CLI), whose exit code the test may not
# look at: every report is written under <build>/sanitizer-logs/ and any file there fails.
# Environment: JOBS (default: all cores), ASAN_BUILD_DIR / TSAN_BUILD_DIR.
set -euo pipefail
cd "$(dirname "$0")/.."
jobs=${JOBS:-$(nproc)}
launcher=()
if command -v ccache >/dev/null; then
  launcher=(-DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
fi

# -O0 -g1 for everything but the core: line tables are all a report's stack needs, and the tests,
# the server and the client compile about twice as fast unoptimised (job_store_test.cc under ASan:
# 10 s against 27 s at -O2), which is most of this script's time. The core keeps -O2
# (core/CMakeLists.txt), so the jobs the tests run are not slowed down. (-O1 made GCC 12 report
# false -Wstringop-overflow and -Warray-bounds errors in nrrd_test under ASan.)
configure() {  # build dir, sanitizer
  cmake -S . -B "$1" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DDECIMA_WERROR=ON \
    -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O0 -g1 -DNDEBUG" \
    -DCMAKE_C_FLAGS_RELWITHDEBINFO="-O0 -g1 -DNDEBUG" \
    -DDECIMA_SANITIZE="$2" -DDECIMA_BUILD_BENCHMARKS=OFF "${launcher[@]}"
}

# Fails if a sanitizer wrote a report into $1 (printing them).
check_logs() {
  if compgen -G "$1/*" >/dev/null; then
    echo "sanitizer reports in $1:" >&2
    cat "$1"/* >&2
    return 1
  fi
}

run_ctest() {  # build dir, label regex
  ctest --test-dir "$1" -L "$2" --output-on-failure -j "$jobs" --timeout 900
}

status=0
# Prints how long each phase took, so a CI log shows where the sanitizer half's time goes.
phase_start=$SECONDS
phase() {  # name
  echo "sanitizer-tests: $1 took $((SECONDS - phase_start)) s"
  phase_start=$SECONDS
}

asan=${ASAN_BUILD_DIR:-build-asan}
configure "$asan" address
# Only the executables of the unit label (tests/CMakeLists.txt's per-label targets).
cmake --build "$asan" -j "$jobs" --target tests-unit
phase "asan build"
asan_logs=$PWD/$asan/sanitizer-logs
rm -rf "$asan_logs" && mkdir -p "$asan_logs"
LSAN_OPTIONS="suppressions=$PWD/tests/lsan.supp:print_suppressions=0" \
ASAN_OPTIONS="log_path=$asan_logs/asan:detect_leaks=1:strict_string_checks=1" \
UBSAN_OPTIONS="log_path=$asan_logs/ubsan:print_stacktrace=1:halt_on_error=1" \
  run_ctest "$asan" unit || status=1
check_logs "$asan_logs" || status=1
phase "asan tests"

tsan=${TSAN_BUILD_DIR:-build-tsan}
configure "$tsan" thread
# The executables of the server and client labels and the two e2e suites below (their
# add_dependencies bring decima-server and decima).
cmake --build "$tsan" -j "$jobs" --target tests-server tests-client service_e2e_test \
  hardening_e2e_test
phase "tsan build"
tsan_logs=$PWD/$tsan/sanitizer-logs
rm -rf "$tsan_logs" && mkdir -p "$tsan_logs"
# OMP_NUM_THREADS=1: libgomp is not instrumented, its hand-offs would be reported as races.
TSAN_OPTIONS="suppressions=$PWD/tests/tsan.supp:log_path=$tsan_logs/tsan:second_deadlock_stack=1" \
OMP_NUM_THREADS=1 run_ctest "$tsan" "server|client" || status=1
phase "tsan server and client tests"
# The end-to-end suites whose subject is concurrency in the service (queue, leases, watchers,
# restarts, uploads); the CLI, README, PACS and scale-out suites run in the plain build, where
# the job pipeline is not slowed down eight-fold.
TSAN_OPTIONS="suppressions=$PWD/tests/tsan.supp:log_path=$tsan_logs/tsan:second_deadlock_stack=1" \
OMP_NUM_THREADS=1 ctest --test-dir "$tsan" -R '^(ServiceE2E|HardeningE2E)\.' --output-on-failure \
  -j "$jobs" --timeout 900 || status=1
check_logs "$tsan_logs" || status=1
phase "tsan e2e tests"

exit $status
