// In-process fan-out of job events to watchers. The job store stays the source of truth: the
// bus only keeps the last few events per active job so that many watchers of the same job are
// served from memory instead of each querying the store, and wakes them when something happens.
//
// A watcher takes Subscribe(job) BEFORE reading the store's backlog: every event committed
// after that read is then in the channel, so store + channel together have no gap.
// Thread-safety: all methods may be called from any thread.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "decima/v1/jobs.pb.h"

namespace decima::server {

class EventBus {
 public:
  class Channel {
   public:
    enum class Wait { kEvents, kGap, kTimeout, kClosed };
    // Waits until an event with sequence > `after` is present, `timeout` passes, or the bus is
    // closed. kEvents: `out` gets every held event > after, in order. kGap: the channel no
    // longer holds after+1 (read the store).
    Wait WaitAfter(int64_t after, std::chrono::milliseconds timeout,
                   std::vector<v1::JobEvent>* out);

   private:
    friend class EventBus;
    std::mutex mu_;
    std::condition_variable cv_;
    std::deque<v1::JobEvent> recent_ ABSL_GUARDED_BY(mu_);
    bool closed_ ABSL_GUARDED_BY(mu_) = false;
  };

  explicit EventBus(size_t keep_per_job = 256) : keep_(keep_per_job) {}

  std::shared_ptr<Channel> Subscribe(const std::string& job_id);
  // Called by the store's listener, in sequence order per job. A final state change retires
  // the job's channel (current subscribers still receive the event).
  void Publish(const std::string& job_id, const v1::JobEvent& event);
  // Drops the bus's reference when `channel` has no other subscriber. Always safe: a channel
  // is only a cache in front of the store.
  void Unsubscribe(const std::string& job_id, const std::shared_ptr<Channel>& channel);
  // The jobs with a channel: watched here, or running with events not yet final.
  std::vector<std::string> ActiveJobs();
  // Wakes every waiter with kClosed (server shutdown).
  void Close();

 private:
  const size_t keep_;
  std::mutex mu_;
  std::map<std::string, std::shared_ptr<Channel>> channels_ ABSL_GUARDED_BY(mu_);
  bool closed_ ABSL_GUARDED_BY(mu_) = false;
};

}  // namespace decima::server
