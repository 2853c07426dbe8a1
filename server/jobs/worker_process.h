// The job child process: `decima-server --run-job REQUEST` runs one job by calling
// decima::pipeline::RunJob, isolated from the server so that a crash or an out-of-memory fails
// that job only, and a cancel (SIGTERM, then SIGKILL) always takes effect.
//
// REQUEST is a serialized decima.worker.RunRequest (server/worker.proto): the stored,
// normalized JobSpec, the input paths, the output folder and the test fault. The child answers
// on file descriptor 3 with length-delimited decima.worker.WorkerMessage (progress..., then one
// result or error) and exits 0 (result), 2 (error) or 3 (cancelled). SIGTERM fires the
// pipeline's CancelToken.
#pragma once

#include <filesystem>

namespace decima::server {

inline constexpr int kWorkerFd = 3;
inline constexpr int kWorkerExitOk = 0;
inline constexpr int kWorkerExitError = 2;
inline constexpr int kWorkerExitCancelled = 3;

// Runs the job described by `request_file` and returns the process exit code; `fd` receives
// the messages.
int RunJobProcess(const std::filesystem::path& request_file, int fd);

}  // namespace decima::server
