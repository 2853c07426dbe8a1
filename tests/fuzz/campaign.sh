#!/usr/bin/env bash
# Runs every libFuzzer target of tests/fuzz at once, each for SECONDS, starting from the
# repository's seeds plus what earlier runs found in WORK/corpus/<target>. A crash, leak or
# timeout is written to WORK/artifacts/<target>/ and the target restarts for the rest of its
# time. Prints the CPU seconds each target got (user + system of the fuzzer processes) and what
# it found.
# Usage: tests/fuzz/campaign.sh BUILD_FUZZ_DIR SECONDS [WORK=/tmp/decima-fuzz] [TARGETS...]
# Environment:
#   BUDGET=wall (default): SECONDS of wall time; the targets share whatever CPU is idle.
#   BUDGET=cpu: each target runs until its fuzzer processes used SECONDS of CPU time, however
#     long that takes on a shared machine (the issue's "one CPU-hour per target" is BUDGET=cpu
#     with 3600).
#   NICE: the fuzzers' niceness (default 19: they yield to everything else on the machine).
set -euo pipefail
repo=$(cd "$(dirname "$0")/../.." && pwd)
build=$(cd "$1" && pwd)
seconds=$2
work=${3:-/tmp/decima-fuzz}
shift $(( $# >= 3 ? 3 : 2 ))
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(nifti metaimage nrrd volume_header dicom upload create_volume vtu transfer_function dicom_receive
           checkpoint dicom_series_check levels stream_window)
fi
declare -A max_len=([nifti]=16384 [metaimage]=16384 [nrrd]=16384 [volume_header]=16384 [dicom]=32768 [upload]=4096
                    [create_volume]=16384 [vtu]=16384 [transfer_function]=8192
                    [dicom_receive]=16384 [dicom_series_check]=32768 [levels]=8192
                    [stream_window]=8192)

budget=${BUDGET:-wall}
niceness=${NICE:-19}
case "$budget" in
  wall | cpu) ;;
  *) echo "campaign.sh: BUDGET=$budget: expected wall or cpu" >&2; exit 2 ;;
esac

# Seconds left of the target's budget: wall time to its end, or CPU seconds not yet used.
left_of() {  # end, cpu used
  if [ "$budget" = wall ]; then
    echo $(( $1 - $(date +%s) ))
  else
    awk -v s="$seconds" -v c="$2" 'BEGIN {l = s - c; print (l > int(l) ? int(l) + 1 : int(l))}'
  fi
}

# Logs of this invocation: <target>.<stamp>.log.<run>, so a campaign resumed in the same WORK
# (a CPU budget spread over several sessions) keeps the logs and times of the earlier parts.
stamp=$(date +%Y%m%d-%H%M%S)-$$

run_target() {  # target
  local t=$1 end=$(( $(date +%s) + seconds )) cpu=0 runs=0 left
  mkdir -p "$work/corpus/$t" "$work/artifacts/$t" "$work/logs"
  local log="$work/logs/$t.$stamp"
  # At most 1000 runs: a fuzzer that cannot start would otherwise spin on a CPU budget.
  while left=$(left_of "$end" "$cpu") && [ "$left" -gt 0 ] && [ "$runs" -lt 1000 ]; do
    runs=$(( runs + 1 ))
    # /usr/bin/time reports the fuzzer's own user + system CPU seconds. With BUDGET=cpu the
    # wall limit is the CPU still owed: on a shared machine the run ends early and the loop
    # goes on with what is left.
    /usr/bin/time -f "%U %S" -o "$log.time.$runs" \
      nice -n "$niceness" "$build/tests/fuzz/${t}_fuzz" -max_total_time="$left" -rss_limit_mb=2048 \
        -timeout=10 -max_len="${max_len[$t]}" -print_final_stats=1 \
        -artifact_prefix="$work/artifacts/$t/" "$work/corpus/$t" "$repo/tests/fuzz/corpus/$t" \
        >"$log.log.$runs" 2>&1 || true
    # The last line: /usr/bin/time writes "Command exited with non-zero status N" before it.
    # A run whose time file is empty (time itself was killed) adds nothing instead of resetting
    # the count.
    cpu=$(tail -n 1 "$log.time.$runs" |
          awk -v c="$cpu" '$1 ~ /^[0-9.]+$/ {c += $1 + $2} END {print c + 0}')
  done
  local execs
  execs=$(grep -h "stat::number_of_executed_units" "$log.log."* |
          awk '{s += $2} END {print s + 0}')
  echo "{\"target\": \"$t\", \"cpu_seconds\": $cpu, \"runs\": $runs, \"execs\": $execs," \
       "\"corpus_files\": $(ls "$work/corpus/$t" | wc -l)," \
       "\"artifacts\": $(ls "$work/artifacts/$t" | wc -l)}" | tee "$log.summary"
}

for t in "${targets[@]}"; do
  if [ -z "${max_len[$t]:-}" ]; then
    echo "campaign.sh: unknown target '$t' (known: ${!max_len[*]})" >&2
    exit 2
  fi
done
for t in "${targets[@]}"; do run_target "$t" & done
wait
