// The pieces of the `decima` CLI that are worth testing on their own: exit codes, input file
// collection, resumable uploads and downloads, and progress formatting. Depends on the proto
// library only (never on core).
#pragma once

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "decima/v1/artifacts.grpc.pb.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"

namespace decima::client {

// Exit codes of the CLI (documented in --help).
enum ExitCode : int {
  kOk = 0,
  kError = 1,
  kUsage = 2,
  kJobFailed = 3,
  kJobCancelled = 4,
  kTimeout = 5,
  kNotFound = 6,
  kUnauthenticated = 7,  // UNAUTHENTICATED, and PERMISSION_DENIED (not this caller's job/volume)
  kPermissionDenied = 7,
  kUnavailable = 8,
};

// The exit code for a failed call.
int ExitCodeFor(grpc::StatusCode code);
// The exit code for a job's final state (0 SUCCEEDED, 3 FAILED, 4 CANCELLED, 1 otherwise).
int ExitCodeFor(v1::JobState state);

// "NOT_FOUND", "UNAVAILABLE", ...
std::string StatusCodeName(grpc::StatusCode code);

struct InputFile {
  std::string name;  // manifest path: the base name of a file, or the path inside a folder
  std::filesystem::path path;
  int64_t size = 0;
  std::string sha256;  // filled by HashInputs
};

// A file -> itself; a folder (DICOM series) -> every regular file below it, sorted, skipping
// hidden ones. INVALID_ARGUMENT-style message on error (missing, empty folder).
bool CollectInputs(const std::filesystem::path& input, std::vector<InputFile>* out,
                   std::string* error);
bool HashInputs(std::vector<InputFile>* files, std::string* error);

// Connection settings and a context factory that sets the token and a deadline.
struct Connection {
  std::shared_ptr<grpc::Channel> channel;
  std::string token;
  std::chrono::milliseconds timeout{30000};
  // A context for one call; `deadline` false for streams.
  std::unique_ptr<grpc::ClientContext> Context(bool deadline = true) const;
};

// TLS settings of a connection. Plaintext when `enabled` is false and every file is empty.
struct TlsFiles {
  bool enabled = false;
  std::string ca_file;    // PEM roots (empty: the system's)
  std::string cert_file;  // PEM client certificate chain for mutual TLS (with key_file)
  std::string key_file;
  bool any() const {
    return enabled || !ca_file.empty() || !cert_file.empty() || !key_file.empty();
  }
};

// The files are read here; a missing or unreadable one is an error naming it (`*error`, and
// a connection with no channel).
Connection Connect(const std::string& address, const std::string& token, const TlsFiles& tls,
                   std::chrono::milliseconds timeout, std::string* error);

// Progress of uploads and downloads: (done bytes, total bytes).
using ByteProgress = std::function<void(int64_t, int64_t)>;

// Uploads `file` unless the server holds it, resuming from the server's committed size.
// Retries a broken stream (UNAVAILABLE, ABORTED) up to `attempts` times. `*resumed_at` gets the
// offset the first stream started at (0 for a fresh upload, size for a deduplicated blob).
grpc::Status UploadBlob(const Connection& c, const InputFile& file, const ByteProgress& progress,
                        int attempts, int64_t* resumed_at);

// Downloads an artifact into `dir` (via `<file>.part`, resuming from its size), checks size and
// sha256, then renames. Returns the final path in `*path`.
grpc::Status DownloadArtifact(const Connection& c, const v1::Artifact& artifact,
                              const std::filesystem::path& dir, const ByteProgress& progress,
                              std::filesystem::path* path);

// One line describing an event for logs: "jobs/x #7 segment 45% iteration 12".
std::string DescribeEvent(const std::string& job, const v1::JobEvent& ev);
// A terminal progress bar line (no newline): "segment   [#####.....]  45% message".
std::string ProgressBar(const v1::Progress& p, int width);

}  // namespace decima::client
