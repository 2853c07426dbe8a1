#include "server/store/event_bus.h"

#include "server/store/job_store.h"

namespace decima::server {

EventBus::Channel::Wait EventBus::Channel::WaitAfter(int64_t after,
                                                     std::chrono::milliseconds timeout,
                                                     std::vector<v1::JobEvent>* out) {
  std::unique_lock<std::mutex> lock(mu_);
  auto has_new = [&] { return closed_ || (!recent_.empty() && recent_.back().sequence() > after); };
  if (!cv_.wait_for(lock, timeout, has_new)) return Wait::kTimeout;
  if (closed_) return Wait::kClosed;
  if (recent_.front().sequence() > after + 1) return Wait::kGap;
  for (const auto& ev : recent_) {
    if (ev.sequence() > after) out->push_back(ev);
  }
  return Wait::kEvents;
}

std::shared_ptr<EventBus::Channel> EventBus::Subscribe(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mu_);
  auto& ch = channels_[job_id];
  if (!ch) {
    ch = std::make_shared<Channel>();
    if (closed_) ch->closed_ = true;
  }
  return ch;
}

void EventBus::Publish(const std::string& job_id, const v1::JobEvent& event) {
  std::shared_ptr<Channel> ch;
  bool final_event = event.has_state_change() && IsFinal(event.state_change().state());
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = channels_.find(job_id);
    if (it == channels_.end()) {
      if (final_event) return;  // nobody listens; a later watcher reads the store
      it = channels_.emplace(job_id, std::make_shared<Channel>()).first;
    }
    ch = it->second;
    if (final_event) channels_.erase(it);
  }
  {
    std::lock_guard<std::mutex> lock(ch->mu_);
    ch->recent_.push_back(event);
    while (ch->recent_.size() > keep_) ch->recent_.pop_front();
  }
  ch->cv_.notify_all();
}

void EventBus::Unsubscribe(const std::string& job_id, const std::shared_ptr<Channel>& channel) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = channels_.find(job_id);
  // Two references: the map's and the caller's.
  if (it != channels_.end() && it->second == channel && channel.use_count() <= 2) {
    channels_.erase(it);
  }
}

std::vector<std::string> EventBus::ActiveJobs() {
  std::lock_guard<std::mutex> lock(mu_);
  std::vector<std::string> ids;
  ids.reserve(channels_.size());
  for (const auto& [id, ch] : channels_) ids.push_back(id);
  return ids;
}

void EventBus::Close() {
  std::map<std::string, std::shared_ptr<Channel>> channels;
  {
    std::lock_guard<std::mutex> lock(mu_);
    closed_ = true;
    channels = channels_;
  }
  for (auto& [id, ch] : channels) {
    {
      std::lock_guard<std::mutex> lock(ch->mu_);
      ch->closed_ = true;
    }
    ch->cv_.notify_all();
  }
}

}  // namespace decima::server
