// The job child process: `decima-server --run-job DIR --input PATH [--label-map PATH]
// [--fault F]` runs one
// job by calling decima::pipeline::RunJob, isolated from the server so that a crash or an
// out-of-memory fails that job only, and a cancel (SIGTERM, then SIGKILL) always takes effect.
//
// Protocol to the parent, on file descriptor 3: JSON lines
//   {"type":"progress","stage":S,"fraction":F,"message":M,"metrics":{name:value,...}}
//   {"type":"result","artifacts":[{"name":N,"path":P,"size":B}],"metrics_json":J}
//   {"type":"error","code":C,"message":M}        (C: an absl/gRPC status code)
// then exit 0 (result), 2 (error) or 3 (cancelled). Anything else (a signal, another code, no
// final line) is a crash. DIR/spec.pb holds the serialized decima.v1.JobSpec; artifacts go to
// DIR/out. SIGTERM fires the pipeline's CancelToken.
#pragma once

#include <filesystem>
#include <string>

namespace decima::server {

inline constexpr int kWorkerFd = 3;
inline constexpr int kWorkerExitOk = 0;
inline constexpr int kWorkerExitError = 2;
inline constexpr int kWorkerExitCancelled = 3;

// Runs the job and returns the process exit code. `fd` receives the protocol lines. `fault` is
// the test seam of faults.h ("" in production).
int RunJobProcess(const std::filesystem::path& job_dir, const std::filesystem::path& input,
                  const std::filesystem::path& label_map, const std::string& fault, int fd);

}  // namespace decima::server
