#include "server/jobs/worker_pool.h"

#include "spdlog/spdlog.h"

namespace decima::server {

WorkerPool::WorkerPool(JobStore* store, WorkerPoolOptions options)
    : store_(store), options_(std::move(options)), runner_(store, options_.runner) {}

WorkerPool::~WorkerPool() { Drain(std::chrono::milliseconds(0)); }

void WorkerPool::Start() {
  for (int i = 0; i < options_.workers; ++i) slots_.push_back(std::make_unique<Slot>());
  for (int i = 0; i < options_.workers; ++i) threads_.emplace_back([this, i] { Loop(i); });
}

void WorkerPool::Notify() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    ++wakeups_;
  }
  cv_.notify_all();
}

void WorkerPool::Cancel(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mu_);
  for (auto& s : slots_) {
    if (s->job_id == job_id) s->stop.cancel = true;
  }
}

void WorkerPool::Drain(std::chrono::milliseconds grace) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (stopping_ && threads_.empty()) return;
    stopping_ = true;
  }
  cv_.notify_all();
  const auto deadline = std::chrono::steady_clock::now() + grace;
  {
    std::lock_guard<std::mutex> lock(mu_);
    const int64_t ms =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline.time_since_epoch()).count();
    for (auto& s : slots_) s->stop.drain_deadline_ms = ms;
  }
  while (running_.load() > 0 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto& s : slots_) s->stop.requeue = true;
  }
  for (auto& t : threads_) t.join();
  threads_.clear();
}

void WorkerPool::Loop(int index) {
  Slot& slot = *slots_[index];
  for (;;) {
    int64_t seen;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (stopping_) return;
      seen = wakeups_;
    }
    auto claimed = store_->ClaimNext(options_.owner, options_.runner.lease_ms);
    if (!claimed.ok()) {
      spdlog::error("worker {}: claiming a job: {}", index, claimed.status().ToString());
    } else if (claimed->has_value()) {
      {
        std::lock_guard<std::mutex> lock(mu_);
        slot.job_id = (*claimed)->lease.job_id;
        slot.stop.cancel = false;
        // A drain that began while claiming still applies: requeue is only ever set, here kept.
        slot.stop.requeue = stopping_;
      }
      running_.fetch_add(1);
      runner_.Run(**claimed, slot.stop);
      running_.fetch_sub(1);
      {
        std::lock_guard<std::mutex> lock(mu_);
        slot.job_id.clear();
      }
      continue;
    }
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait_for(lock, std::chrono::seconds(1), [&] { return stopping_ || wakeups_ != seen; });
  }
}

}  // namespace decima::server
