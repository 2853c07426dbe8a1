// The WatchJob stream as a class: a snapshot, then every event above `after_sequence` in order
// (from the store first, then live from the event bus), heartbeats while nothing happens, and
// the end after the event that made the job final (if it is still the job's newest event: a
// retried job goes on). A gap in the bus (a slow watcher) is filled from the store, which stays
// the source of truth. Independent of gRPC: the handler passes a sink that writes to the stream.
// Thread-safety: one Run per object at a time; many objects may share a store and a bus.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/status.h"
#include "server/store/event_bus.h"
#include "server/store/job_store.h"

namespace decima::server {

struct WatchOptions {
  std::chrono::milliseconds heartbeat{5000};  // a heartbeat after this long without a write
  std::chrono::milliseconds wait{250};        // longest sleep between checks of the controls
  int store_batch = 1000;                     // events read from the store at once
};

struct WatchControls {
  // Writes one event to the watcher; false when the watcher is gone.
  std::function<bool(const v1::JobEvent&)> send;
  // The watcher cancelled (checked between waits).
  std::function<bool()> cancelled = [] { return false; };
  // The server drains: end with UNAVAILABLE telling where to resume. A watch of a RUNNING job
  // goes on while the job gets its drain time (its drain progress and its requeue or end are
  // sent) and ends once the job is no longer running or the event bus closed.
  std::function<bool()> draining = [] { return false; };
};

class WatchLoop {
 public:
  WatchLoop(JobStore* store, EventBus* bus, WatchOptions options = {})
      : store_(store), bus_(bus), options_(options) {}

  // OK after the final event (or at once after the snapshot of a job already final with
  // nothing newer); CANCELLED when the watcher went away; UNAVAILABLE while draining (the
  // message names after_sequence to resume from); NOT_FOUND for an unknown job; store errors.
  absl::Status Run(const std::string& job_id, int64_t after_sequence,
                   const WatchControls& controls);

 private:
  JobStore* store_;
  EventBus* bus_;
  const WatchOptions options_;
};

}  // namespace decima::server
