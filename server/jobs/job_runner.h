// Runs one claimed job to its recorded outcome, in four steps:
//   Prepare  a fresh jobs/<id>/attempts/<epoch>/out/, the volumes resolved to files,
//   jobs/<id>/request.pb; Spawn    the child `decima-server --run-job jobs/<id>/request.pb`
//   (child_process.h); Relay    its length-delimited messages (worker_protocol.h) into the store as
//   progress
//            events, renewing the lease every third of it and polling the store for a cancel
//            that arrived through another replica; a stop request terminates the child;
//   Outcome  SUCCEEDED (artifacts checked to be plain files in out/ and hashed), FAILED (the
//            pipeline's status code and message, or how the child died and the last log line),
//            CANCELLED, QUEUED again (server shutdown), or nothing when the lease was lost (the
//            job belongs to another claim now).
// Every store write presents the claim's lease, so a runner that lost its lease changes nothing.
// Thread-safety: Run may be called from several threads at once (one job each).
#pragma once

#include <atomic>
#include <chrono>
#include <filesystem>
#include <string>

#include "server/files/data_dir.h"
#include "server/store/job_store.h"

namespace decima::server {

struct JobRunnerOptions {
  DataDir data_dir{""};
  std::filesystem::path worker_exe;    // the binary run as `--run-job` (decima-server itself)
  int64_t lease_ms = 15000;            // renewed every lease_ms / 3
  int64_t cancel_grace_ms = 500;       // SIGTERM -> SIGKILL
  int64_t progress_interval_ms = 100;  // progress events stored at most this often per stage
  // The most one job may use (job_memory.h); 0 = DefaultJobMemoryCapBytes(). The child runs
  // under RLIMIT_AS = JobAddressSpaceLimitBytes(estimate, cap), except in sanitizer builds
  // (their shadow memory needs terabytes of address space).
  int64_t worker_memory_mb = 0;
  bool allow_faults = false;  // hand jobs/<id>/fault to the child (tests only)
};

// Set from other threads to stop a running job early.
struct StopFlags {
  std::atomic<bool> cancel{false};   // the user cancelled: record CANCELLED
  std::atomic<bool> requeue{false};  // the server drains: give the job back to the queue
  // While the server drains: when (steady clock, ms since its epoch) the job will be stopped and
  // requeued unless it finished; 0 when not draining. The runner reports the time left.
  std::atomic<int64_t> drain_deadline_ms{0};
};

class JobRunner {
 public:
  JobRunner(JobStore* store, JobRunnerOptions options);

  // Runs `claim` and records its outcome; returns when the child is reaped.
  void Run(const Claim& claim, StopFlags& stop);

 private:
  struct ChildEnd;
  struct Prepared {
    std::filesystem::path request;
    int64_t memory_limit_bytes = 0;  // 0: none
  };
  absl::StatusOr<Prepared> Prepare(const v1::Job& job, int64_t epoch);
  ChildEnd Relay(class ChildProcess& child, const Lease& lease, StopFlags& stop);
  void RecordOutcome(const v1::Job& job, const Lease& lease, const ChildEnd& end,
                     const StopFlags& stop, double seconds);
  void Fail(const Lease& lease, absl::StatusCode code, const std::string& message, double seconds);

  JobStore* store_;
  const JobRunnerOptions options_;
};

}  // namespace decima::server
