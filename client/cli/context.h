// What every verb of the `decima` CLI shares: the global flags, the connection to the server,
// how a failed call is reported (and its exit code), retries of a restarting server, JOB
// arguments resolved to names, and the volumes met so far. One CliContext is made by main and
// passed to each verb; nothing of it is global.
#pragma once

#include <atomic>
#include <chrono>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include "client/client_lib.h"

// CLI11 is header-only and costs about 8 s of compile time per file that includes it: only the
// files that declare flags (client/cmd/, context.cc, dicomweb_flags.cc) do.
namespace CLI {
class App;
}  // namespace CLI

namespace decima::client {

inline constexpr const char* kDefaultServer = "127.0.0.1:50051";

// The flags before the verb (and -o / --json after it).
struct GlobalFlags {
  std::string server = kDefaultServer;
  std::string token;
  bool json = false;
  std::string output;  // "", "json" or "wide" (-o)
  bool tls = false;
  std::string ca_file, cert_file, key_file;
  double timeout_s = 30;
  double reconnect_s = 60;
  bool quiet = false;
};

struct CliContext {
  GlobalFlags flags;
  Connection conn;
  bool stderr_tty = false;
  // Set after the first answer from the server: from then on UNAVAILABLE means "restarting" and
  // is retried; before it, the address is probably wrong and the command fails at once. Atomic:
  // the watchers of several jobs run on threads of their own.
  std::atomic<bool> ever_connected{false};
  // The last error Report printed ("INVALID_ARGUMENT: ..."), for the table of a batch.
  std::string last_error;
  // Volumes by name, fetched once per command.
  std::map<std::string, v1::Volume> volumes;

  bool JsonOut() const { return flags.json || flags.output == "json"; }
  bool Quiet() const { return flags.quiet || JsonOut(); }
  bool Wide() const { return flags.output == "wide"; }
  bool TlsAsked() const { return flags.tls || !flags.ca_file.empty() || !flags.cert_file.empty(); }
};

// The global flags on the app.
void AddGlobalFlags(CLI::App& app, GlobalFlags& flags);
// -o FORMAT and --json on a subcommand (kubectl puts -o after the verb; the global --json of
// earlier releases keeps working).
void AddOutputFlags(CLI::App* cmd, GlobalFlags& flags);

// Opens the channel (TLS files read here); kUsage naming the file when one is unreadable.
int Connect(CliContext& ctx);
// Before the first call: waits (at most 5 s, or --timeout if shorter) until the channel is
// connected, and fails at once with a hint when the address refuses connections or does not
// answer, instead of retrying for a minute and then printing gRPC's text.
int EnsureReachable(CliContext& ctx, const std::string& what);

// Connect, then EnsureReachable: what every verb that calls the server does first.
int ConnectAndCheck(CliContext& ctx, const std::string& verb);

// Prints a failed call as "decima: WHAT: CODE: message" and returns its exit code.
int Report(CliContext& ctx, const grpc::Status& s, const std::string& what);
// An error of the client's own (no call failed): printed, and kept for a batch's table.
int InputError(CliContext& ctx, const std::string& message);

// Retries a unary call while the server is UNAVAILABLE (restarting), up to --reconnect, saying
// so once; never before the first answer (then the address is wrong: fail fast). CANCELLED is
// retried too: the CLI never cancels a unary call itself, so it is a server that shut down with
// the call in flight (watch streams stay open through a drain, so the watch's last GetJob can
// land just as the draining server stops).
template <typename F>
grpc::Status WithRetry(CliContext& ctx, F call) {
  auto until = std::chrono::steady_clock::now() +
               std::chrono::milliseconds(static_cast<int64_t>(ctx.flags.reconnect_s * 1000));
  int wait_ms = 100;
  bool said = false;
  for (;;) {
    grpc::Status s = call();
    if (s.error_code() != grpc::StatusCode::UNAVAILABLE &&
        s.error_code() != grpc::StatusCode::CANCELLED) {
      if (s.ok()) ctx.ever_connected = true;
      return s;
    }
    if (!ctx.ever_connected || std::chrono::steady_clock::now() > until) return s;
    if (!said && !ctx.Quiet()) {
      std::fprintf(stderr, "decima: server unavailable (%s); retrying for up to %s\n",
                   TerminalSafe(s.error_message()).c_str(),
                   FormatDuration(ctx.flags.reconnect_s).c_str());
      said = true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms));
    wait_ms = std::min(wait_ms * 2, 2000);
  }
}

// Resolves JOB: "jobs/{id}", a full id, or a unique prefix of an id (as docker does).
int ResolveJob(CliContext& ctx, const std::string& arg, std::string* name);
// Resolves JOB and gets the job, retried while the server restarts; a failure is reported as
// "VERB jobs/...".
int GetJobOf(CliContext& ctx, const std::string& arg, const std::string& verb, v1::Job* job);
// The volume `name` (cached), or nullptr when it is empty or cannot be read.
const v1::Volume* GetVolume(CliContext& ctx, const std::string& name);
// Every page of ListJobs (bounded), newest first.
int ListAllJobs(CliContext& ctx, const std::vector<v1::JobState>& states,
                std::vector<v1::Job>* out);

// A fresh random (version 4) UUID, the default request id.
std::string NewRequestId();
// The command line that runs `verb` on a job (re-attach, cancel), with --server when it is not the
// default.
std::string ShellCommand(const CliContext& ctx, const std::string& verb, const std::string& job);
// An upload's or download's bar on a terminal's stderr (nothing otherwise, or with -q).
void ByteBar(const CliContext& ctx, const std::string& what, int64_t done, int64_t total);

}  // namespace decima::client
