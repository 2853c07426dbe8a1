#include "server/jobs/lease_reaper.h"

#include "spdlog/spdlog.h"

namespace decima::server {

LeaseReaper::LeaseReaper(JobStore* store, std::chrono::milliseconds period, int max_attempts,
                         std::function<void()> on_requeued)
    : store_(store),
      period_(period),
      max_attempts_(max_attempts),
      on_requeued_(std::move(on_requeued)) {}

LeaseReaper::~LeaseReaper() { Stop(); }

void LeaseReaper::Start() {
  thread_ = std::thread([this] { Loop(); });
}

void LeaseReaper::Stop() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

absl::StatusOr<size_t> LeaseReaper::SweepOnce() {
  auto r = store_->RecoverLeases(/*all=*/false, max_attempts_);
  if (!r.ok()) return r.status();
  for (const auto& id : r->requeued) spdlog::info("job {} QUEUED again (its lease lapsed)", id);
  for (const auto& id : r->failed) spdlog::info("job {} ended: its lease lapsed too often", id);
  if (!r->requeued.empty() && on_requeued_) on_requeued_();
  return r->requeued.size() + r->failed.size();
}

void LeaseReaper::Loop() {
  for (;;) {
    {
      std::unique_lock<std::mutex> lock(mu_);
      if (cv_.wait_for(lock, period_, [&] { return stop_; })) return;
    }
    if (auto r = SweepOnce(); !r.ok()) spdlog::warn("lease reaper: {}", r.status().ToString());
  }
}

}  // namespace decima::server
