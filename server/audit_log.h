// The audit log: one JSON line per state-changing call (Upload, CreateVolume, DeleteVolume,
// CreateJob, CancelJob, RetryJob, DeleteJob), allowed or refused, through its own spdlog logger
// to a size-rotated file (separate from the server's log on stderr). A line holds who (principal
// and role), what (the RPC), which resource (a name such as "jobs/{id}" or "blobs/{sha256}") and
// the result (the status code). Never a token, a message text or a file's content: status
// messages may quote client input, so only the code is written.
// Thread-safety: Record from any thread (spdlog's _mt sink).
#pragma once

#include <grpcpp/grpcpp.h>

#include <cstddef>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "server/call_guard.h"

namespace spdlog {
class logger;
}

namespace decima::server {

class AuditLog {
 public:
  // A disabled log (Record does nothing).
  AuditLog() = default;
  // Appends to `path`, rotated at `max_bytes` keeping `max_files` old files (path.1, path.2, ...).
  // INVALID_ARGUMENT naming the file when it cannot be opened.
  static absl::StatusOr<std::shared_ptr<AuditLog>> Open(const std::string& path, size_t max_bytes,
                                                        size_t max_files);
  ~AuditLog();

  // `caller` null: the call was refused before anyone was identified. Returns `result`.
  grpc::Status Record(const Principal* caller, const char* rpc, const std::string& resource,
                      const grpc::Status& result) const;

 private:
  std::shared_ptr<spdlog::logger> logger_;
};

}  // namespace decima::server
