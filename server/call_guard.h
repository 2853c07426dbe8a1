// The one check in front of every decima.v1 call: the bearer token (when configured, compared in
// constant time) and the drain state. gRPC 1.51's server interceptors cannot end a call with a
// status, and an AuthMetadataProcessor needs TLS credentials (auth must hold without TLS too), so
// every handler's first line is `guard.Check(ctx)`; the rule itself lives here only.
// The health and reflection services are not behind it (probes call them without credentials).
// Thread-safety: Check from any thread; StartDraining once.
#pragma once

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <string>

namespace decima::server {

class CallGuard {
 public:
  explicit CallGuard(std::string token) : token_(std::move(token)) {}

  // UNAUTHENTICATED without the right "authorization: Bearer <token>" metadata, UNAVAILABLE
  // while draining, else OK.
  grpc::Status Check(grpc::ServerContext* ctx) const;

  void StartDraining() { draining_.store(true); }
  bool draining() const { return draining_.load(); }

 private:
  const std::string token_;  // empty: no authentication
  std::atomic<bool> draining_{false};
};

}  // namespace decima::server
