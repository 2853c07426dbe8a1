#include "client/cli/job_event_stream.h"

#include <algorithm>
#include <thread>

namespace decima::client {

JobEventStream::JobEventStream(v1::Jobs::StubInterface* stub,
                               std::function<std::unique_ptr<grpc::ClientContext>()> new_context,
                               std::string name, ReconnectPolicy policy,
                               std::atomic<bool>* ever_connected)
    : stub_(stub),
      new_context_(std::move(new_context)),
      name_(std::move(name)),
      policy_(policy),
      ever_connected_(ever_connected) {}

grpc::Status JobEventStream::Follow(const Handlers& h) {
  auto give_up = std::chrono::steady_clock::now() + policy_.give_up_after;
  auto wait = policy_.first_wait;
  int attempts = 0;
  for (;;) {
    v1::WatchJobRequest req;
    req.set_name(name_);
    req.set_after_sequence(last_);
    auto ctx = new_context_();
    auto reader = stub_->WatchJob(ctx.get(), req);
    v1::JobEvent ev;
    while (reader->Read(&ev)) {
      *ever_connected_ = true;
      if (attempts > 0 && h.reconnected) h.reconnected(attempts);
      attempts = 0;
      give_up = std::chrono::steady_clock::now() + policy_.give_up_after;
      wait = policy_.first_wait;
      if (h.event) h.event(ev);
      if (!ev.has_snapshot() && !ev.has_heartbeat()) last_ = ev.sequence();
    }
    const grpc::Status s = reader->Finish();
    if (h.stream_ended) h.stream_ended();
    if (s.ok()) return s;
    const bool server_went_away = s.error_code() == grpc::StatusCode::UNAVAILABLE ||
                                  s.error_code() == grpc::StatusCode::CANCELLED;
    if (server_went_away && *ever_connected_ && std::chrono::steady_clock::now() < give_up) {
      // One notice per outage (its first reason), not one per attempt.
      if (++attempts == 1 && h.outage) h.outage(s);
      sleep(wait);
      wait = std::min(wait * 2, policy_.max_wait);
      continue;
    }
    if (attempts > 0 && h.gave_up) h.gave_up(attempts);
    return s;
  }
}

}  // namespace decima::client
