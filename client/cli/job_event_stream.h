// One job's WatchJob stream that outlives a server restart: when the server goes away
// (UNAVAILABLE, or CANCELLED: this client never cancels a watch, so that is the server's
// shutdown cutting the call), it asks again with the last sequence it saw, waiting 0.1 s, then
// twice as long each time up to 1 s, for up to --reconnect after the last event. Used by the
// watch of one job and by the watch of several; how each words an outage is its own.
#pragma once

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "decima/v1/jobs.grpc.pb.h"

namespace decima::client {

struct ReconnectPolicy {
  std::chrono::milliseconds give_up_after{60000};  // --reconnect, counted from the last event
  std::chrono::milliseconds first_wait{100};
  std::chrono::milliseconds max_wait{1000};
};

class JobEventStream {
 public:
  struct Handlers {
    std::function<void(const v1::JobEvent&)> event;   // every event, heartbeats included
    std::function<void()> stream_ended;               // after each stream, before any retry
    std::function<void(const grpc::Status&)> outage;  // the first failed attempt of an outage
    std::function<void(int attempts)> reconnected;    // the first event after an outage
    std::function<void(int attempts)> gave_up;
  };

  // `ever_connected`: set on every event; no retry before the server answered once (a wrong
  // address fails at once). `new_context` makes each stream's context (no deadline).
  JobEventStream(v1::Jobs::StubInterface* stub,
                 std::function<std::unique_ptr<grpc::ClientContext>()> new_context,
                 std::string name, ReconnectPolicy policy, std::atomic<bool>* ever_connected);

  // Follows the job until its stream ends by itself (OK: the job is final) or the server stays
  // away past the policy (that stream's status).
  grpc::Status Follow(const Handlers& handlers);

  // The sequence of the last event that was neither the snapshot nor a heartbeat (0: none yet).
  int64_t last_sequence() const { return last_; }

  // How a wait between attempts is spent (a test records them instead).
  std::function<void(std::chrono::milliseconds)> sleep = [](std::chrono::milliseconds d) {
    std::this_thread::sleep_for(d);
  };

 private:
  v1::Jobs::StubInterface* stub_;
  std::function<std::unique_ptr<grpc::ClientContext>()> new_context_;
  std::string name_;
  ReconnectPolicy policy_;
  std::atomic<bool>* ever_connected_;
  int64_t last_ = 0;
};

}  // namespace decima::client
