#include "client/cli/context.h"

#include <sys/types.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <random>

#include "client/cli/output.h"

namespace decima::client {

namespace {

// Where the address came from, for the hint.
std::string ServerSource(const GlobalFlags& g) {
  if (const char* env = std::getenv("DECIMA_SERVER"); env != nullptr && g.server == env) {
    return "from DECIMA_SERVER";
  }
  return g.server == kDefaultServer ? "the default" : "from --server";
}

void PrintUnreachable(const CliContext& ctx, const std::string& what, const std::string& detail) {
  const GlobalFlags& g = ctx.flags;
  const bool tls_options = ctx.TlsAsked();
  // Something accepts TCP there, so the server may well run: a plaintext call to a TLS server
  // fails exactly like this (issue 35 part 7: the hint used to ask only whether it runs).
  if (!tls_options && TcpPortAnswers(g.server, std::chrono::seconds(1))) {
    std::fprintf(stderr,
                 "decima: %s: cannot talk to decima-server at %s (%s): %s\n"
                 "  hint: something accepts connections there, so the server may serve TLS "
                 "(decima-server --tls-cert): add --tls, with --ca-cert CA.pem for a private CA "
                 "(or DECIMA_CA_CERT)\n",
                 what.c_str(), g.server.c_str(), ServerSource(g).c_str(), detail.c_str());
    return;
  }
  std::fprintf(stderr,
               "decima: %s: cannot reach decima-server at %s (%s): %s\n"
               "  hint: is the server running there? Start it with `decima-server --listen %s`, "
               "or point the client at it with --server HOST:PORT or DECIMA_SERVER.\n",
               what.c_str(), g.server.c_str(), ServerSource(g).c_str(), detail.c_str(),
               g.server.c_str());
  // A refused TLS handshake looks exactly like an unreachable server to gRPC.
  if (tls_options) {
    std::fprintf(stderr,
                 "  over TLS this is also what a refused handshake looks like: check --ca-cert "
                 "(the server's CA), and under mutual TLS --tls-cert/--tls-key (a client "
                 "certificate the server's --tls-client-ca signed)\n");
  }
}

}  // namespace

void AddGlobalFlags(CLI::App& app, GlobalFlags& g) {
  app.add_option("--server", g.server, "host:port of decima-server")
      ->envname("DECIMA_SERVER")
      ->capture_default_str();
  app.add_option("--token", g.token, "bearer token")->envname("DECIMA_TOKEN");
  app.add_flag("--json", g.json, "machine output: one JSON object per line on stdout");
  app.add_flag("--tls", g.tls, "connect with TLS (system roots unless --ca-cert)");
  app.add_option("--ca-cert,--tls-ca", g.ca_file, "PEM roots for TLS (implies --tls)")
      ->envname("DECIMA_CA_CERT");
  app.add_option("--tls-cert", g.cert_file,
                 "PEM client certificate for mutual TLS (implies --tls; with --tls-key)")
      ->envname("DECIMA_TLS_CERT");
  app.add_option("--tls-key", g.key_file, "PEM private key of --tls-cert")
      ->envname("DECIMA_TLS_KEY");
  app.add_option("--timeout", g.timeout_s, "deadline of each call, seconds")
      ->envname("DECIMA_TIMEOUT")
      ->capture_default_str();
  app.add_option("--reconnect", g.reconnect_s,
                 "how long to keep retrying a server that was reachable and went away, seconds")
      ->capture_default_str();
  app.add_flag("-q,--quiet", g.quiet, "no progress on stderr");
}

void AddOutputFlags(CLI::App* cmd, GlobalFlags& g) {
  cmd->add_option("-o,--output", g.output, "output format: json or wide")
      ->transform(CLI::IsMember({"json", "wide"}, CLI::ignore_case));
  cmd->add_flag("--json", g.json, "same as -o json");
}

int Connect(CliContext& ctx) {
  const GlobalFlags& g = ctx.flags;
  TlsFiles tls{g.tls, g.ca_file, g.cert_file, g.key_file};
  std::string connect_error;
  ctx.conn =
      Connect(g.server, g.token, tls,
              std::chrono::milliseconds(static_cast<int64_t>(g.timeout_s * 1000)), &connect_error);
  if (!ctx.conn.channel) {
    std::fprintf(stderr, "decima: %s\n", connect_error.c_str());
    return kUsage;
  }
  return kOk;
}

int EnsureReachable(CliContext& ctx, const std::string& what) {
  const auto limit = std::chrono::milliseconds(
      static_cast<int64_t>(std::min(5.0, std::max(0.1, ctx.flags.timeout_s)) * 1000));
  const auto deadline = std::chrono::system_clock::now() + limit;
  grpc::Channel& channel = *ctx.conn.channel;
  grpc_connectivity_state st = channel.GetState(/*try_to_connect=*/true);
  // A failed connect is tried twice more, 0.1 and 0.2 s later (gRPC's own backoff would wait a
  // second or more): one failure is not proof of a dead address (under ThreadSanitizer about one
  // connect in 60 to a live server fails with a clobbered errno, ENOENT), three in a row are;
  // a wrong address still fails within about 2 s.
  int failures = 0;
  // Bounded by the deadline: WaitForStateChange returns false when it passes.
  while (st != GRPC_CHANNEL_READY) {
    if (st == GRPC_CHANNEL_SHUTDOWN ||
        (st == GRPC_CHANNEL_TRANSIENT_FAILURE &&
         (++failures >= 3 || std::chrono::system_clock::now() >= deadline))) {
      PrintUnreachable(ctx, what, "connection refused or failed");
      return kUnavailable;
    }
    if (st == GRPC_CHANNEL_TRANSIENT_FAILURE) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100 * failures));
      grpc::experimental::ChannelResetConnectionBackoff(&channel);
      // The reset takes effect asynchronously: wait (briefly) for the channel to leave
      // TRANSIENT_FAILURE before asking it to connect again.
      channel.WaitForStateChange(
          GRPC_CHANNEL_TRANSIENT_FAILURE,
          std::min(deadline, std::chrono::system_clock::now() + std::chrono::seconds(1)));
      st = channel.GetState(/*try_to_connect=*/true);
      continue;
    }
    if (!channel.WaitForStateChange(st, deadline)) {
      PrintUnreachable(ctx, what, "no answer within " + FormatDuration(limit.count() / 1000.0));
      return kUnavailable;
    }
    st = channel.GetState(true);
  }
  ctx.ever_connected = true;
  return kOk;
}

int ConnectAndCheck(CliContext& ctx, const std::string& verb) {
  if (int rc = Connect(ctx); rc != kOk) return rc;
  return EnsureReachable(ctx, verb);
}

int Report(CliContext& ctx, const grpc::Status& s, const std::string& what) {
  const auto code = s.error_code();
  if (!ctx.ever_connected &&
      (code == grpc::StatusCode::UNAVAILABLE || code == grpc::StatusCode::DEADLINE_EXCEEDED)) {
    PrintUnreachable(ctx, what, StatusCodeName(code) + ": " + s.error_message());
    return kUnavailable;
  }
  std::fprintf(stderr, "decima: %s: %s: %s\n", what.c_str(), StatusCodeName(code).c_str(),
               TerminalSafe(s.error_message()).c_str());
  ctx.last_error = StatusCodeName(code) + ": " + s.error_message();
  if (code == grpc::StatusCode::FAILED_PRECONDITION &&
      s.error_message().find("active") != std::string::npos) {
    std::fprintf(stderr, "  hint: cancel it first (decima cancel JOB)\n");
  }
  // gRPC reports a refused handshake as UNAVAILABLE with a generic text: say what to check.
  if (code == grpc::StatusCode::UNAVAILABLE && ctx.TlsAsked()) {
    std::fprintf(stderr,
                 "decima: over TLS this is also what a refused handshake looks like: check "
                 "--ca-cert (the server's CA), and under mutual TLS --tls-cert/--tls-key (a "
                 "client certificate the server's --tls-client-ca signed)\n");
  }
  return ExitCodeFor(code);
}

int InputError(CliContext& ctx, const std::string& message) {
  std::fprintf(stderr, "decima: %s\n", message.c_str());
  ctx.last_error = message;
  return kUsage;
}

int ResolveJob(CliContext& ctx, const std::string& arg, std::string* name) {
  if (arg.rfind("jobs/", 0) == 0 || arg.size() >= 16) {
    *name = arg.rfind("jobs/", 0) == 0 ? arg : "jobs/" + arg;
    return kOk;
  }
  if (arg.empty()) {
    std::fprintf(stderr, "decima: JOB is empty\n");
    return kUsage;
  }
  auto stub = v1::Jobs::NewStub(ctx.conn.channel);
  std::vector<std::string> matches;
  v1::ListJobsRequest req;
  req.set_page_size(1000);
  for (int page = 0; page < 1000; ++page) {  // bounded: a million jobs
    v1::ListJobsResponse resp;
    grpc::Status s =
        WithRetry(ctx, [&] { return stub->ListJobs(ctx.conn.Context().get(), req, &resp); });
    if (!s.ok()) return Report(ctx, s, "resolve " + arg);
    for (const auto& j : resp.jobs()) {
      if (ShortId(j.name()).rfind(arg, 0) == 0) matches.push_back(j.name());
    }
    if (resp.next_page_token().empty()) break;
    req.set_page_token(resp.next_page_token());
  }
  if (matches.size() == 1) {
    *name = matches[0];
    return kOk;
  }
  if (matches.empty()) {
    std::fprintf(stderr, "decima: no job id starts with '%s' (decima list shows the jobs)\n",
                 arg.c_str());
    return kNotFound;
  }
  std::fprintf(stderr, "decima: '%s' is ambiguous: %zu jobs start with it:", arg.c_str(),
               matches.size());
  for (size_t i = 0; i < matches.size() && i < 10; ++i) {
    std::fprintf(stderr, " %s", ShortId(matches[i]).c_str());
  }
  std::fprintf(stderr, "%s\n", matches.size() > 10 ? " ..." : "");
  return kUsage;
}

int GetJobOf(CliContext& ctx, const std::string& arg, const std::string& verb, v1::Job* job) {
  v1::GetJobRequest req;
  if (int rc = ResolveJob(ctx, arg, req.mutable_name()); rc != kOk) return rc;
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  grpc::Status s = WithRetry(ctx, [&] { return jobs->GetJob(ctx.conn.Context().get(), req, job); });
  if (!s.ok()) return Report(ctx, s, verb + " " + req.name());
  return kOk;
}

const v1::Volume* GetVolume(CliContext& ctx, const std::string& name) {
  if (name.empty()) return nullptr;
  auto it = ctx.volumes.find(name);
  if (it != ctx.volumes.end()) return &it->second;
  auto stub = v1::Volumes::NewStub(ctx.conn.channel);
  v1::GetVolumeRequest req;
  req.set_name(name);
  v1::Volume vol;
  if (!stub->GetVolume(ctx.conn.Context().get(), req, &vol).ok()) return nullptr;
  return &(ctx.volumes[name] = vol);
}

int ListAllJobs(CliContext& ctx, const std::vector<v1::JobState>& states,
                std::vector<v1::Job>* out) {
  auto stub = v1::Jobs::NewStub(ctx.conn.channel);
  v1::ListJobsRequest req;
  for (auto s : states) req.add_states(s);
  req.set_page_size(1000);
  for (int page = 0; page < 1000; ++page) {
    v1::ListJobsResponse resp;
    grpc::Status s =
        WithRetry(ctx, [&] { return stub->ListJobs(ctx.conn.Context().get(), req, &resp); });
    if (!s.ok()) return Report(ctx, s, "list");
    for (auto& j : *resp.mutable_jobs()) out->push_back(std::move(j));
    if (resp.next_page_token().empty()) break;
    req.set_page_token(resp.next_page_token());
  }
  return kOk;
}

std::string NewRequestId() {
  std::random_device rd;
  std::mt19937_64 rng((uint64_t{rd()} << 32) ^ rd());
  char buf[40];
  uint64_t a = rng(), b = rng();
  std::snprintf(buf, sizeof buf, "%08x-%04x-4%03x-%04x-%012llx", static_cast<unsigned>(a >> 32),
                static_cast<unsigned>(a >> 16) & 0xffff, static_cast<unsigned>(a) & 0xfff,
                static_cast<unsigned>(b >> 48 & 0x3fff) | 0x8000,
                static_cast<unsigned long long>(b & 0xffffffffffffULL));
  return buf;
}

std::string ShellCommand(const CliContext& ctx, const std::string& verb, const std::string& job) {
  std::string s = "decima ";
  if (ctx.flags.server != kDefaultServer) s += "--server " + ctx.flags.server + " ";
  return s + verb + " " + ShortId(job);
}

void ByteBar(const CliContext& ctx, const std::string& what, int64_t done, int64_t total) {
  if (ctx.Quiet() || !ctx.stderr_tty) return;
  double f = total > 0 ? static_cast<double>(done) / total : 1.0;
  std::fprintf(stderr, "\r\033[K%s %5.1f%% of %s", what.c_str(), f * 100,
               FormatBytes(total).c_str());
  // A finished bar is erased: the path on stdout or the summary line is the record.
  if (done >= total) std::fprintf(stderr, "\r\033[K");
}

}  // namespace decima::client
