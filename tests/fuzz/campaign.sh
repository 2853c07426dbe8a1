#!/usr/bin/env bash
# Runs every libFuzzer target of tests/fuzz at once, each for SECONDS of wall time at nice 19
# (they share whatever CPU is idle, fairly among themselves), starting from the repository's
# seeds plus what earlier runs found in WORK/corpus/<target>. A crash, leak or timeout is
# written to WORK/artifacts/<target>/ and the target restarts for the rest of its time. Prints
# the CPU seconds each target got (user + system of the fuzzer processes) and what it found.
# Usage: tests/fuzz/campaign.sh BUILD_FUZZ_DIR SECONDS [WORK=/tmp/decima-fuzz] [TARGETS...]
set -euo pipefail
repo=$(cd "$(dirname "$0")/../.." && pwd)
build=$(cd "$1" && pwd)
seconds=$2
work=${3:-/tmp/decima-fuzz}
shift $(( $# >= 3 ? 3 : 2 ))
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(nifti metaimage nrrd dicom upload create_volume vtu transfer_function)
fi
declare -A max_len=([nifti]=16384 [metaimage]=16384 [nrrd]=16384 [dicom]=32768 [upload]=4096
                    [create_volume]=16384 [vtu]=16384 [transfer_function]=8192)

run_target() {  # target
  local t=$1 end=$(( $(date +%s) + seconds )) cpu=0 runs=0
  mkdir -p "$work/corpus/$t" "$work/artifacts/$t" "$work/logs"
  while [ "$(date +%s)" -lt "$end" ]; do
    local left=$(( end - $(date +%s) ))
    runs=$(( runs + 1 ))
    # /usr/bin/time reports the fuzzer's own user + system CPU seconds.
    /usr/bin/time -f "%U %S" -o "$work/logs/$t.time.$runs" \
      nice -n 19 "$build/tests/fuzz/${t}_fuzz" -max_total_time="$left" -rss_limit_mb=2048 \
        -timeout=10 -max_len="${max_len[$t]}" -print_final_stats=1 \
        -artifact_prefix="$work/artifacts/$t/" "$work/corpus/$t" "$repo/tests/fuzz/corpus/$t" \
        >"$work/logs/$t.log.$runs" 2>&1 || true
    # The last line: /usr/bin/time writes "Command exited with non-zero status N" before it.
    cpu=$(tail -n 1 "$work/logs/$t.time.$runs" | awk -v c="$cpu" '{print c + $1 + $2}')
  done
  local execs
  execs=$(grep -h "stat::number_of_executed_units" "$work/logs/$t.log."* |
          awk '{s += $2} END {print s + 0}')
  echo "{\"target\": \"$t\", \"cpu_seconds\": $cpu, \"runs\": $runs, \"execs\": $execs," \
       "\"corpus_files\": $(ls "$work/corpus/$t" | wc -l)," \
       "\"artifacts\": $(ls "$work/artifacts/$t" | wc -l)}" | tee "$work/logs/$t.summary"
}

for t in "${targets[@]}"; do run_target "$t" & done
wait
