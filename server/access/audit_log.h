// The audit log: one JSON line per state-changing call (Upload, CreateVolume, DeleteVolume,
// CreateJob, CancelJob, RetryJob, DeleteJob), allowed or refused, and per state change the
// DICOM receiver makes on a sender's behalf (a job queued from a received series, the sending of
// its results), through its own spdlog logger to a size-rotated file (separate from the server's
// log on stderr). A line holds who (principal and role), what (the RPC), which resource (a name
// such as "jobs/{id}" or "blobs/{sha256}") and the result (the status code). Never a token, a
// message text or a file's content: status messages may quote client input, so only the code is
// written.
//
// What an attacker without credentials could do to it before (issue 35 part 3) and why each
// rule below exists:
// - A refused caller is not identified, so nothing it sent is written: its lines hold the RPC
//   and the code only, and at most kUnidentifiedPerSecond of them are written a second (the
//   number left out rides in the next one as "unidentified_dropped"). Oversized requests
//   cannot rotate the records of identified callers out of the files.
// - Every field is bounded (kMaxField bytes, then "...(+N bytes)") and escaped (control
//   characters, DEL and every byte >= 0x80 as \u00XX), so a line stays one line of JSON.
// - One writer per file: Open takes an exclusive lock on "<file>.lock" that the kernel drops
//   when the process dies; a second process on the same file is refused (replicas sharing a
//   data dir each get their own file, see DefaultAuditPath), so rotation never races.
// - A record that cannot be written (full disk, I/O error) is logged loudly on stderr and the
//   log turns "stopped": Ready() then refuses further mutations with UNAVAILABLE until a line
//   can be written again (the first line written after the gap says how many were refused).
// Thread-safety: Record and Ready from any thread.
#pragma once

#include <grpcpp/grpcpp.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "server/access/call_guard.h"

namespace spdlog {
class logger;
}

namespace decima::server {

class AuditLog {
 public:
  // Longest field written (principal, role, resource); longer ones are cut and say by how much.
  static constexpr size_t kMaxField = 256;
  // Lines of refused, unidentified calls written per second at most.
  static constexpr int kUnidentifiedPerSecond = 10;

  // A disabled log (Record does nothing, Ready is OK).
  AuditLog() = default;
  // Appends to `path`, rotated at `max_bytes` keeping `max_files` old files (spdlog's names:
  // audit.log -> audit.1.log, audit.2.log, ...). Holds an exclusive flock on "<path>.lock" for
  // its lifetime. FAILED_PRECONDITION naming the file when another process holds that lock,
  // INVALID_ARGUMENT naming the file when it cannot be opened.
  static absl::StatusOr<std::shared_ptr<AuditLog>> Open(const std::string& path, size_t max_bytes,
                                                        size_t max_files);
  ~AuditLog();
  AuditLog(const AuditLog&) = delete;
  AuditLog& operator=(const AuditLog&) = delete;

  // `caller` null: the call was refused before anyone was identified (then `resource` is not
  // written and the line counts against kUnidentifiedPerSecond). Returns `result`.
  grpc::Status Record(const Principal* caller, const char* rpc, const std::string& resource,
                      const grpc::Status& result) const;
  // The same for a change the server makes on behalf of `principal` (the DICOM receiver);
  // `association` non-empty: the DICOM association it came from ("association" in the line).
  void RecordSystem(const std::string& principal, const char* action, const std::string& resource,
                    const absl::Status& result, const std::string& association = "") const;

  // OK while records are being written. After a record failed: tries to write a line saying
  // auditing resumes; UNAVAILABLE naming the file if that fails too (the caller refuses its
  // mutation).
  grpc::Status Ready() const;

  const std::string& path() const { return path_; }

 private:
  // Writes `json` (one object); false and the log marked stopped when it could not be written.
  bool WriteLocked(const std::string& json) const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  std::shared_ptr<spdlog::logger> logger_;
  std::string path_;
  int lock_fd_ = -1;
  mutable absl::Mutex mu_;
  mutable bool write_failed_ ABSL_GUARDED_BY(mu_) = false;  // set by the logger's error handler
  mutable std::string last_error_ ABSL_GUARDED_BY(mu_);
  mutable bool stopped_ ABSL_GUARDED_BY(mu_) = false;
  mutable int64_t refused_while_stopped_ ABSL_GUARDED_BY(mu_) = 0;
  mutable int64_t window_second_ ABSL_GUARDED_BY(mu_) = 0;
  mutable int window_count_ ABSL_GUARDED_BY(mu_) = 0;
  mutable int64_t unidentified_dropped_ ABSL_GUARDED_BY(mu_) = 0;
};

// The default audit file of a server on `data_dir`: "audit-<hostname>.log", so that replicas
// sharing the data dir (one host name per Kubernetes pod) write a file each; `n` > 1 gives
// "audit-<hostname>-<n>.log" for a further server on the same host.
std::string DefaultAuditPath(const std::string& data_dir, int n);

}  // namespace decima::server
