// The opening every decima.v1 handler shares, written once. gRPC 1.51's server interceptors
// cannot end a call with a status (call_guard.h), so each handler body is wrapped in one of
// these instead:
// - Guarded: a call that changes nothing: the caller check (who, and the drain state), then the
//   body with the caller.
// - Audited: a call that changes state: a refused caller is audited without an identity, a change
//   that cannot be audited is not made (AuditLog::Ready), and the body's outcome is audited with
//   the resource it names.
#pragma once

#include <grpcpp/grpcpp.h>

#include <string>
#include <utility>

#include "server/api/service.h"

namespace decima::server {

// `body(const Principal& caller)` -> grpc::Status, run once the guard admits the caller.
template <typename Body>
grpc::Status Guarded(const ServiceDeps& d, grpc::ServerContext* ctx, Body&& body) {
  Principal caller;
  if (grpc::Status g = d.guard->Check(ctx, &caller); !g.ok()) return g;
  return std::forward<Body>(body)(caller);
}

// `body(const Principal& caller, std::string& resource)` -> grpc::Status. `resource` starts as
// given and the body may name it once it is known (a created job, an uploaded blob); the audit
// line of the outcome holds it. A refused caller's line holds no resource (AuditLog::Record).
template <typename Body>
grpc::Status Audited(const ServiceDeps& d, grpc::ServerContext* ctx, const char* rpc,
                     std::string resource, Body&& body) {
  Principal caller;
  if (grpc::Status g = d.guard->Check(ctx, &caller); !g.ok()) {
    return d.audit->Record(nullptr, rpc, "", g);
  }
  if (grpc::Status a = d.audit->Ready(); !a.ok()) return a;
  grpc::Status st = std::forward<Body>(body)(caller, resource);
  return d.audit->Record(&caller, rpc, resource, st);
}

}  // namespace decima::server
