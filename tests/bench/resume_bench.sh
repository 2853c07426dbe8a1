#!/usr/bin/env bash
# The figure of issue 35 part 6: a job stopped by SIGTERM at a stage boundary resumes and
# finishes in at most 1.2x the uninterrupted time. Real processes on loopback: one decima-server
# (--allow-faults, one worker) on a scratch data dir and the decima CLI.
#
#   tests/bench/resume_bench.sh BUILD_DIR VOLUME [BOUNDARY...]
#
# BOUNDARY is segment and/or simplify (default both). For each: the job is submitted with the
# test fault pause-after:BOUNDARY; once it pauses (its checkpoint saved), the server gets SIGTERM
# (drain 1 s, the job is requeued) and is started again on the same data dir; the job resumes.
# The resumed time is (submit -> paused) + (restarted server healthy -> SUCCEEDED): the job's
# own time, without the test pause and the server's restart. The uninterrupted time is
# submit -> SUCCEEDED of the same job without a fault. Job states are polled every 0.2 s.
# Prints one JSON object, with the pipeline's own stage seconds of the uninterrupted job and of
# each resumed attempt (a resumed stage's seconds are the time to read its checkpoint), which
# show the resume's cost apart from the machine's load.
set -euo pipefail
build=${1:?usage: resume_bench.sh BUILD_DIR VOLUME [BOUNDARY...]}
volume=${2:?usage: resume_bench.sh BUILD_DIR VOLUME [BOUNDARY...]}
shift 2
boundaries=("$@")
[[ ${#boundaries[@]} -gt 0 ]] || boundaries=(segment simplify)
server_bin=$build/server/decima-server
cli_bin=$build/client/decima
scratch=$(mktemp -d /tmp/decima-resume-bench.XXXXXX)
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
addr=127.0.0.1:$port
server_pid=

stop_server() {
  if [[ -n $server_pid ]]; then
    kill -TERM "$server_pid" 2>/dev/null || true
    wait "$server_pid" 2>/dev/null || true
    server_pid=
  fi
}
trap 'stop_server; rm -rf "$scratch"' EXIT

start_server() {
  "$server_bin" --data-dir "$scratch/data" --listen "$addr" --workers 1 --allow-faults \
    --drain-seconds 1 >>"$scratch/server.log" 2>&1 &
  server_pid=$!
  for _ in $(seq 1 300); do
    "$cli_bin" --server "$addr" --timeout 2 health >/dev/null 2>&1 && return 0
    sleep 0.1
  done
  echo "decima-server did not become healthy; log: $scratch/server.log" >&2
  exit 1
}

now() { date +%s.%N; }

# Prints the job's state and progress message, tab-separated.
job_state() {
  "$cli_bin" --server "$addr" status "$1" -o json |
    python3 -c 'import json,sys; j=json.load(sys.stdin); print(j.get("state",""), j.get("progress",{}).get("message",""), sep="\t")'
}

# Waits (at most 1 h) until the job's state or message matches the regex $2.
wait_for() {
  local deadline=$(($(date +%s) + 3600))
  while (($(date +%s) < deadline)); do
    local s
    s=$(job_state "$1")
    [[ $s =~ $2 ]] && return 0
    [[ $s =~ ^(FAILED|CANCELLED) ]] && { echo "job $1: $s" >&2; exit 1; }
    sleep 0.2
  done
  echo "job $1: timed out waiting for /$2/" >&2
  exit 1
}

submit() { "$cli_bin" --server "$addr" submit "$volume" "$@" | head -1; }

start_server
t0=$(now)
job=$(submit)
wait_for "$job" '^SUCCEEDED'
uninterrupted=$(python3 -c "print(round($(now) - $t0, 2))")
# The uninterrupted job's own figures: pipeline seconds and peak memory (issue 30).
memory=$("$cli_bin" --server "$addr" status "$job" -o json | python3 -c '
import json,sys
m=json.loads(json.load(sys.stdin).get("metrics_json","{}"))
print(json.dumps({"pipeline_s": m["seconds"]["total"], "seconds": m["seconds"],
                  "peak_rss_mb": m.get("peak_rss_mb"),
                  "stage_peak_rss_mb": m.get("stage_peak_rss_mb")}))')

results=""
for b in "${boundaries[@]}"; do
  t0=$(now)
  job=$(submit --fault "pause-after:$b")
  wait_for "$job" "paused after the $b checkpoint"
  before=$(python3 -c "print($(now) - $t0)")
  stop_server
  start_server
  t1=$(now)
  wait_for "$job" '^SUCCEEDED'
  after=$(python3 -c "print($(now) - $t1)")
  resumed=$("$cli_bin" --server "$addr" status "$job" -o json | python3 -c '
import json,sys
j=json.load(sys.stdin)
m=json.loads(j.get("metrics_json","{}"))
print(json.dumps({"resumed_stages": m.get("resumed_stages"), "seconds": m.get("seconds")}))')
  results+=$(python3 -c "
import json
before, after, base = $before, $after, $uninterrupted
print(json.dumps({'boundary': '$b', 'until_paused_s': round(before, 2),
                  'after_restart_s': round(after, 2), 'resumed_total_s': round(before + after, 2),
                  'ratio': round((before + after) / base, 3), 'resumed_job': $resumed}) + ',')")
done
python3 -c "
import json
print(json.dumps({'volume': '$volume', 'uninterrupted_s': $uninterrupted,
                  'uninterrupted_job': $memory, 'sigterm_at': [${results%,}]}, indent=2))"
