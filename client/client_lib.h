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
#include <string_view>
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
  // The job SUCCEEDED but simplification stopped before the target reduction (metrics.json
  // "reached_target": false); the artifacts are fetched as usual.
  kTargetNotReached = 10,
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
// `text` from the server made safe to print on a terminal: C0 controls (ESC included), DEL and
// C1 controls (U+0080..U+009F) become `\xNN` / `\u00NN`, and so does every byte that is not
// part of valid UTF-8; printable text, UTF-8 letters included, is kept. A display name such as
// "\x1b]0;owned\x07" can then not retitle, clear or rewrite an admin's terminal.
std::string TerminalSafe(std::string_view text);

// Whether a TCP connection to `address` ("host:port", "[v6]:port", with an optional "dns:///"
// or "ipv4:" / "ipv6:" prefix) is accepted within `timeout`: tells "nothing listens there" from
// "something listens but the gRPC call failed" (a plaintext client against a TLS server).
bool TcpPortAnswers(const std::string& address, std::chrono::milliseconds timeout);

// The sha256 of `bytes` as 64 lower-case hex digits, in memory (no temporary file: a predictable
// name in the temp folder let another user plant a symlink or a FIFO there).
std::string Sha256HexOf(std::string_view bytes);

// For a single .mhd or .nhdr header in `*files`: adds the data file(s) it names
// (MetaImage ElementDataFile, NRRD "data file:", single names or LIST) with manifest names
// relative to the header's folder. A header with LOCAL data or an attached NRRD adds nothing.
// False with a message naming the header and the line when a data file is missing, outside
// the header's folder, or given as a pattern, and when any component of its path below the
// header's folder is a symbolic link (a linked folder such as `sub -> /etc` would otherwise
// upload `sub/passwd`; every link is refused, also one pointing inside the folder).
bool AddHeaderDataFiles(std::vector<InputFile>* files, std::string* error);

// Keeps the DICOM files of a folder: drops DICOMDIR and files without the "DICM" marker at
// byte 128 (notes, checksums, thumbnails). Returns the names dropped, for a warning.
std::vector<std::string> KeepDicomFiles(std::vector<InputFile>* files);

// Overall progress of a running job across its stages, from the stage's own fraction and the
// stage weights measured on a CT job (client/README.md "Progress"). 0..1. `with_curve`: the job
// asked for the "curve" output, which adds its stage (JobWithCurve).
double OverallFraction(const std::string& stage, double stage_fraction, bool with_curve = false);
// Whether the job's spec asks for the "curve" output (its own, long stage).
bool JobWithCurve(const v1::Job& job);
// "1:05", "12:03:09"; "-" for a negative value.
std::string FormatDuration(double seconds);
// "15.6 MB", "812 KB", "73 B".
std::string FormatBytes(int64_t bytes);
// The job's overall fraction: the job's own (Progress.overall_fraction, from its stage model and
// measured rates) when the event carries it, else OverallFraction's fixed stage weights.
double JobFraction(const v1::Progress& p, bool with_curve = false);
// One status line for a TTY (no newline): "[#####.....]  45% simplify  elapsed 0:12  ETA 0:15".
// The ETA is the job's own (Progress.eta_seconds, less the `since_event_s` seconds since the
// event was sent); for an event without one it is extrapolated from the elapsed time and left
// out while the overall fraction is below 2 % (too early to say).
std::string OverallBar(const v1::Progress& p, double elapsed_s, int width, bool with_curve = false,
                       double since_event_s = 0);

// After a succeeded job: achieved against target reduction, cells, the artifacts' total size
// and its ratio to the input's bytes. `target_reached` false when metrics say so.
struct JobSummary {
  double target_reduction = 0, achieved_reduction = 0;
  int64_t cells_before = 0, cells_after = 0;
  bool reached_target = true;
  // The job's PSNR floor (JobSpec.min_psnr) stopped it before the target: what was asked for, so
  // no warning and exit code 0 (the target is the maximum, the floor may stop earlier).
  bool stopped_by_floor = false;
  std::string stop_message;
  int64_t artifact_bytes = 0, input_bytes = 0;
  // The job did what its spec asked: the target reached, or the PSNR floor stopped it first.
  bool Met() const { return reached_target || stopped_by_floor; }
};
JobSummary SummarizeJob(const v1::Job& job, int64_t input_bytes);
std::vector<std::string> SummaryLines(const JobSummary& s);

// The fidelity figures `decima status` shows from metrics.json: "diff1 0.017", "psnr_db 63.7",
// "mean_dice 1", each only if present. metrics.json writes a PSNR that is not finite as null:
// with rmse 0 (the field reproduced exactly) that is "psnr_db inf (rmse 0)", else "psnr_db n/a".
std::vector<std::string> FidelityLines(const std::string& metrics_json);

// Case-insensitive parse of a job state name ("succeeded" -> SUCCEEDED); false if unknown.
bool ParseJobState(const std::string& name, v1::JobState* state);

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
