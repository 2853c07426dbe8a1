#include "server/access/audit_log.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <ctime>

#include <grpcpp/support/status.h>
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "spdlog/sinks/rotating_file_sink.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace {

// A JSON string literal of at most AuditLog::kMaxField bytes of `s` (names come from the tokens
// file, certificates and request fields): control characters, DEL and every byte >= 0x80 are
// written as \u00XX, so the line is one line of ASCII whatever the caller sent.
std::string Quote(const std::string& s) {
  const size_t n = std::min(s.size(), AuditLog::kMaxField);
  std::string out = "\"";
  for (size_t i = 0; i < n; ++i) {
    const unsigned char c = static_cast<unsigned char>(s[i]);
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c < 0x20 || c >= 0x7f) {
      absl::StrAppend(&out, "\\u00", absl::Hex(c, absl::kZeroPad2));
    } else {
      out += static_cast<char>(c);
    }
  }
  if (n < s.size()) absl::StrAppend(&out, "...(+", s.size() - n, " bytes)");
  return out + "\"";
}

const char* CodeName(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return "OK";
    case grpc::StatusCode::CANCELLED:
      return "CANCELLED";
    case grpc::StatusCode::UNKNOWN:
      return "UNKNOWN";
    case grpc::StatusCode::INVALID_ARGUMENT:
      return "INVALID_ARGUMENT";
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::NOT_FOUND:
      return "NOT_FOUND";
    case grpc::StatusCode::ALREADY_EXISTS:
      return "ALREADY_EXISTS";
    case grpc::StatusCode::PERMISSION_DENIED:
      return "PERMISSION_DENIED";
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::FAILED_PRECONDITION:
      return "FAILED_PRECONDITION";
    case grpc::StatusCode::ABORTED:
      return "ABORTED";
    case grpc::StatusCode::OUT_OF_RANGE:
      return "OUT_OF_RANGE";
    case grpc::StatusCode::UNIMPLEMENTED:
      return "UNIMPLEMENTED";
    case grpc::StatusCode::INTERNAL:
      return "INTERNAL";
    case grpc::StatusCode::UNAVAILABLE:
      return "UNAVAILABLE";
    case grpc::StatusCode::DATA_LOSS:
      return "DATA_LOSS";
    case grpc::StatusCode::UNAUTHENTICATED:
      return "UNAUTHENTICATED";
    default:
      return "UNKNOWN";
  }
}

}  // namespace

absl::StatusOr<std::shared_ptr<AuditLog>> AuditLog::Open(const std::string& path, size_t max_bytes,
                                                         size_t max_files) {
  auto log = std::make_shared<AuditLog>();
  log->path_ = path;
  // One writer per file: spdlog rotates by renaming, and two processes renaming the same files
  // each on their own lose records (issue 35: replicas on a shared data dir).
  const std::string lock = path + ".lock";
  log->lock_fd_ = ::open(lock.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0600);
  if (log->lock_fd_ < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("--audit-log ", path, ": cannot open ", lock, ": ", std::strerror(errno)));
  }
  if (::flock(log->lock_fd_, LOCK_EX | LOCK_NB) != 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("--audit-log ", path, ": written by another process (", lock,
                     " is locked); give every server its own audit file"));
  }
  try {
    auto sink = std::make_shared<spdlog::sinks::rotating_file_sink_mt>(path, max_bytes, max_files);
    log->logger_ = std::make_shared<spdlog::logger>("audit", std::move(sink));
  } catch (const spdlog::spdlog_ex& e) {
    return absl::InvalidArgumentError(absl::StrCat("--audit-log ", path, ": ", e.what()));
  }
  // The time in UTC, then the JSON object; every line is flushed (an audit line must survive a
  // crash right after the call).
  log->logger_->set_pattern("%Y-%m-%dT%H:%M:%S.%fZ %v", spdlog::pattern_time_type::utc);
  log->logger_->set_level(spdlog::level::info);
  log->logger_->flush_on(spdlog::level::info);
  // spdlog reports a failed write or flush here instead of throwing; it runs inside
  // logger_->info(), i.e. under mu_ in WriteLocked.
  AuditLog* self = log.get();
  log->logger_->set_error_handler([self](const std::string& msg) ABSL_NO_THREAD_SAFETY_ANALYSIS {
    self->write_failed_ = true;
    self->last_error_ = msg;
  });
  return log;
}

AuditLog::~AuditLog() {
  if (lock_fd_ >= 0) ::close(lock_fd_);
}

bool AuditLog::WriteLocked(const std::string& json) const {
  write_failed_ = false;
  logger_->info("{}", json);
  if (!write_failed_) return true;
  if (!stopped_) {
    spdlog::error(
        "AUDIT LOG STOPPED: {} cannot be written ({}); state-changing calls are refused with "
        "UNAVAILABLE until it can",
        path_, last_error_);
  }
  stopped_ = true;
  return false;
}

grpc::Status AuditLog::Record(const Principal* caller, const char* rpc, const std::string& resource,
                              const grpc::Status& result) const {
  if (!logger_) return result;
  absl::MutexLock lock(&mu_);
  std::string extra;
  if (caller == nullptr) {
    // Unidentified: a bounded number of lines a second, whatever they sent.
    const int64_t now = static_cast<int64_t>(std::time(nullptr));
    if (now != window_second_) {
      window_second_ = now;
      window_count_ = 0;
    }
    if (++window_count_ > kUnidentifiedPerSecond) {
      ++unidentified_dropped_;
      return result;
    }
    if (unidentified_dropped_ > 0) {
      extra = absl::StrCat(",\"unidentified_dropped\":", unidentified_dropped_);
    }
  }
  const std::string json =
      absl::StrCat("{\"principal\":", Quote(caller ? caller->name : ""),
                   ",\"role\":", Quote(caller ? RoleName(caller->role) : ""), ",\"rpc\":\"", rpc,
                   "\",\"resource\":", Quote(caller ? resource : ""), ",\"result\":\"",
                   CodeName(result.error_code()), "\"", extra, "}");
  if (WriteLocked(json) && caller == nullptr) unidentified_dropped_ = 0;
  return result;
}

void AuditLog::RecordSystem(const std::string& principal, const char* action,
                            const std::string& resource, const absl::Status& result,
                            const std::string& association) const {
  if (!logger_) return;
  absl::MutexLock lock(&mu_);
  WriteLocked(
      absl::StrCat("{\"principal\":", Quote(principal), ",\"role\":\"system\",\"rpc\":\"", action,
                   "\",\"resource\":", Quote(resource),
                   association.empty() ? "" : absl::StrCat(",\"association\":", Quote(association)),
                   ",\"result\":\"", absl::StatusCodeToString(result.code()), "\"}"));
}

grpc::Status AuditLog::Ready() const {
  if (!logger_) return grpc::Status::OK;
  absl::MutexLock lock(&mu_);
  if (!stopped_) return grpc::Status::OK;
  if (WriteLocked(absl::StrCat(
          "{\"audit\":\"resumed\",\"refused_while_stopped\":", refused_while_stopped_, "}"))) {
    spdlog::warn("audit log {} is written again ({} state-changing calls were refused meanwhile)",
                 path_, refused_while_stopped_);
    stopped_ = false;
    refused_while_stopped_ = 0;
    return grpc::Status::OK;
  }
  ++refused_while_stopped_;
  return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                      absl::StrCat("the audit log cannot be written (", last_error_,
                                   "); state-changing calls are refused until it can"));
}

std::string DefaultAuditPath(const std::string& data_dir, int n) {
  char host[256] = {};
  if (::gethostname(host, sizeof host - 1) != 0 || host[0] == '\0') {
    std::snprintf(host, sizeof host, "localhost");
  }
  // A host name is [A-Za-z0-9.-]; anything else becomes '_' so the name stays one file name.
  std::string h(host);
  for (char& c : h) {
    if (!absl::ascii_isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '.') c = '_';
  }
  return absl::StrCat(data_dir, "/audit-", h, n > 1 ? absl::StrCat("-", n) : "", ".log");
}

}  // namespace decima::server
