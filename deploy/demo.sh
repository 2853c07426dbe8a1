#!/usr/bin/env bash
# The README's main command: builds Decima, starts decima-server on its embedded defaults
# (loopback, SQLite job store and blobs under a temp data dir), submits the real Colin27 T1 MRI
# that Debian's mricron-data package installs, watches the job, and downloads the mesh, the
# label map, the rendered images and metrics.json into OUT_DIR (default ./decima-demo).
set -euo pipefail
cd "$(dirname "$0")/.."
out_dir=$(realpath -m "${1:-decima-demo}")
bash deploy/install-deps.sh
build_dir=${BUILD_DIR:-build}
# A build folder made earlier (by deploy/build-and-test.sh, say) keeps its generator and flags.
if [ -f "$build_dir/CMakeCache.txt" ]; then
  cmake -S . -B "$build_dir" >/dev/null
else
  cmake -S . -B "$build_dir" -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
fi
cmake --build "$build_dir" -j "$(nproc)" --target decima decima-server

input=/usr/share/mricron/templates/ch2.nii.gz
[ -f "$input" ] || { echo "demo: $input missing after installing mricron-data" >&2; exit 1; }

data_dir=$(mktemp -d -t decima-demo-data.XXXXXX)
port=${DECIMA_DEMO_PORT:-50151}
"$build_dir/server/decima-server" --listen "127.0.0.1:$port" --data-dir "$data_dir" &
server_pid=$!
trap 'kill "$server_pid" 2>/dev/null; wait "$server_pid" 2>/dev/null; rm -rf "$data_dir"' EXIT

client="$build_dir/client/decima"
for _ in $(seq 1 100); do
  "$client" --server "127.0.0.1:$port" health >/dev/null 2>&1 && break
  sleep 0.1
done
"$client" --server "127.0.0.1:$port" submit "$input" --regions 3 --reduction 0.5 --watch --out "$out_dir"
echo "demo: results in $out_dir"
ls -l "$out_dir"
