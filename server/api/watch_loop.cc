#include "server/api/watch_loop.h"

#include <vector>

#include "absl/strings/str_cat.h"

namespace decima::server {

absl::Status WatchLoop::Run(const std::string& job_id, int64_t after_sequence,
                            const WatchControls& c) {
  using Clock = std::chrono::steady_clock;
  // Subscribe before reading the store so that nothing committed in between is missed.
  auto channel = bus_->Subscribe(job_id);
  struct Unsubscribe {
    EventBus* bus;
    const std::string& id;
    std::shared_ptr<EventBus::Channel> ch;
    ~Unsubscribe() { bus->Unsubscribe(id, ch); }
  } unsubscribe{bus_, job_id, channel};

  auto job = store_->GetJob(job_id);
  if (!job.ok()) return job.status();
  int64_t last = after_sequence;
  // The job's state as of the last event sent: while the server drains, a watch of a RUNNING job
  // goes on (the drain's progress and the job's end or requeue are what its watcher waits for).
  v1::JobState state = job->state();
  {
    v1::JobEvent snap;
    snap.set_sequence(job->last_sequence());
    *snap.mutable_time() = NowTimestamp();
    *snap.mutable_snapshot() = *job;
    if (!c.send(snap)) return absl::CancelledError("the watcher went away");
  }
  // A job already final with nothing newer to send: the snapshot was the whole answer.
  if (IsFinal(job->state()) && last >= job->last_sequence()) return absl::OkStatus();

  bool ended = false, gone = false, closed = false, flushed = false;
  // Sends `events` in order, skipping what was sent; false on a gap (reread the store).
  auto send = [&](const std::vector<v1::JobEvent>& events) -> bool {
    for (const auto& ev : events) {
      if (ev.sequence() <= last) continue;
      if (ev.sequence() != last + 1) return false;
      if (!c.send(ev)) {
        gone = true;
        return true;
      }
      last = ev.sequence();
      if (ev.has_state_change()) state = ev.state_change().state();
      if (ev.has_state_change() && IsFinal(ev.state_change().state())) {
        auto now = store_->GetJob(job_id);
        if (now.ok() && now->last_sequence() == last) ended = true;
      }
      if (ended) return true;
    }
    return true;
  };
  auto last_write = Clock::now();
  bool need_store = true;
  for (;;) {
    if (gone || c.cancelled()) return absl::CancelledError("the watcher went away");
    // After the bus closed, the store is read once more: the requeue may have been committed
    // but not yet published when the drain ended.
    if (c.draining() && (state != v1::RUNNING || (closed && flushed))) {
      return absl::UnavailableError(
          absl::StrCat("the server is shutting down; watch again with after_sequence=", last));
    }
    if (need_store) {
      auto events = store_->ListEvents(job_id, last, options_.store_batch);
      if (!events.ok()) return events.status();
      const int64_t before = last;
      send(*events);
      if (ended) return absl::OkStatus();
      if (last != before) last_write = Clock::now();
      need_store = static_cast<int>(events->size()) == options_.store_batch;
      if (need_store) continue;
    }
    std::vector<v1::JobEvent> events;
    switch (channel->WaitAfter(last, options_.wait, &events)) {
      case EventBus::Channel::Wait::kEvents: {
        const int64_t before = last;
        if (!send(events)) need_store = true;
        if (ended) return absl::OkStatus();
        if (last == before) need_store = true;
        if (last != before) last_write = Clock::now();
        break;
      }
      case EventBus::Channel::Wait::kGap:
        need_store = true;
        break;
      case EventBus::Channel::Wait::kClosed:  // the draining check above ends the stream
        flushed = closed;
        closed = true;
        need_store = true;
        break;
      case EventBus::Channel::Wait::kTimeout:
        break;
    }
    if (Clock::now() - last_write >= options_.heartbeat) {
      v1::JobEvent hb;
      hb.set_sequence(last);
      *hb.mutable_time() = NowTimestamp();
      hb.mutable_heartbeat();
      if (!c.send(hb)) return absl::CancelledError("the watcher went away");
      last_write = Clock::now();
      // A heartbeat tick also rechecks the store: a cheap guard against any missed wake-up.
      need_store = true;
    }
  }
}

}  // namespace decima::server
