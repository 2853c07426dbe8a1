// The worker pool: N threads, each claiming the oldest queued job with a lease, running it in a
// child process (worker_process.h), relaying its progress into the job store, renewing the
// lease, and recording the outcome. Cancel signals the child (SIGTERM, SIGKILL after a grace
// period); a child that dies by a signal or exits without a result fails its job with the
// reason. Graceful drain: stop claiming, let running jobs finish until a deadline, then stop
// them and give them back to the queue.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "server/blob_store.h"
#include "server/data_dir.h"
#include "server/job_store.h"

namespace decima::server {

struct WorkerPoolOptions {
  int workers = 1;
  DataDir data_dir{""};                // jobs/<id>/ and volumes/<id>/ live here
  std::filesystem::path worker_exe;    // the binary run as `--run-job` (decima-server itself)
  std::string owner;                   // lease owner id, unique per server process
  int64_t lease_ms = 15000;            // renewed every lease_ms / 3
  int max_attempts = 3;                // claims before a job whose worker is lost fails
  int64_t cancel_grace_ms = 500;       // SIGTERM -> SIGKILL
  int64_t progress_interval_ms = 100;  // progress events stored at most this often per stage
  int64_t worker_memory_mb = 0;        // RLIMIT_AS of the child, 0 = unlimited
  bool allow_faults = false;           // hand jobs/<id>/fault to the child (tests only)
};

class WorkerPool {
 public:
  WorkerPool(JobStore* store, WorkerPoolOptions options);
  ~WorkerPool();

  void Start();
  // A job was queued: wake an idle worker.
  void Notify();
  // Signals the child running `job_id` in this process, if any (the store already holds the
  // cancel request; workers also poll it, for cancels that came through another replica).
  void Cancel(const std::string& job_id);
  // Stops claiming; waits up to `grace` for running jobs, then stops and requeues the rest;
  // joins the threads.
  void Drain(std::chrono::milliseconds grace);

  int running() const { return running_.load(); }

 private:
  struct Slot {
    std::string job_id;
    std::atomic<bool> cancel{false};
    std::atomic<bool> requeue{false};
  };
  void Loop(int index);
  void RunOne(Slot& slot, const v1::Job& job);

  JobStore* store_;
  const WorkerPoolOptions options_;
  std::vector<std::thread> threads_;
  std::vector<std::unique_ptr<Slot>> slots_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  int64_t wakeups_ ABSL_GUARDED_BY(mu_) = 0;
  std::atomic<int> running_{0};
};

}  // namespace decima::server
