// The worker pool: N threads, each claiming the oldest queued job with a lease and handing it
// to the JobRunner (job_runner.h), which runs it in a child process and records the outcome.
// Cancel and graceful drain reach a running job through its slot's StopFlags. Drain: stop
// claiming, let running jobs finish until a deadline, then stop them and give them back to the
// queue.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "server/jobs/job_runner.h"
#include "server/store/job_store.h"

namespace decima::server {

struct WorkerPoolOptions {
  int workers = 1;
  std::string owner;  // lease owner id, unique per server process
  JobRunnerOptions runner;
};

class WorkerPool {
 public:
  WorkerPool(JobStore* store, WorkerPoolOptions options);
  ~WorkerPool();

  void Start();
  // A job was queued: wake an idle worker.
  void Notify();
  // Stops the child running `job_id` in this process, if any (the store already holds the
  // cancel request; runners also poll it, for cancels that came through another replica).
  void Cancel(const std::string& job_id);
  // Stops claiming; waits up to `grace` for running jobs, then stops and requeues the rest;
  // joins the threads.
  void Drain(std::chrono::milliseconds grace);

  int running() const { return running_.load(); }

 private:
  struct Slot {
    std::string job_id;  // guarded by WorkerPool::mu_
    StopFlags stop;
  };
  void Loop(int index);

  JobStore* store_;
  const WorkerPoolOptions options_;
  JobRunner runner_;
  std::vector<std::thread> threads_;
  std::vector<std::unique_ptr<Slot>> slots_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  int64_t wakeups_ ABSL_GUARDED_BY(mu_) = 0;
  std::atomic<int> running_{0};
};

}  // namespace decima::server
