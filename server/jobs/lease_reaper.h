// Lease expiry on its own timer: every `period` the reaper gives lapsed leases back to the queue
// (JobStore::RecoverLeases(all=false)) and tells `on_requeued` so idle workers wake. Each
// replica of a shared store runs one; a lease lapses only when its holder stopped renewing
// (dead, paused, cut off), and its late writes are then refused by the lease's epoch.
// Thread-safety: Start and Stop from one thread; the callback runs on the reaper's thread.
#pragma once

#include <chrono>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "server/store/job_store.h"

namespace decima::server {

class LeaseReaper {
 public:
  LeaseReaper(JobStore* store, std::chrono::milliseconds period, int max_attempts,
              std::function<void()> on_requeued);
  ~LeaseReaper();  // Stop()

  void Start();
  // Returns after the current sweep, if any, ended. Idempotent.
  void Stop();
  // One sweep now, on the caller's thread (tests). The number of jobs it re-queued or failed.
  absl::StatusOr<size_t> SweepOnce();

 private:
  void Loop();

  JobStore* store_;
  const std::chrono::milliseconds period_;
  const int max_attempts_;
  std::function<void()> on_requeued_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool stop_ ABSL_GUARDED_BY(mu_) = false;
  std::thread thread_;
};

}  // namespace decima::server
