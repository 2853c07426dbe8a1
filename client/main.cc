// decima: the command-line client of decima-server. Data on stdout, progress on stderr.
#include <signal.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <optional>
#include <random>
#include <set>
#include <thread>

#include "client/batch.h"
#include "client/client_lib.h"
#include "client/dicomweb.h"
#include "grpc/health/v1/health.grpc.pb.h"

#ifndef DECIMA_VERSION
#define DECIMA_VERSION "unknown"
#endif

namespace fs = std::filesystem;
using namespace decima;
using namespace decima::client;

namespace {

const char* kExitCodes = R"(
Exit codes:
  0 success            1 error              2 usage
  3 job failed         4 job cancelled      5 timeout (deadline exceeded)
  6 not found          7 not authenticated, or permission denied
  8 server unavailable (also: TLS handshake refused)
  10 job succeeded but the reduction target was not reached (see the warning)
Several studies (submit DIR1 DIR2 ..., submit --each FOLDER, watch JOB1 JOB2 ...): 0 only
when every study succeeded; else 3 if any failed (its job FAILED, or its input was refused
before a job was made), else 4 if any was cancelled, else 10 if any stopped short of its
target. A folder with no volume in it is reported and skipped; it does not change the code.

Environment: DECIMA_SERVER (default 127.0.0.1:50051), DECIMA_TOKEN, DECIMA_TIMEOUT,
DECIMA_CA_CERT, DECIMA_TLS_CERT, DECIMA_TLS_KEY.)";

constexpr const char* kDefaultServer = "127.0.0.1:50051";

struct Globals {
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

Globals g;
Connection conn;
bool stderr_tty = false;
// Set after the first answer from the server: from then on UNAVAILABLE means "restarting" and
// is retried; before it, the address is probably wrong and the command fails at once. Atomic:
// the watchers of several jobs run on threads of their own.
std::atomic<bool> ever_connected{false};
// The last error Report printed ("INVALID_ARGUMENT: ..."), for the table of a batch.
std::string g_last_error;

bool JsonOut() { return g.json || g.output == "json"; }
bool Quiet() { return g.quiet || JsonOut(); }

std::string ToJson(const google::protobuf::Message& m) {
  std::string out;
  google::protobuf::util::JsonPrintOptions o;
  o.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(m, &out, o);
  return out;
}

std::string JsonString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", c);
      out += buf;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

// Where the address came from, for the hint.
std::string ServerSource() {
  if (const char* env = std::getenv("DECIMA_SERVER"); env != nullptr && g.server == env) {
    return "from DECIMA_SERVER";
  }
  return g.server == kDefaultServer ? "the default" : "from --server";
}

void PrintUnreachable(const std::string& what, const std::string& detail) {
  const bool tls_options = g.tls || !g.ca_file.empty() || !g.cert_file.empty();
  // Something accepts TCP there, so the server may well run: a plaintext call to a TLS server
  // fails exactly like this (issue 35 part 7: the hint used to ask only whether it runs).
  if (!tls_options && TcpPortAnswers(g.server, std::chrono::seconds(1))) {
    std::fprintf(stderr,
                 "decima: %s: cannot talk to decima-server at %s (%s): %s\n"
                 "  hint: something accepts connections there, so the server may serve TLS "
                 "(decima-server --tls-cert): add --tls, with --ca-cert CA.pem for a private CA "
                 "(or DECIMA_CA_CERT)\n",
                 what.c_str(), g.server.c_str(), ServerSource().c_str(), detail.c_str());
    return;
  }
  std::fprintf(stderr,
               "decima: %s: cannot reach decima-server at %s (%s): %s\n"
               "  hint: is the server running there? Start it with `decima-server --listen %s`, "
               "or point the client at it with --server HOST:PORT or DECIMA_SERVER.\n",
               what.c_str(), g.server.c_str(), ServerSource().c_str(), detail.c_str(),
               g.server.c_str());
  // A refused TLS handshake looks exactly like an unreachable server to gRPC.
  if (tls_options) {
    std::fprintf(stderr,
                 "  over TLS this is also what a refused handshake looks like: check --ca-cert "
                 "(the server's CA), and under mutual TLS --tls-cert/--tls-key (a client "
                 "certificate the server's --tls-client-ca signed)\n");
  }
}

// Prints a failed call as "decima: WHAT: CODE: message" and returns its exit code.
int Report(const grpc::Status& s, const std::string& what) {
  const auto code = s.error_code();
  if (!ever_connected &&
      (code == grpc::StatusCode::UNAVAILABLE || code == grpc::StatusCode::DEADLINE_EXCEEDED)) {
    PrintUnreachable(what, StatusCodeName(code) + ": " + s.error_message());
    return kUnavailable;
  }
  std::fprintf(stderr, "decima: %s: %s: %s\n", what.c_str(), StatusCodeName(code).c_str(),
               TerminalSafe(s.error_message()).c_str());
  g_last_error = StatusCodeName(code) + ": " + s.error_message();
  if (code == grpc::StatusCode::FAILED_PRECONDITION &&
      s.error_message().find("active") != std::string::npos) {
    std::fprintf(stderr, "  hint: cancel it first (decima cancel JOB)\n");
  }
  // gRPC reports a refused handshake as UNAVAILABLE with a generic text: say what to check.
  if (code == grpc::StatusCode::UNAVAILABLE &&
      (g.tls || !g.ca_file.empty() || !g.cert_file.empty())) {
    std::fprintf(stderr,
                 "decima: over TLS this is also what a refused handshake looks like: check "
                 "--ca-cert (the server's CA), and under mutual TLS --tls-cert/--tls-key (a "
                 "client certificate the server's --tls-client-ca signed)\n");
  }
  return ExitCodeFor(code);
}

// Before the first call: wait (at most 5 s, or --timeout if shorter) until the channel is
// connected, and fail at once with a hint when the address refuses connections or does not
// answer, instead of retrying for a minute and then printing gRPC's text.
int EnsureReachable(const std::string& what) {
  const auto limit = std::chrono::milliseconds(
      static_cast<int64_t>(std::min(5.0, std::max(0.1, g.timeout_s)) * 1000));
  const auto deadline = std::chrono::system_clock::now() + limit;
  grpc_connectivity_state st = conn.channel->GetState(/*try_to_connect=*/true);
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
      PrintUnreachable(what, "connection refused or failed");
      return kUnavailable;
    }
    if (st == GRPC_CHANNEL_TRANSIENT_FAILURE) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100 * failures));
      grpc::experimental::ChannelResetConnectionBackoff(conn.channel.get());
      // The reset takes effect asynchronously: wait (briefly) for the channel to leave
      // TRANSIENT_FAILURE before asking it to connect again.
      conn.channel->WaitForStateChange(
          GRPC_CHANNEL_TRANSIENT_FAILURE,
          std::min(deadline, std::chrono::system_clock::now() + std::chrono::seconds(1)));
      st = conn.channel->GetState(/*try_to_connect=*/true);
      continue;
    }
    if (!conn.channel->WaitForStateChange(st, deadline)) {
      PrintUnreachable(what, "no answer within " + FormatDuration(limit.count() / 1000.0));
      return kUnavailable;
    }
    st = conn.channel->GetState(true);
  }
  ever_connected = true;
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

// Retries a unary call while the server is UNAVAILABLE (restarting), up to --reconnect, saying
// so once; never before the first answer (then the address is wrong: fail fast). CANCELLED is
// retried too: the CLI never cancels a unary call itself, so it is a server that shut down with
// the call in flight (watch streams stay open through a drain, so the watch's last GetJob can
// land just as the draining server stops).
template <typename F>
grpc::Status WithRetry(F call) {
  auto until = std::chrono::steady_clock::now() +
               std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
  int wait_ms = 100;
  bool said = false;
  for (;;) {
    grpc::Status s = call();
    if (s.error_code() != grpc::StatusCode::UNAVAILABLE &&
        s.error_code() != grpc::StatusCode::CANCELLED) {
      if (s.ok()) ever_connected = true;
      return s;
    }
    if (!ever_connected || std::chrono::steady_clock::now() > until) return s;
    if (!said && !Quiet()) {
      std::fprintf(stderr, "decima: server unavailable (%s); retrying for up to %s\n",
                   TerminalSafe(s.error_message()).c_str(), FormatDuration(g.reconnect_s).c_str());
      said = true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms));
    wait_ms = std::min(wait_ms * 2, 2000);
  }
}

int TerminalColumns() {
  struct winsize ws {};
  if (::ioctl(2, TIOCGWINSZ, &ws) == 0 && ws.ws_col > 20) return ws.ws_col;
  return 100;
}

void ByteBar(const std::string& what, int64_t done, int64_t total) {
  if (Quiet() || !stderr_tty) return;
  double f = total > 0 ? static_cast<double>(done) / total : 1.0;
  std::fprintf(stderr, "\r\033[K%s %5.1f%% of %s", what.c_str(), f * 100,
               FormatBytes(total).c_str());
  // A finished bar is erased: the path on stdout or the summary line is the record.
  if (done >= total) std::fprintf(stderr, "\r\033[K");
}

double SecondsSince(const google::protobuf::Timestamp& t) {
  if (t.seconds() == 0 && t.nanos() == 0) return -1;
  const auto now = std::chrono::system_clock::now().time_since_epoch();
  return std::chrono::duration<double>(now).count() - (t.seconds() + t.nanos() / 1e9);
}

double Between(const google::protobuf::Timestamp& a, const google::protobuf::Timestamp& b) {
  if (a.seconds() == 0 || b.seconds() == 0) return -1;
  return (b.seconds() - a.seconds()) + (b.nanos() - a.nanos()) / 1e9;
}

std::string FormatTime(const google::protobuf::Timestamp& t) {
  if (t.seconds() == 0) return "-";
  std::time_t secs = static_cast<std::time_t>(t.seconds());
  std::tm tm{};
  localtime_r(&secs, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", &tm);
  return buf;
}

std::string ShortId(const std::string& name) {
  return name.rfind("jobs/", 0) == 0 ? name.substr(5) : name;
}

// The command that re-attaches to a job, with --server when it is not the default.
std::string Command(const std::string& verb, const std::string& job) {
  std::string s = "decima ";
  if (g.server != kDefaultServer) s += "--server " + g.server + " ";
  return s + verb + " " + ShortId(job);
}

// Ctrl-C while watching: the job goes on on the server; say so and how to come back.
char g_interrupt_message[1024];
void OnInterrupt(int) {
  ssize_t n = ::write(2, g_interrupt_message, std::strlen(g_interrupt_message));
  (void)n;
  ::_exit(130);
}
void ArmInterrupt(const std::string& job) {
  std::snprintf(g_interrupt_message, sizeof g_interrupt_message,
                "\ndecima: stopped watching %s; the job goes on on the server.\n"
                "  re-attach: %s\n  cancel it: %s\n",
                job.c_str(), Command("watch", job).c_str(), Command("cancel", job).c_str());
  struct sigaction sa {};
  sa.sa_handler = OnInterrupt;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
}

// Resolves JOB: "jobs/{id}", a full id, or a unique prefix of an id (as docker does).
int ResolveJob(const std::string& arg, std::string* name) {
  if (arg.rfind("jobs/", 0) == 0 || arg.size() >= 16) {
    *name = arg.rfind("jobs/", 0) == 0 ? arg : "jobs/" + arg;
    return kOk;
  }
  if (arg.empty()) {
    std::fprintf(stderr, "decima: JOB is empty\n");
    return kUsage;
  }
  auto stub = v1::Jobs::NewStub(conn.channel);
  std::vector<std::string> matches;
  v1::ListJobsRequest req;
  req.set_page_size(1000);
  for (int page = 0; page < 1000; ++page) {  // bounded: a million jobs
    v1::ListJobsResponse resp;
    grpc::Status s = WithRetry([&] { return stub->ListJobs(conn.Context().get(), req, &resp); });
    if (!s.ok()) return Report(s, "resolve " + arg);
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

// Volume display names by volume name, fetched once per command.
std::map<std::string, v1::Volume> g_volumes;
const v1::Volume* GetVolume(const std::string& name) {
  if (name.empty()) return nullptr;
  auto it = g_volumes.find(name);
  if (it != g_volumes.end()) return &it->second;
  auto stub = v1::Volumes::NewStub(conn.channel);
  v1::GetVolumeRequest req;
  req.set_name(name);
  v1::Volume vol;
  if (!stub->GetVolume(conn.Context().get(), req, &vol).ok()) return nullptr;
  return &(g_volumes[name] = vol);
}

std::string Percent(double f, int decimals = 0) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.*f%%", decimals, 100 * f);
  return buf;
}

double JobSeconds(const v1::Job& j) {
  if (j.start_time().seconds() == 0) return -1;
  if (j.end_time().seconds() != 0) return Between(j.start_time(), j.end_time());
  return SecondsSince(j.start_time());
}

// A table printed with columns as wide as their widest cell (kubectl's plain output).
// Every cell is passed through TerminalSafe: names and messages come from the server (issue 35
// part 7: a display name with escape sequences reached an admin's terminal).
void PrintTable(const std::vector<std::vector<std::string>>& raw_rows) {
  std::vector<std::vector<std::string>> rows = raw_rows;
  for (auto& r : rows) {
    for (auto& cell : r) cell = TerminalSafe(cell);
  }
  std::vector<size_t> width;
  for (const auto& r : rows) {
    if (width.size() < r.size()) width.resize(r.size(), 0);
    for (size_t c = 0; c < r.size(); ++c) width[c] = std::max(width[c], r[c].size());
  }
  for (const auto& r : rows) {
    std::string line;
    for (size_t c = 0; c < r.size(); ++c) {
      line += r[c];
      if (c + 1 < r.size()) line.append(width[c] - r[c].size() + 3, ' ');
    }
    std::printf("%s\n", line.c_str());
  }
}

std::vector<std::string> JobHeader(bool wide) {
  std::vector<std::string> h = {"NAME", "STATE",     "STAGE %", "INPUT",
                                "K",    "REDUCTION", "CREATED", "DURATION"};
  if (wide) {
    for (const char* c : {"ACHIEVED", "POLICY", "VIEWS", "ARTIFACTS", "MESSAGE"}) h.push_back(c);
  }
  return h;
}

std::vector<std::string> JobRow(const v1::Job& j, bool wide) {
  const v1::Volume* vol = GetVolume(j.spec().volume());
  std::string stage = "-";
  if (j.state() == v1::RUNNING && !j.progress().stage().empty()) {
    stage = j.progress().stage() + " " + Percent(j.progress().fraction());
  }
  std::vector<std::string> r = {ShortId(j.name()),
                                v1::JobState_Name(j.state()),
                                stage,
                                vol != nullptr ? vol->display_name() : j.spec().volume(),
                                std::to_string(j.spec().regions()),
                                Percent(j.spec().target_reduction()),
                                FormatTime(j.create_time()),
                                FormatDuration(JobSeconds(j))};
  if (wide) {
    const JobSummary s = SummarizeJob(j, 0);
    r.push_back(j.state() == v1::SUCCEEDED
                    ? Percent(s.achieved_reduction, 1) + (s.reached_target ? "" : " (short)")
                    : "-");
    std::string policy = v1::SimplifyPolicy_Name(j.spec().policy());
    for (char& c : policy) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    r.push_back(policy);
    std::string views;
    for (const auto& v : j.spec().views()) views += (views.empty() ? "" : " ") + v;
    r.push_back(views.empty() ? "-" : views);
    r.push_back(j.artifacts_size() > 0 ? std::to_string(j.artifacts_size()) + " files, " +
                                             FormatBytes(s.artifact_bytes)
                                       : "-");
    r.push_back(j.error().message().empty() ? "-" : j.error().message().substr(0, 80));
  }
  return r;
}

// After one page of a listing: true to fetch the next page (--all); else, when there is one,
// says how to get it (a JSON line, or a hint on stderr) and returns false.
bool ContinueListing(const std::string& next_page_token, bool all) {
  if (next_page_token.empty()) return false;
  if (all) return true;
  if (JsonOut()) {
    std::printf("{\"next_page_token\":%s}\n", JsonString(next_page_token).c_str());
  } else {
    std::fprintf(stderr, "more: --page-token %s (or --all)\n", next_page_token.c_str());
  }
  return false;
}

// `decima status`: kubectl describe for one job.
void DescribeJob(const v1::Job& j) {
  auto line = [](const char* key, const std::string& value) {
    std::printf("%-14s %s\n", key, TerminalSafe(value).c_str());
  };
  line("Name:", j.name());
  line("State:", v1::JobState_Name(j.state()));
  if (j.state() == v1::RUNNING || j.state() == v1::QUEUED) {
    const v1::Progress& p = j.progress();
    line("Progress:", p.stage().empty()
                          ? "-"
                          : Percent(OverallFraction(p.stage(), p.fraction(), JobWithCurve(j))) +
                                " overall, " + p.stage() + " " + Percent(p.fraction()) + " " +
                                p.message());
  }
  if (!j.error().message().empty()) line("Error:", j.error().message());
  const v1::Volume* vol = GetVolume(j.spec().volume());
  if (vol != nullptr) {
    std::string desc =
        vol->display_name() + " (" + vol->name() + ", " + v1::VolumeFormat_Name(vol->format());
    if (vol->dims_size() == 3) {
      char buf[128];
      std::snprintf(buf, sizeof buf, ", %lldx%lldx%lld voxels, %.3gx%.3gx%.3g mm",
                    static_cast<long long>(vol->dims(0)), static_cast<long long>(vol->dims(1)),
                    static_cast<long long>(vol->dims(2)), vol->spacing(0), vol->spacing(1),
                    vol->spacing(2));
      desc += buf;
    }
    if (!vol->modality().empty()) desc += ", " + vol->modality();
    desc += ", " + FormatBytes(vol->size_bytes()) + ")";
    line("Input:", desc);
  } else {
    line("Input:", j.spec().volume());
  }
  line("Request id:", j.request_id().empty() ? "-" : j.request_id());
  std::printf("Spec:\n");
  const v1::JobSpec& s = j.spec();
  std::printf("  regions %d, target_reduction %s, policy %s, error_tolerance %g\n", s.regions(),
              Percent(s.target_reduction(), 1).c_str(), v1::SimplifyPolicy_Name(s.policy()).c_str(),
              s.error_tolerance());
  std::string views, outputs;
  for (const auto& v : s.views()) views += (views.empty() ? "" : ", ") + v;
  for (const auto& o : s.outputs()) outputs += (outputs.empty() ? "" : ", ") + o;
  std::printf("  views %s, image_size %d, transfer_function %s\n", views.c_str(), s.image_size(),
              s.transfer_function().size() > 40 ? "(JSON)" : s.transfer_function().c_str());
  std::printf("  outputs %s, vtu_compression_level %d\n",
              outputs.empty() ? "(default)" : outputs.c_str(), s.vtu_compression_level());
  if (!s.label_map().empty()) std::printf("  label_map %s\n", s.label_map().c_str());
  std::printf("Times:\n");
  std::printf("  created %s, started %s, ended %s\n", FormatTime(j.create_time()).c_str(),
              FormatTime(j.start_time()).c_str(), FormatTime(j.end_time()).c_str());
  std::printf("  duration %s, attempts %d\n", FormatDuration(JobSeconds(j)).c_str(), j.attempts());
  if (j.state() == v1::SUCCEEDED) {
    std::printf("Result:\n");
    for (const auto& l : SummaryLines(SummarizeJob(j, vol != nullptr ? vol->size_bytes() : 0))) {
      std::printf("  %s\n", l.c_str());
    }
    for (const auto& l : FidelityLines(j.metrics_json())) std::printf("  %s\n", l.c_str());
    std::printf("Artifacts:\n");
    std::vector<std::vector<std::string>> rows = {{"  FILE", "SIZE", "SHA256"}};
    for (const auto& a : j.artifacts()) {
      rows.push_back({"  " + a.file_name(), FormatBytes(a.size_bytes()), a.sha256().substr(0, 12)});
    }
    PrintTable(rows);
  }
}

// The end of a watch: achieved reduction, sizes, bytes ratio, and the warning. Returns
// kTargetNotReached when the target was missed, kOk otherwise.
int PrintSummary(const v1::Job& job) {
  const v1::Volume* vol = GetVolume(job.spec().volume());
  const JobSummary s = SummarizeJob(job, vol != nullptr ? vol->size_bytes() : 0);
  if (JsonOut()) {
    std::printf(
        "{\"summary\":{\"job\":%s,\"target_reduction\":%g,\"achieved_reduction\":%g,"
        "\"reached_target\":%s,\"cells_before\":%lld,\"cells_after\":%lld,"
        "\"artifact_bytes\":%lld,\"input_bytes\":%lld}}\n",
        JsonString(job.name()).c_str(), s.target_reduction, s.achieved_reduction,
        s.reached_target ? "true" : "false", static_cast<long long>(s.cells_before),
        static_cast<long long>(s.cells_after), static_cast<long long>(s.artifact_bytes),
        static_cast<long long>(s.input_bytes));
    std::fflush(stdout);
  }
  // The warning is printed even with -q: it changes the exit code.
  for (const auto& l : SummaryLines(s)) {
    if (!g.quiet || l.rfind("WARNING", 0) == 0) std::fprintf(stderr, "decima: %s\n", l.c_str());
  }
  return s.reached_target ? kOk : kTargetNotReached;
}

// Watches a job until a final state, reconnecting with the last sequence on UNAVAILABLE.
// Returns the exit code and the final job in *final.
int Watch(const std::string& name, v1::Job* final) {
  auto stub = v1::Jobs::NewStub(conn.channel);
  ArmInterrupt(name);
  int64_t last = 0;
  bool bar_open = false;
  auto give_up = std::chrono::steady_clock::now() +
                 std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
  int wait_ms = 100;
  int attempts = 0;
  const auto watch_start = std::chrono::steady_clock::now();
  google::protobuf::Timestamp start_time;
  v1::Progress current;
  bool with_curve = false;   // from the snapshot's spec: the curve stage counts in the bar
  int64_t replay_until = 0;  // the snapshot's last_sequence: events up to it are replayed
  // Plain (non-TTY) lines: one per stage change, every 10 points of overall progress, or every
  // 15 s, so a log shows motion without one line per event.
  std::string plain_stage;
  int plain_decile = -1;
  auto plain_at = std::chrono::steady_clock::now();
  auto elapsed = [&] {
    const double s = SecondsSince(start_time);
    return s >= 0 ? s
                  : std::chrono::duration<double>(std::chrono::steady_clock::now() - watch_start)
                        .count();
  };
  auto draw = [&] {
    if (Quiet() || current.stage().empty()) return;
    if (stderr_tty) {
      std::string l = OverallBar(current, elapsed(), 24, with_curve) + "  " + current.message();
      l.resize(std::min<size_t>(l.size(), static_cast<size_t>(TerminalColumns() - 1)));
      std::fprintf(stderr, "\r\033[K%s", l.c_str());
      bar_open = true;
      return;
    }
    const int decile =
        static_cast<int>(OverallFraction(current.stage(), current.fraction(), with_curve) * 10);
    if (current.stage() == plain_stage && decile == plain_decile &&
        std::chrono::steady_clock::now() - plain_at < std::chrono::seconds(15)) {
      return;
    }
    plain_stage = current.stage();
    plain_decile = decile;
    plain_at = std::chrono::steady_clock::now();
    std::fprintf(stderr, "%s %s %s\n", ShortId(name).c_str(),
                 OverallBar(current, elapsed(), 0, with_curve).substr(3).c_str(),
                 TerminalSafe(current.message()).c_str());
  };
  auto say = [&](const std::string& text) {
    if (Quiet()) return;
    if (bar_open) std::fprintf(stderr, "\r\033[K");
    bar_open = false;
    std::fprintf(stderr, "%s\n", text.c_str());
  };
  for (;;) {
    v1::WatchJobRequest req;
    req.set_name(name);
    req.set_after_sequence(last);
    auto ctx = conn.Context(false);
    auto reader = stub->WatchJob(ctx.get(), req);
    v1::JobEvent ev;
    while (reader->Read(&ev)) {
      ever_connected = true;
      if (attempts > 0) {
        say("decima: reconnected to " + g.server + " after " + std::to_string(attempts) +
            " attempt(s)");
        attempts = 0;
      }
      give_up = std::chrono::steady_clock::now() +
                std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
      wait_ms = 100;
      if (JsonOut()) {
        std::printf("%s\n", ToJson(ev).c_str());
        std::fflush(stdout);
      }
      if (ev.has_snapshot()) {
        *final = ev.snapshot();
        with_curve = JobWithCurve(ev.snapshot());
        start_time = ev.snapshot().start_time();
        if (last == 0) replay_until = ev.snapshot().last_sequence();
        if (last == 0) {
          // The first contact: one line saying where the job is, no internal numbers.
          const v1::Job& j = ev.snapshot();
          std::string text = "decima: watching " + j.name() + ": " + v1::JobState_Name(j.state());
          if (j.state() == v1::RUNNING && !j.progress().stage().empty()) {
            text += ", " + j.progress().stage() + " " + Percent(j.progress().fraction());
          }
          if (j.start_time().seconds() != 0) {
            text += ", started " + FormatDuration(SecondsSince(j.start_time())) + " ago";
          }
          say(text);
          if (j.state() == v1::RUNNING) current = j.progress();
        }
        continue;
      }
      if (!ev.has_heartbeat()) last = ev.sequence();
      if (!ev.has_heartbeat() && ev.sequence() <= replay_until) {
        // Stored events replayed after the snapshot: the snapshot line said where the job is,
        // so they only bring the bar up to date.
        if (ev.has_progress()) current = ev.progress();
        if (ev.has_state_change() && ev.state_change().state() == v1::RUNNING) {
          start_time = ev.time();
        }
        if (ev.sequence() == replay_until) draw();
        continue;
      }
      if (ev.has_progress()) {
        if (start_time.seconds() == 0) start_time = ev.time();
        *final->mutable_progress() = ev.progress();
        current = ev.progress();
        draw();
      } else if (ev.has_heartbeat()) {
        if (stderr_tty) draw();  // the elapsed time moves while a stage is quiet
      } else if (ev.has_state_change()) {
        const auto& sc = ev.state_change();
        std::string text = ShortId(name) + " " + v1::JobState_Name(sc.state());
        if (sc.state() == v1::RUNNING) {
          start_time = ev.time();
        } else if (start_time.seconds() != 0) {
          text += " after " + FormatDuration(Between(start_time, ev.time()));
        }
        if (!sc.error().message().empty()) text += ": " + sc.error().message();
        say(text);
      }
    }
    grpc::Status s = reader->Finish();
    if (bar_open && !Quiet()) std::fprintf(stderr, "\n");
    bar_open = false;
    if (s.ok()) {
      // The stream ends after the final state (or at once for a job already final).
      v1::GetJobRequest greq;
      greq.set_name(name);
      grpc::Status gs = WithRetry([&] { return stub->GetJob(conn.Context().get(), greq, final); });
      if (!gs.ok()) return Report(gs, "get " + name);
      signal(SIGINT, SIG_DFL);
      // -q hides progress, never why a job did not succeed.
      if (g.quiet && !JsonOut() && final->state() != v1::SUCCEEDED) {
        std::fprintf(stderr, "decima: %s %s%s%s\n", name.c_str(),
                     v1::JobState_Name(final->state()).c_str(),
                     final->error().message().empty() ? "" : ": ",
                     TerminalSafe(final->error().message()).c_str());
      }
      if (final->state() == v1::SUCCEEDED) return PrintSummary(*final);
      return ExitCodeFor(final->state());
    }
    // UNAVAILABLE: the server is draining or restarting. CANCELLED: this client never cancels
    // a watch, so it is the server's shutdown cutting a call in flight; both end the same way.
    const bool server_went_away = s.error_code() == grpc::StatusCode::UNAVAILABLE ||
                                  s.error_code() == grpc::StatusCode::CANCELLED;
    if (server_went_away && ever_connected && std::chrono::steady_clock::now() < give_up) {
      ++attempts;
      const std::string why = s.error_code() == grpc::StatusCode::CANCELLED
                                  ? "the server closed the stream"
                                  : s.error_message();
      // One line per outage (the first reason), not one per attempt or per changing text.
      if (attempts == 1) {
        say("decima: watch " + name + ": server unavailable (" + why +
            "); reconnecting for up to " + FormatDuration(g.reconnect_s));
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms));
      wait_ms = std::min(wait_ms * 2, 1000);
      continue;
    }
    if (attempts > 0) {
      say("decima: watch " + name + ": gave up after " + std::to_string(attempts) +
          " reconnection attempts");
    }
    return Report(s, "watch " + name);
  }
}

// Ctrl-C while watching several jobs: they go on; say how to come back to all of them.
void ArmInterruptMany(const std::vector<std::string>& names) {
  std::string ids;
  for (const auto& n : names) ids += " " + ShortId(n);
  std::string again = "decima ";
  if (g.server != kDefaultServer) again += "--server " + g.server + " ";
  again += "watch" + ids;
  std::snprintf(g_interrupt_message, sizeof g_interrupt_message,
                "\ndecima: stopped watching %zu jobs; they go on on the server.\n"
                "  re-attach: %s\n",
                names.size(), again.c_str());
  struct sigaction sa {};
  sa.sa_handler = OnInterrupt;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
}

// How one of several watched jobs ended.
struct WatchOutcome {
  v1::Job final;
  int rc = kError;    // 0, kJobFailed, kJobCancelled, kTargetNotReached, or the watch's error
  std::string error;  // the watch's own failure ("UNAVAILABLE: ..."), else ""
};

// Follows several jobs at once: one thread per job, each with its own WatchJob stream
// (reconnecting with its last sequence while the server restarts, as Watch does), all printing
// plain lines prefixed with the job id — the first contact, each stage, every 10 points of
// overall progress, each state change — one line at a time. With --json the events go to
// stdout as JSON lines (each names its job). Returns when every job is final (or its watch
// failed); outcomes in the order of `names`.
std::vector<WatchOutcome> WatchMany(const std::vector<std::string>& names) {
  std::mutex mu;  // one whole line at a time on stdout and stderr
  auto say = [&](const std::string& text) {
    if (Quiet()) return;
    std::lock_guard<std::mutex> lock(mu);
    std::fprintf(stderr, "%s\n", text.c_str());
  };
  std::vector<WatchOutcome> out(names.size());
  auto follow = [&](size_t i) {
    const std::string& name = names[i];
    const std::string id = ShortId(name);
    auto stub = v1::Jobs::NewStub(conn.channel);
    int64_t last = 0, replay_until = 0;
    bool with_curve = false;
    std::string stage;
    int decile = -1;
    int attempts = 0;
    int wait_ms = 100;
    auto give_up = std::chrono::steady_clock::now() +
                   std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
    for (;;) {
      v1::WatchJobRequest req;
      req.set_name(name);
      req.set_after_sequence(last);
      auto ctx = conn.Context(false);
      auto reader = stub->WatchJob(ctx.get(), req);
      v1::JobEvent ev;
      while (reader->Read(&ev)) {
        ever_connected = true;
        if (attempts > 0)
          say(id + " reconnected after " + std::to_string(attempts) + " attempt(s)");
        attempts = 0;
        wait_ms = 100;
        give_up = std::chrono::steady_clock::now() +
                  std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
        if (JsonOut()) {
          std::lock_guard<std::mutex> lock(mu);
          std::printf("%s\n", ToJson(ev).c_str());
          std::fflush(stdout);
        }
        if (ev.has_snapshot()) {
          const v1::Job& j = ev.snapshot();
          with_curve = JobWithCurve(j);
          if (last == 0) {
            replay_until = j.last_sequence();
            std::string text = id + " " + v1::JobState_Name(j.state());
            if (j.state() == v1::RUNNING && !j.progress().stage().empty()) {
              stage = j.progress().stage();
              text += ", " + stage + " " + Percent(j.progress().fraction());
            }
            say(text);
          }
          continue;
        }
        if (ev.has_heartbeat()) continue;
        last = ev.sequence();
        if (ev.has_progress()) {
          const v1::Progress& p = ev.progress();
          const double f = OverallFraction(p.stage(), p.fraction(), with_curve);
          const int d = static_cast<int>(f * 10);
          // Replayed events (older than the snapshot) only bring the counters up to date.
          if ((p.stage() != stage || d != decile) && ev.sequence() > replay_until) {
            say(id + " " + Percent(f) + " " + p.stage() + " " + p.message());
          }
          stage = p.stage();
          decile = d;
        } else if (ev.has_state_change() && ev.sequence() > replay_until) {
          const auto& sc = ev.state_change();
          say(id + " " + v1::JobState_Name(sc.state()) +
              (sc.error().message().empty() ? "" : ": " + sc.error().message()));
        }
      }
      const grpc::Status s = reader->Finish();
      if (s.ok()) {
        // The stream ends after the final state (at once for a job already final).
        v1::GetJobRequest greq;
        greq.set_name(name);
        const grpc::Status gs =
            WithRetry([&] { return stub->GetJob(conn.Context().get(), greq, &out[i].final); });
        if (!gs.ok()) {
          out[i].rc = ExitCodeFor(gs.error_code());
          out[i].error = StatusCodeName(gs.error_code()) + ": " + gs.error_message();
          return;
        }
        const v1::Job& f = out[i].final;
        out[i].rc = f.state() == v1::SUCCEEDED
                        ? (SummarizeJob(f, 0).reached_target ? kOk : kTargetNotReached)
                        : ExitCodeFor(f.state());
        return;
      }
      const bool server_went_away = s.error_code() == grpc::StatusCode::UNAVAILABLE ||
                                    s.error_code() == grpc::StatusCode::CANCELLED;
      if (server_went_away && ever_connected && std::chrono::steady_clock::now() < give_up) {
        if (++attempts == 1) {
          say(id + " server unavailable (" + s.error_message() + "); reconnecting for up to " +
              FormatDuration(g.reconnect_s));
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms));
        wait_ms = std::min(wait_ms * 2, 1000);
        continue;
      }
      out[i].rc = ExitCodeFor(s.error_code());
      out[i].error = StatusCodeName(s.error_code()) + ": " + s.error_message();
      {
        std::lock_guard<std::mutex> lock(mu);
        std::fprintf(stderr, "decima: watch %s: %s\n", name.c_str(), out[i].error.c_str());
      }
      return;
    }
  };
  ArmInterruptMany(names);
  std::vector<std::thread> threads;
  threads.reserve(names.size());
  for (size_t i = 0; i < names.size(); ++i) threads.emplace_back(follow, i);
  for (auto& t : threads) t.join();
  signal(SIGINT, SIG_DFL);
  return out;
}

// One row of the table of several studies or jobs.
struct StudyRow {
  std::string job = "-";  // "jobs/..." once made
  std::string input;
  std::string state;  // a JobState name, or REFUSED (no job was made) or SKIPPED (no volume)
  std::string detail;
  int rc = kOk;  // this study's part of the exit code (BatchExitCode); SKIPPED rows have none
};

// A finished job's row: the state, and what a user wants next to it (the achieved reduction,
// or why it failed).
void SetOutcome(const WatchOutcome& o, StudyRow* row) {
  row->rc = o.rc;
  if (!o.error.empty()) {
    row->state = "UNKNOWN";
    row->detail = "watch: " + o.error;
    return;
  }
  row->state = v1::JobState_Name(o.final.state());
  if (o.final.state() == v1::SUCCEEDED) {
    const JobSummary s = SummarizeJob(o.final, 0);
    row->detail = "reduction " + Percent(s.achieved_reduction, 1) + " (target " +
                  Percent(s.target_reduction, 1) + ")" +
                  (s.reached_target ? "" : ", short: " + s.stop_message);
  } else {
    row->detail = o.final.error().message();
  }
}

// The table of a batch (stdout): JOB, INPUT, STATE, DETAIL; with --json one object per row.
void PrintStudyTable(const std::vector<StudyRow>& rows) {
  if (JsonOut()) {
    for (const auto& r : rows) {
      std::printf("{\"job\":%s,\"input\":%s,\"state\":%s,\"detail\":%s}\n",
                  JsonString(r.job == "-" ? "" : r.job).c_str(), JsonString(r.input).c_str(),
                  JsonString(r.state).c_str(), JsonString(r.detail).c_str());
    }
    std::fflush(stdout);
    return;
  }
  std::vector<std::vector<std::string>> table = {{"JOB", "INPUT", "STATE", "DETAIL"}};
  for (const auto& r : rows) {
    table.push_back({ShortId(r.job), r.input, r.state, r.detail.empty() ? "-" : r.detail});
  }
  PrintTable(table);
  std::fflush(stdout);
}

// "10 studies: 9 SUCCEEDED, 1 FAILED; 1 skipped" on stderr (`jobs`: "10 jobs: ...").
void PrintStudyCounts(const std::vector<StudyRow>& rows, bool jobs = false) {
  if (g.quiet) return;
  std::map<std::string, int> by_state;
  int studies = 0;
  for (const auto& r : rows) {
    ++by_state[r.state];
    if (r.state != "SKIPPED") ++studies;
  }
  std::string text =
      "decima: " + std::to_string(studies) +
      (jobs ? (studies == 1 ? " job" : " jobs") : (studies == 1 ? " study" : " studies"));
  std::string sep = ": ";
  for (const auto& [state, n] : by_state) {
    if (state == "SKIPPED") continue;
    text += sep + std::to_string(n) + " " + state;
    sep = ", ";
  }
  if (by_state.count("SKIPPED") != 0) {
    text += "; " + std::to_string(by_state["SKIPPED"]) + " skipped";
  }
  std::fprintf(stderr, "%s\n", text.c_str());
}

// Artifact kinds (as in --outputs) to the file names they produce, for fetch --only.
bool MatchesOnly(const std::string& file, const std::vector<std::string>& only) {
  if (only.empty()) return true;
  for (std::string o : only) {
    for (char& c : o) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    if (o == file) return true;
    if (o == "vtu" && file == "mesh.vtu") return true;
    if (o == "msh" && file == "mesh.msh") return true;
    if (o == "medit" && file == "mesh.mesh") return true;
    if (o == "glb" && file == "surfaces.glb") return true;
    if (o == "levels" && file == "mesh.levels") return true;
    if (o == "stl" && file.rfind("surface-", 0) == 0 && file.size() > 4 &&
        file.compare(file.size() - 4, 4, ".stl") == 0) {
      return true;
    }
    if (o == "labels" && file == "labels.nii.gz") return true;
    if (o == "segmentation" && file == "segmentation.png") return true;
    if (o == "report" && file == "report.html") return true;
    if (o == "curve" && file == "curve.png") return true;
    if (o == "metrics" && file == "metrics.json") return true;
    if (o == "images" && file.size() > 4 && file.compare(file.size() - 4, 4, ".png") == 0 &&
        file != "segmentation.png" && file != "curve.png") {
      return true;
    }
  }
  return false;
}

int Fetch(const v1::Job& job, const fs::path& out, const std::vector<std::string>& only) {
  if (job.state() != v1::SUCCEEDED) {
    std::fprintf(stderr, "decima: fetch %s: the job is %s%s%s\n", job.name().c_str(),
                 v1::JobState_Name(job.state()).c_str(), job.error().message().empty() ? "" : ": ",
                 TerminalSafe(job.error().message()).c_str());
    int code = ExitCodeFor(job.state());
    return code == kOk ? kError : code;
  }
  // Every name given must select something, so a typo is an error and not an empty fetch.
  for (const auto& o : only) {
    bool any = false;
    for (const auto& a : job.artifacts()) any = any || MatchesOnly(a.file_name(), {o});
    if (!any) {
      std::string names;
      for (const auto& a : job.artifacts()) names += " " + a.file_name();
      std::fprintf(stderr,
                   "decima: fetch --only %s: no such artifact in %s; it has:%s (or the kinds "
                   "vtu, msh, medit, stl, glb, labels, images, segmentation, report, curve, "
                   "metrics)\n",
                   o.c_str(), job.name().c_str(), names.c_str());
      return kUsage;
    }
  }
  int64_t total = 0;
  for (const auto& a : job.artifacts()) {
    if (!MatchesOnly(a.file_name(), only)) continue;
    fs::path path;
    grpc::Status s = WithRetry([&] {
      return DownloadArtifact(
          conn, a, out, [&](int64_t d, int64_t t) { ByteBar("fetch " + a.file_name(), d, t); },
          &path);
    });
    if (!s.ok()) return Report(s, "fetch " + a.name());
    total += a.size_bytes();
    if (JsonOut()) {
      std::printf("{\"artifact\":%s,\"path\":%s,\"size_bytes\":%lld}\n",
                  JsonString(a.file_name()).c_str(), JsonString(path.string()).c_str(),
                  static_cast<long long>(a.size_bytes()));
    } else {
      std::printf("%s\n", path.c_str());
    }
  }
  if (!job.metrics_json().empty() && MatchesOnly("metrics.json", only) &&
      !fs::exists(out / "metrics.json")) {
    std::ofstream(out / "metrics.json") << job.metrics_json();
  }
  if (!Quiet())
    std::fprintf(stderr, "decima: fetched %s into %s\n", FormatBytes(total).c_str(), out.c_str());
  std::fflush(stdout);
  return kOk;
}

void PrintJobLine(const v1::Job& j) {
  if (JsonOut()) {
    std::printf("%s\n", ToJson(j).c_str());
    return;
  }
  PrintTable({JobHeader(false), JobRow(j, false)});
}

std::string Sha256Hex(const std::string& text) { return Sha256HexOf(text); }

// An error of the client's own (no call failed): printed, and kept for a batch's table.
int InputError(const std::string& message) {
  std::fprintf(stderr, "decima: %s\n", message.c_str());
  g_last_error = message;
  return kUsage;
}

int UploadVolume(const fs::path& input, std::vector<InputFile> files,
                 const std::string& display_name, const std::string& series,
                 const std::string& request_id, std::string* name);

// Uploads the files of INPUT and creates a volume; returns its name in *name. With a job
// request id, the volume's request id is derived from it and the files, so a retried submit
// finds the same volume (and the server can tell a retry from a different request).
int MakeVolume(const fs::path& input, const std::string& series, const std::string& request_id,
               std::string* name) {
  std::vector<InputFile> files;
  std::string err;
  if (!CollectInputs(input, &files, &err) || !AddHeaderDataFiles(&files, &err)) {
    return InputError(err);
  }
  std::error_code ec;
  if (fs::is_directory(input, ec)) {
    const std::vector<std::string> dropped = KeepDicomFiles(&files);
    if (!dropped.empty() && !g.quiet) {
      std::string list;
      for (size_t i = 0; i < dropped.size() && i < 5; ++i) list += " " + dropped[i];
      std::fprintf(stderr,
                   "decima: warning: skipping %zu file(s) of %s that are not DICOM images:%s%s\n",
                   dropped.size(), input.c_str(), list.c_str(), dropped.size() > 5 ? " ..." : "");
    }
    if (files.empty()) {
      return InputError(input.string() +
                        ": no DICOM file in the folder (none has the DICM marker); give a "
                        "volume file or a folder of DICOM images");
    }
  }
  return UploadVolume(input, std::move(files), input.filename().string(), series, request_id, name);
}

// The upload and CreateVolume half of MakeVolume, for files already chosen (a batch's DICOM
// series). `input` names the volume in progress lines.
int UploadVolume(const fs::path& input, std::vector<InputFile> files,
                 const std::string& display_name, const std::string& series,
                 const std::string& request_id, std::string* name) {
  std::string err;
  if (!HashInputs(&files, &err)) return InputError(err);
  int64_t total = 0, sent = 0, present = 0;
  for (const auto& f : files) total += f.size;
  v1::CreateVolumeRequest req;
  std::string manifest;
  for (const auto& f : files) {
    int64_t resumed = 0;
    // One bar for the whole volume: the bytes of all its files.
    grpc::Status s = WithRetry([&] {
      return UploadBlob(
          conn, f,
          [&](int64_t d, int64_t) {
            if (d < f.size || resumed < f.size)
              ByteBar("upload " + input.filename().string(), sent + d, total);
          },
          4, &resumed);
    });
    if (!s.ok()) return Report(s, "upload " + f.path.string());
    if (resumed == f.size) present += f.size;
    if (resumed > 0 && resumed < f.size && !Quiet()) {
      std::fprintf(stderr, "\ndecima: resumed upload of %s at byte %lld of %lld\n", f.name.c_str(),
                   static_cast<long long>(resumed), static_cast<long long>(f.size));
    }
    sent += f.size;
    auto* vf = req.mutable_volume()->add_files();
    vf->set_path(f.name);
    vf->set_blob("blobs/" + f.sha256);
    manifest += f.name + "\n" + f.sha256 + "\n";
  }
  if (!Quiet() && present != total && stderr_tty) std::fprintf(stderr, "\r\033[K");
  req.mutable_volume()->set_display_name(display_name);
  req.mutable_volume()->set_series_instance_uid(series);
  req.set_request_id(
      request_id.empty()
          ? NewRequestId()
          : "vol-" + Sha256Hex(request_id + "\n" + series + "\n" + manifest).substr(0, 32));
  auto stub = v1::Volumes::NewStub(conn.channel);
  v1::Volume vol;
  grpc::Status s = WithRetry([&] { return stub->CreateVolume(conn.Context().get(), req, &vol); });
  if (!s.ok()) return Report(s, "create volume from " + input.string());
  if (!Quiet()) {
    // Said after CreateVolume: only the server knows whether these files are a volume already.
    if (vol.reused()) {
      std::fprintf(stderr, "decima: reusing %s: the same %zu file(s) as %s (%s)\n",
                   vol.name().c_str(), files.size(), input.c_str(), FormatBytes(total).c_str());
    } else if (present == total) {
      std::fprintf(stderr, "decima: %s already on the server (%zu file(s), %s)\n", input.c_str(),
                   files.size(), FormatBytes(total).c_str());
    } else if (!stderr_tty) {
      std::fprintf(stderr, "decima: uploaded %s (%zu file(s), %s)\n", input.c_str(), files.size(),
                   FormatBytes(total - present).c_str());
    }
    std::fprintf(stderr, "decima: %s = %s %s", vol.name().c_str(),
                 TerminalSafe(vol.display_name()).c_str(),
                 v1::VolumeFormat_Name(vol.format()).c_str());
    if (vol.dims_size() == 3) {
      std::fprintf(stderr, " %lldx%lldx%lld voxels, %.3gx%.3gx%.3g mm",
                   static_cast<long long>(vol.dims(0)), static_cast<long long>(vol.dims(1)),
                   static_cast<long long>(vol.dims(2)), vol.spacing(0), vol.spacing(1),
                   vol.spacing(2));
    }
    if (!vol.modality().empty()) std::fprintf(stderr, " %s", vol.modality().c_str());
    std::fprintf(stderr, ", %s\n", FormatBytes(vol.size_bytes()).c_str());
  }
  g_volumes[vol.name()] = vol;
  *name = vol.name();
  return kOk;
}

// True when this run's CreateVolume made `name` (not a volume it reused).
bool MadeBySubmit(const std::string& name) {
  auto it = g_volumes.find(name);
  return it != g_volumes.end() && !it->second.reused();
}

// Every page of ListJobs (bounded), newest first.
int ListAllJobs(const std::vector<v1::JobState>& states, std::vector<v1::Job>* out) {
  auto stub = v1::Jobs::NewStub(conn.channel);
  v1::ListJobsRequest req;
  for (auto s : states) req.add_states(s);
  req.set_page_size(1000);
  for (int page = 0; page < 1000; ++page) {
    v1::ListJobsResponse resp;
    grpc::Status s = WithRetry([&] { return stub->ListJobs(conn.Context().get(), req, &resp); });
    if (!s.ok()) return Report(s, "list");
    for (auto& j : *resp.mutable_jobs()) out->push_back(std::move(j));
    if (resp.next_page_token().empty()) break;
    req.set_page_token(resp.next_page_token());
  }
  return kOk;
}

// "7d", "12h", "30m", "45s" -> seconds; false if malformed.
bool ParseAge(const std::string& s, double* seconds) {
  if (s.size() < 2) return false;
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size() - 1 || !(v >= 0)) return false;
  switch (s.back()) {
    case 's':
      *seconds = v;
      return true;
    case 'm':
      *seconds = v * 60;
      return true;
    case 'h':
      *seconds = v * 3600;
      return true;
    case 'd':
      *seconds = v * 86400;
      return true;
    default:
      return false;
  }
}

// -o FORMAT and --json on a subcommand (kubectl puts -o after the verb; the global --json of
// earlier releases keeps working).
void AddOutputFlags(CLI::App* cmd) {
  cmd->add_option("-o,--output", g.output, "output format: json or wide")
      ->transform(CLI::IsMember({"json", "wide"}, CLI::ignore_case));
  cmd->add_flag("--json", g.json, "same as -o json");
}

}  // namespace

int main(int argc, char** argv) {
  stderr_tty = ::isatty(2) != 0;
  CLI::App app{
      "decima: submit medical volumes to a decima-server, watch the jobs, fetch the "
      "meshes and images"};
  app.footer(kExitCodes);
  app.require_subcommand(1);
  app.set_version_flag("--version", std::string("decima ") + DECIMA_VERSION);
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

  // submit
  auto* submit = app.add_subcommand(
      "submit",
      "upload a volume (file or DICOM folder) and queue a job; several INPUTs or --each: one "
      "job per study found in them");
  std::vector<std::string> inputs;
  fs::path each;
  std::string input, label_map, policy = "field", tf, fault, request_id, series;
  fs::path out;
  // Unset options stay unset in the request: the server owns the defaults.
  std::optional<int> regions, image_size, vtu_level;
  std::optional<double> reduction, tolerance;
  std::vector<double> means;
  std::vector<std::string> weights, views, view_list, outputs, only;
  bool watch_flag = false;
  submit->add_option("INPUT", inputs,
                     "volume file (.nii, .nii.gz, .mha, .mhd + data, .nrrd, .nhdr + data) or "
                     "DICOM folder (or --dicomweb); several: a batch, one job per study found "
                     "in each (a volume file, or a DICOM series by SeriesInstanceUID)");
  submit->add_option("--each", each,
                     "a batch of every entry of FOLDER (its subfolders and volume files), one "
                     "job per study found; a subfolder with no volume is reported and skipped");
  // DICOMweb pull (client/dicomweb.h): shared by `submit --dicomweb` and `pull`.
  DicomWebPull web;
  std::string web_token_file;
  fs::path pull_out;
  // `submit` has its own --series (the series to process), which also names the series to pull.
  auto add_dicomweb = [&](CLI::App* cmd, bool is_pull) {
    auto* url = cmd->add_option("--dicomweb", web.base_url,
                                "DICOMweb base URL: pull the series by WADO-RS instead of INPUT");
    auto* study = cmd->add_option("--study", web.study_uid, "StudyInstanceUID to pull");
    if (is_pull) {
      cmd->add_option("--series", web.series_uid, "SeriesInstanceUID (default: the whole study)")
          ->needs(study);
    }
    cmd->add_option("--dicomweb-user", web.user, "NAME:PASSWORD for HTTP basic auth")
        ->envname("DECIMA_DICOMWEB_USER");
    cmd->add_option("--dicomweb-token-file", web_token_file, "bearer token for the DICOMweb server")
        ->check(CLI::ExistingFile);
    cmd->add_option("--dicomweb-ca", web.ca_file, "PEM roots for https (default: the system's)")
        ->check(CLI::ExistingFile);
    url->needs(study);
    study->needs(url);
    if (is_pull) {
      url->required();
      study->required();
    }
  };
  add_dicomweb(submit, false);
  submit->add_option("--regions,-k", regions, "K regions of the segmentation (2..8, default 3)");
  submit->add_option("--class-means", means, "K class means instead of k-means")->delimiter(',');
  submit->add_option("--label-map", label_map,
                     "a label map on the same grid (replaces the level set)");
  submit->add_option("--reduction", reduction,
                     "target_reduction: fraction of cells to remove (0..0.99, default 0.5; 0 = "
                     "no target, stop on --tolerance)");
  submit->add_option("--policy", policy, "simplification policy: paper, tetfusion or field")
      ->transform(CLI::IsMember({"paper", "tetfusion", "field"}, CLI::ignore_case))
      ->capture_default_str();
  submit->add_option("--tolerance", tolerance, "error tolerance (>= 0; default 0 = none)");
  submit->add_option("--weight", weights,
                     "weight override NAME=VALUE (w_r/regional, w_g/gradient, w_s/shape, "
                     "w_v/volume, w_n/neighbour)");
  submit
      ->add_option("--views", view_list,
                   "render views, comma-separated: anterior, posterior, left, lateral, right, "
                   "superior, inferior, oblique or AZIMUTH:ELEVATION (default anterior)")
      ->delimiter(',');
  submit->add_option("--view", views, "one render view (repeatable), e.g. --view 30:20");
  submit->add_option("--image-size", image_size, "rendered image size, pixels (default 512)");
  submit->add_option("--transfer-function", tf, "preset name, auto, or JSON");
  submit
      ->add_option(
          "--outputs", outputs,
          "artifacts to produce, comma-separated: vtu, msh, medit, stl, glb, levels, labels, "
          "images, segmentation, report, curve (default vtu,labels,images,segmentation,report; "
          "metrics.json always; stl = one closed surface per region, "
          "surface-region_<r>.stl; glb = all of them, named and coloured, in surfaces.glb; "
          "levels = mesh.levels, the collapse record down to 90 %, from which any level of "
          "detail can be extracted later (field policy; the run goes down to 90 %); "
          "curve = diff1 against cells removed, one more "
          "simplification per 10 % step)")
      ->delimiter(',')
      ->transform(CLI::IsMember({"vtu", "msh", "medit", "stl", "glb", "levels", "labels",
                                 "images", "segmentation", "report", "curve"},
                                CLI::ignore_case));
  submit
      ->add_option("--vtu-level", vtu_level,
                   "zlib level of mesh.vtu: 0 uncompressed, 1 fastest (default) .. 9 smallest")
      ->check(CLI::Range(0, 9));
  submit->add_option("--series", series,
                     "DICOM: the SeriesInstanceUID to use when the folder holds several series "
                     "(with --dicomweb: the series to pull)");
  submit->add_option("--request-id", request_id,
                     "idempotency key (default: a new UUID); reused with other parameters it is "
                     "refused (ALREADY_EXISTS)");
  // Test seam (server/faults.h): sent as metadata, read only by a server run with --allow-faults.
  submit->add_option("--fault", fault, "test-only fault injection")->group("");
  submit->add_flag("--watch", watch_flag, "watch the job until it ends");
  submit->add_option("--out", out,
                     "download the artifacts here when it succeeds (implies --watch)");
  submit->add_option("--only", only, "with --out: download only these artifacts");
  AddOutputFlags(submit);

  auto* watch = app.add_subcommand(
      "watch", "stream a job's progress until it ends (several jobs: all at once, one table)");
  std::string job_arg;
  std::vector<std::string> job_args, watch_args;
  watch->add_option("JOB", watch_args, "job ids, unique id prefixes, or jobs/{id}")->required();
  AddOutputFlags(watch);
  auto* status =
      app.add_subcommand("status", "describe a job: spec, input, times, result, artifacts");
  status->alias("describe");
  status->add_option("JOB", job_arg, "job id, unique id prefix, or jobs/{id}")->required();
  AddOutputFlags(status);
  auto* list = app.add_subcommand("list", "list jobs as a table, newest first");
  list->alias("ls");
  std::vector<std::string> states;
  int page_size = 50;
  std::string page_token;
  bool all = false;
  list->add_option("--state", states,
                   "only these states (queued, running, succeeded, failed, cancelled; any case)")
      ->delimiter(',');
  list->add_option("--page-size", page_size, "jobs per page")->capture_default_str();
  list->add_option("--page-token", page_token, "continue a listing");
  list->add_flag("--all", all, "follow every page");
  AddOutputFlags(list);
  auto* cancel = app.add_subcommand("cancel", "cancel a job (waits until it stopped)");
  cancel->add_option("JOB", job_arg, "job id, unique id prefix, or jobs/{id}")->required();
  AddOutputFlags(cancel);
  auto* retry = app.add_subcommand("retry", "queue a failed or cancelled job again");
  retry->add_option("JOB", job_arg, "job id, unique id prefix, or jobs/{id}")->required();
  retry->add_flag("--watch", watch_flag, "watch the job until it ends");
  AddOutputFlags(retry);
  auto* fetch = app.add_subcommand("fetch", "download a succeeded job's artifacts");
  fetch->add_option("JOB", job_arg, "job id, unique id prefix, or jobs/{id}")->required();
  fetch->add_option("--out", out, "destination folder")->required();
  fetch->add_option("--only", only,
                    "only these artifacts: file names (mesh.vtu) or kinds (vtu, msh, medit, "
                    "labels, images, segmentation, report, curve, metrics)");
  AddOutputFlags(fetch);
  auto* del = app.add_subcommand("delete", "delete finished jobs with their artifacts");
  del->alias("rm");
  bool with_volume = false;
  del->add_option("JOB", job_args, "job ids, unique id prefixes, or jobs/{id}")->required();
  del->add_flag("--volume", with_volume,
                "also delete each job's input volume when no other job uses it");
  AddOutputFlags(del);
  auto* prune = app.add_subcommand(
      "prune", "delete finished jobs and the volumes no job uses (a dry run unless --force)");
  std::vector<std::string> prune_states;
  std::string older_than;
  bool force = false;
  prune
      ->add_option("--state", prune_states,
                   "only jobs in these final states (succeeded, failed, cancelled; default all "
                   "three)")
      ->delimiter(',');
  prune->add_option("--older-than", older_than,
                    "only jobs that ended before this age: 30m, 12h, 7d");
  prune->add_flag("-f,--force", force, "delete; without it prune only lists what it would delete");
  AddOutputFlags(prune);
  auto* health = app.add_subcommand("health", "check that the server is serving");
  AddOutputFlags(health);
  auto* version = app.add_subcommand("version", "print the client's version and the server's");
  AddOutputFlags(version);
  auto* pull = app.add_subcommand("pull", "download a DICOM series or study by WADO-RS");
  add_dicomweb(pull, true);
  pull->add_option("--out", pull_out, "destination folder")->required();
  AddOutputFlags(pull);

  auto* series_cmd = app.add_subcommand(
      "series", "list the series the server received by DICOM C-STORE and what became of them");
  int series_page_size = 50;
  std::string series_page_token;
  bool series_all = false;
  series_cmd->add_option("--page-size", series_page_size, "series per page")->capture_default_str();
  series_cmd->add_option("--page-token", series_page_token, "continue a listing");
  series_cmd->add_flag("--all", series_all, "follow every page");
  AddOutputFlags(series_cmd);
  auto* series_delete = series_cmd->add_subcommand(
      "delete",
      "remove a received series' waiting instances (not yet in a job) and free their blobs");
  std::string series_delete_uid, series_delete_from;
  series_delete->add_option("SERIES_UID", series_delete_uid, "the SeriesInstanceUID")->required();
  series_delete->add_option("--from", series_delete_from,
                            "only the instances sent by this calling AE title (default: every "
                            "sender's you may delete)");

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    int rc = app.exit(e);
    return rc == 0 ? kOk : kUsage;
  }

  // DICOMweb: pull into a folder first; `submit` then uploads it like any DICOM folder.
  std::optional<fs::path> pulled_dir;
  if ((*pull || *submit) && !web.base_url.empty()) {
    if (*submit && (!inputs.empty() || !each.empty())) {
      std::fprintf(stderr, "decima: submit: give INPUT (or --each) or --dicomweb, not both\n");
      return kUsage;
    }
    if (!web_token_file.empty()) {
      std::ifstream in(web_token_file);
      std::getline(in, web.bearer_token);
      if (web.bearer_token.empty()) {
        std::fprintf(stderr, "decima: --dicomweb-token-file %s: empty\n", web_token_file.c_str());
        return kUsage;
      }
    }
    fs::path dir = pull_out;
    if (*submit) {
      web.series_uid = series;
      char tmpl[] = "/tmp/decima-dicomweb-XXXXXX";
      if (::mkdtemp(tmpl) == nullptr) {
        std::fprintf(stderr, "decima: cannot create a temporary folder\n");
        return kError;
      }
      dir = tmpl;
      pulled_dir = dir;
    }
    DicomWebResult pulled;
    std::string err;
    const bool ok = PullDicomWeb(web, dir, &pulled, &err);
    if (!ok) {
      if (pulled_dir) fs::remove_all(*pulled_dir);
      std::fprintf(stderr, "decima: dicomweb: %s\n", err.c_str());
      return kError;
    }
    if (JsonOut() && *pull) {
      std::printf("{\"instances\":%d,\"bytes\":%lld,\"seconds\":%.4f,\"out\":\"%s\"}\n",
                  pulled.instances, static_cast<long long>(pulled.bytes), pulled.seconds,
                  dir.c_str());
    } else if (!g.quiet) {
      std::fprintf(stderr, "decima: pulled %d instances (%lld bytes) by WADO-RS in %.3f s\n",
                   pulled.instances, static_cast<long long>(pulled.bytes), pulled.seconds);
    }
    if (*pull) return kOk;
    input = dir.string();
  }
  // Several inputs, or --each: a batch, one job per study (client/batch.h).
  const bool batch = *submit && (inputs.size() > 1 || !each.empty());
  if (*submit && inputs.size() == 1 && !batch) input = inputs[0];
  if (*submit && input.empty() && !batch) {
    std::fprintf(stderr, "decima: submit: INPUT or --dicomweb URL --study UID is required\n");
    return kUsage;
  }
  // The pulled copy is only needed until the upload is done.
  struct RemovePulled {
    std::optional<fs::path>* dir;
    ~RemovePulled() {
      std::error_code ec;
      if (*dir) fs::remove_all(**dir, ec);
    }
  } remove_pulled{&pulled_dir};

  TlsFiles tls{g.tls, g.ca_file, g.cert_file, g.key_file};
  std::string connect_error;
  conn =
      Connect(g.server, g.token, tls,
              std::chrono::milliseconds(static_cast<int64_t>(g.timeout_s * 1000)), &connect_error);
  if (!conn.channel) {
    std::fprintf(stderr, "decima: %s\n", connect_error.c_str());
    return kUsage;
  }
  auto jobs = v1::Jobs::NewStub(conn.channel);

  if (*version) {
    auto stub = grpc::health::v1::Health::NewStub(conn.channel);
    grpc::health::v1::HealthCheckRequest req;
    grpc::health::v1::HealthCheckResponse resp;
    // At most 2 s: the client's version is the answer; the server's reachability an extra.
    auto ctx = conn.Context();
    ctx->set_deadline(
        std::chrono::system_clock::now() +
        std::chrono::milliseconds(static_cast<int64_t>(std::min(2.0, g.timeout_s) * 1000)));
    grpc::Status s = stub->Check(ctx.get(), req, &resp);
    if (JsonOut()) {
      std::printf("{\"client\":%s,\"server\":%s,\"server_reachable\":%s}\n",
                  JsonString(DECIMA_VERSION).c_str(), JsonString(g.server).c_str(),
                  s.ok() ? "true" : "false");
    } else {
      std::printf("decima %s\nserver %s %s\n", DECIMA_VERSION, g.server.c_str(),
                  s.ok() ? "reachable" : "unreachable");
    }
    return kOk;
  }

  // Fail fast with a hint when nothing answers at the address.
  if (int rc = EnsureReachable(app.get_subcommands()[0]->get_name()); rc != kOk) return rc;

  if (*health) {
    auto stub = grpc::health::v1::Health::NewStub(conn.channel);
    grpc::health::v1::HealthCheckRequest req;
    grpc::health::v1::HealthCheckResponse resp;
    grpc::Status s = stub->Check(conn.Context().get(), req, &resp);
    if (!s.ok()) return Report(s, "health " + g.server);
    std::string st = grpc::health::v1::HealthCheckResponse::ServingStatus_Name(resp.status());
    if (JsonOut()) {
      std::printf("{\"server\":%s,\"status\":\"%s\"}\n", JsonString(g.server).c_str(), st.c_str());
    } else {
      std::printf("%s %s\n", g.server.c_str(), st.c_str());
    }
    return resp.status() == grpc::health::v1::HealthCheckResponse::SERVING ? kOk : kUnavailable;
  }

  if (*submit) {
    v1::CreateJobRequest req;
    auto* spec = req.mutable_spec();
    // "--views 30,20" splits into "30" and "20", never views on their own: join such pairs.
    std::vector<std::string> all_views;
    for (size_t i = 0; i < view_list.size(); ++i) {
      auto number = [](const std::string& s) {
        char* end = nullptr;
        std::strtod(s.c_str(), &end);
        return !s.empty() && end == s.c_str() + s.size();
      };
      if (number(view_list[i]) && i + 1 < view_list.size() && number(view_list[i + 1])) {
        all_views.push_back(view_list[i] + ":" + view_list[i + 1]);
        ++i;
      } else {
        all_views.push_back(view_list[i]);
      }
    }
    all_views.insert(all_views.end(), views.begin(), views.end());
    // Everything of the spec but its volume, from the flags (the same for every study of a
    // batch).
    auto fill_spec = [&](v1::JobSpec* spec) -> int {
      if (regions) spec->set_regions(*regions);
      for (double m : means) spec->add_class_means(m);
      if (reduction) spec->set_target_reduction(*reduction);
      spec->set_policy(policy == "paper"       ? v1::PAPER
                       : policy == "tetfusion" ? v1::TETFUSION
                                               : v1::FIELD);
      if (tolerance) spec->set_error_tolerance(*tolerance);
      for (const auto& w : weights) {
        auto eq = w.find('=');
        if (eq == std::string::npos) {
          std::fprintf(stderr, "decima: --weight %s: expected NAME=VALUE\n", w.c_str());
          return kUsage;
        }
        std::string name = w.substr(0, eq);
        for (char& c : name) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
        double value = 0;
        try {
          value = std::stod(w.substr(eq + 1));
        } catch (...) {
          std::fprintf(stderr, "decima: --weight %s: VALUE is not a number\n", w.c_str());
          return kUsage;
        }
        v1::ErrorWeights* ew = spec->mutable_weights();
        if (name == "w_r" || name == "regional") {
          ew->set_regional(value);
        } else if (name == "w_g" || name == "gradient") {
          ew->set_gradient(value);
        } else if (name == "w_s" || name == "shape") {
          ew->set_shape(value);
        } else if (name == "w_v" || name == "volume") {
          ew->set_volume(value);
        } else if (name == "w_n" || name == "neighbour") {
          ew->set_neighbour(value);
        } else {
          std::fprintf(stderr, "decima: --weight %s: unknown weight (w_r, w_g, w_s, w_v, w_n)\n",
                       w.c_str());
          return kUsage;
        }
      }
      for (const auto& v : all_views) spec->add_views(v);
      if (image_size) spec->set_image_size(*image_size);
      spec->set_transfer_function(tf);
      for (const auto& o : outputs) spec->add_outputs(o);
      if (vtu_level) spec->set_vtu_compression_level(*vtu_level);
      return kOk;
    };
    if (batch) {
      // One label map is on one volume's grid, one series UID picks within one folder: neither
      // means anything for several studies.
      if (!label_map.empty() || !series.empty()) {
        std::fprintf(stderr,
                     "decima: submit: --label-map and --series take one INPUT, not a batch\n");
        return kUsage;
      }
      v1::JobSpec common;
      if (int frc = fill_spec(&common); frc != kOk) return frc;
      std::vector<fs::path> sources;
      std::string err;
      if (!each.empty() && !EachEntry(each, &sources, &err)) {
        std::fprintf(stderr, "decima: %s\n", err.c_str());
        return kUsage;
      }
      for (const auto& i : inputs) sources.emplace_back(i);
      std::vector<StudyRow> rows;
      std::vector<std::string> names;   // the jobs made, in table order
      std::vector<size_t> job_rows;     // their rows
      std::vector<std::string> labels;  // the study labels of the jobs, for --out folders
      int fatal = kOk;                  // the server went away or refused the caller: stop
      int number = 0;
      for (const auto& source : sources) {
        std::vector<Study> studies;
        if (!FindStudies(source, &studies, &err) || studies.empty()) {
          const std::string why =
              err.empty() ? "no volume in it (no DICOM file, no .nii, .nii.gz, .mha, .mhd, "
                            ".nrrd or .nhdr)"
                          : err;
          std::fprintf(stderr, "decima: skipped %s: %s\n", source.c_str(), why.c_str());
          rows.push_back({"-", source.string(), "SKIPPED", why, kOk});
          err.clear();
          continue;
        }
        for (const Study& study : studies) {
          if (!Quiet())
            std::fprintf(stderr, "decima: study %d: %s\n", ++number, study.label.c_str());
          // A batch's request id gives each study its own, stable across retries of the batch.
          const std::string rid =
              request_id.empty() ? "" : request_id + "/" + Sha256Hex(study.label).substr(0, 16);
          g_last_error.clear();
          v1::CreateJobRequest jreq;
          *jreq.mutable_spec() = common;
          int vrc = study.dicom()
                        ? UploadVolume(study.input, study.files, study.display_name,
                                       study.series_uid, rid, jreq.mutable_spec()->mutable_volume())
                        : MakeVolume(study.input, "", rid, jreq.mutable_spec()->mutable_volume());
          if (vrc == kOk) {
            jreq.set_request_id(rid.empty() ? NewRequestId() : rid);
            v1::Job job;
            grpc::Status s = WithRetry([&] {
              auto ctx = conn.Context();
              if (!fault.empty()) ctx->AddMetadata("decima-test-fault", fault);
              return jobs->CreateJob(ctx.get(), jreq, &job);
            });
            if (s.ok()) {
              rows.push_back({job.name(), study.label, v1::JobState_Name(job.state()), "", kOk});
              names.push_back(job.name());
              job_rows.push_back(rows.size() - 1);
              labels.push_back(study.label);
              continue;
            }
            vrc = Report(s, "submit " + study.label);
            // As for one INPUT: no volume left behind by a refusal.
            if (request_id.empty() && MadeBySubmit(jreq.spec().volume())) {
              auto vstub = v1::Volumes::NewStub(conn.channel);
              v1::DeleteVolumeRequest dreq;
              dreq.set_name(jreq.spec().volume());
              v1::DeleteVolumeResponse dresp;
              (void)vstub->DeleteVolume(conn.Context().get(), dreq, &dresp);
            }
          }
          rows.push_back({"-", study.label, "REFUSED", g_last_error, kJobFailed});
          if (vrc == kUnavailable || vrc == kUnauthenticated) {
            fatal = vrc;
            break;
          }
        }
        if (fatal != kOk) break;
      }
      if (fatal != kOk) {
        PrintStudyTable(rows);
        std::fprintf(stderr, "decima: submit: stopped the batch after %zu stud%s: %s\n",
                     rows.size(), rows.size() == 1 ? "y" : "ies", g_last_error.c_str());
        return fatal;
      }
      if (names.empty() && std::none_of(rows.begin(), rows.end(),
                                        [](const StudyRow& r) { return r.state == "REFUSED"; })) {
        std::fprintf(stderr, "decima: submit: no volume found in any INPUT or --each entry\n");
        return kUsage;
      }
      if ((watch_flag || !out.empty()) && !names.empty()) {
        const std::vector<WatchOutcome> outcomes = WatchMany(names);
        std::vector<std::string> taken;
        for (size_t k = 0; k < names.size(); ++k) {
          StudyRow& row = rows[job_rows[k]];
          SetOutcome(outcomes[k], &row);
          if (out.empty() || outcomes[k].final.state() != v1::SUCCEEDED) continue;
          // Each study's artifacts in a folder of its own, named after the study.
          const int frc =
              Fetch(outcomes[k].final, out / ArtifactFolderName(labels[k], &taken), only);
          if (frc != kOk) {
            row.rc = frc;
            row.detail += "; fetch failed";
          }
        }
      }
      PrintStudyTable(rows);
      PrintStudyCounts(rows);
      std::vector<int> codes;
      for (const auto& r : rows) {
        if (r.state != "SKIPPED") codes.push_back(r.rc);
      }
      return BatchExitCode(codes);
    }
    int rc = MakeVolume(input, series, request_id, spec->mutable_volume());
    if (rc != kOk) return rc;
    if (!label_map.empty()) {
      rc = MakeVolume(label_map, "", request_id.empty() ? "" : request_id + "/label-map",
                      spec->mutable_label_map());
      if (rc != kOk) return rc;
    }
    if (int frc = fill_spec(spec); frc != kOk) return frc;
    req.set_request_id(request_id.empty() ? NewRequestId() : request_id);
    v1::Job job;
    grpc::Status s = WithRetry([&] {
      auto ctx = conn.Context();
      if (!fault.empty()) ctx->AddMetadata("decima-test-fault", fault);
      return jobs->CreateJob(ctx.get(), req, &job);
    });
    if (!s.ok()) {
      // Volumes made for this job only (a fresh request id) are not left behind by a refused
      // job; with --request-id they may belong to the job made first, and a reused one is the
      // caller's from before, so those stay.
      if (request_id.empty()) {
        auto vstub = v1::Volumes::NewStub(conn.channel);
        for (const std::string& name : {spec->volume(), spec->label_map()}) {
          if (name.empty() || !MadeBySubmit(name)) continue;
          v1::DeleteVolumeRequest dreq;
          dreq.set_name(name);
          v1::DeleteVolumeResponse dresp;
          (void)vstub->DeleteVolume(conn.Context().get(), dreq, &dresp);
        }
      }
      return Report(s, "submit");
    }
    if (JsonOut()) {
      std::printf("%s\n", ToJson(job).c_str());
    } else {
      std::printf("%s\n", job.name().c_str());
    }
    std::fflush(stdout);
    if (!watch_flag && out.empty()) return kOk;
    v1::Job final;
    rc = Watch(job.name(), &final);
    if ((rc != kOk && rc != kTargetNotReached) || out.empty()) return rc;
    const int frc = Fetch(final, out, only);
    return frc != kOk ? frc : rc;
  }

  if (*watch) {
    if (watch_args.size() == 1) {
      std::string name;
      if (int rc = ResolveJob(watch_args[0], &name); rc != kOk) return rc;
      v1::Job final;
      return Watch(name, &final);
    }
    std::vector<std::string> names(watch_args.size());
    for (size_t i = 0; i < watch_args.size(); ++i) {
      if (int rc = ResolveJob(watch_args[i], &names[i]); rc != kOk) return rc;
    }
    const std::vector<WatchOutcome> outcomes = WatchMany(names);
    std::vector<StudyRow> rows;
    std::vector<int> codes;
    for (size_t i = 0; i < names.size(); ++i) {
      StudyRow row;
      row.job = names[i];
      const v1::Volume* vol = GetVolume(outcomes[i].final.spec().volume());
      row.input = vol != nullptr ? vol->display_name() : outcomes[i].final.spec().volume();
      SetOutcome(outcomes[i], &row);
      codes.push_back(row.rc);
      rows.push_back(std::move(row));
    }
    PrintStudyTable(rows);
    PrintStudyCounts(rows, /*jobs=*/true);
    return BatchExitCode(codes);
  }

  if (*status) {
    v1::GetJobRequest req;
    if (int rc = ResolveJob(job_arg, req.mutable_name()); rc != kOk) return rc;
    v1::Job job;
    grpc::Status s = WithRetry([&] { return jobs->GetJob(conn.Context().get(), req, &job); });
    if (!s.ok()) return Report(s, "status " + req.name());
    if (JsonOut()) {
      std::printf("%s\n", ToJson(job).c_str());
    } else {
      DescribeJob(job);
    }
    return kOk;
  }

  if (*list) {
    v1::ListJobsRequest req;
    for (const auto& st : states) {
      v1::JobState v;
      if (!ParseJobState(st, &v)) {
        std::fprintf(
            stderr,
            "decima: --state %s: not one of queued, running, succeeded, failed, cancelled\n",
            st.c_str());
        return kUsage;
      }
      req.add_states(v);
    }
    req.set_page_size(page_size);
    req.set_page_token(page_token);
    const bool wide = g.output == "wide";
    std::vector<std::vector<std::string>> rows = {JobHeader(wide)};
    for (int page = 0; page < 1000; ++page) {
      v1::ListJobsResponse resp;
      grpc::Status s = WithRetry([&] { return jobs->ListJobs(conn.Context().get(), req, &resp); });
      if (!s.ok()) return Report(s, "list");
      for (const auto& j : resp.jobs()) {
        if (JsonOut()) {
          std::printf("%s\n", ToJson(j).c_str());
        } else {
          rows.push_back(JobRow(j, wide));
        }
      }
      if (!ContinueListing(resp.next_page_token(), all)) break;
      req.set_page_token(resp.next_page_token());
    }
    if (!JsonOut()) {
      if (rows.size() == 1) {
        std::fprintf(stderr, "decima: no jobs%s\n", states.empty() ? "" : " in these states");
      } else {
        PrintTable(rows);
      }
    }
    return kOk;
  }

  if (*series_delete) {
    auto volumes = v1::Volumes::NewStub(conn.channel);
    v1::DeleteReceivedSeriesRequest req;
    req.set_series_instance_uid(series_delete_uid);
    req.set_calling_ae(series_delete_from);
    v1::DeleteReceivedSeriesResponse resp;
    // Not retried: a delete that reached the server and lost its answer finds nothing the
    // second time (NOT_FOUND), which would hide that it worked.
    grpc::Status s = volumes->DeleteReceivedSeries(conn.Context().get(), req, &resp);
    if (!s.ok()) return Report(s, "series delete " + series_delete_uid);
    if (JsonOut()) {
      std::printf("%s\n", ToJson(resp).c_str());
    } else {
      std::printf("deleted %d waiting instance(s) of series %s (%s freed)\n",
                  resp.deleted_instances(), series_delete_uid.c_str(),
                  FormatBytes(resp.freed_bytes()).c_str());
    }
    return kOk;
  }

  if (*series_cmd) {
    auto volumes = v1::Volumes::NewStub(conn.channel);
    v1::ListReceivedSeriesRequest req;
    req.set_page_size(series_page_size);
    req.set_page_token(series_page_token);
    const bool wide = g.output == "wide";
    std::vector<std::vector<std::string>> rows = {
        {"SERIES", "FROM", "TO", "INSTANCES", "STATE", "JOB / REASON", "FIRST", "LAST"}};
    if (wide) rows[0].insert(rows[0].end(), {"ROUTE", "OWNER", "ASSOCIATION", "RESULTS"});
    for (int page = 0; page < 1000; ++page) {
      v1::ListReceivedSeriesResponse resp;
      grpc::Status s =
          WithRetry([&] { return volumes->ListReceivedSeries(conn.Context().get(), req, &resp); });
      if (!s.ok()) return Report(s, "series");
      for (const auto& r : resp.received_series()) {
        if (JsonOut()) {
          std::printf("%s\n", ToJson(r).c_str());
          continue;
        }
        // The UID's tail tells series apart; -o wide or json shows it whole.
        const std::string& uid = r.series_instance_uid();
        std::string state = v1::ReceivedSeries::State_Name(r.state());
        // The job and, when it failed or the receive was closed by another, why.
        std::string what = r.job().empty()      ? r.reason()
                           : r.reason().empty() ? ShortId(r.job())
                                                : ShortId(r.job()) + ": " + r.reason();
        rows.push_back({wide || uid.size() <= 24 ? uid : "..." + uid.substr(uid.size() - 21),
                        r.calling_ae(), r.called_ae(), std::to_string(r.instance_count()), state,
                        what.empty() ? "-" : (wide ? what : what.substr(0, 100)),
                        FormatTime(r.first_receive_time()), FormatTime(r.last_receive_time())});
        if (wide) {
          rows.back().insert(rows.back().end(),
                             {r.route().empty() ? "-" : r.route(), r.owner(),
                              r.association_id().empty() ? "-" : r.association_id(),
                              r.send_status().empty() ? "-" : r.send_status()});
        }
      }
      if (!ContinueListing(resp.next_page_token(), series_all)) break;
      req.set_page_token(resp.next_page_token());
    }
    if (!JsonOut()) {
      if (rows.size() == 1) {
        std::fprintf(stderr, "decima: no series received\n");
      } else {
        PrintTable(rows);
      }
    }
    return kOk;
  }

  if (*cancel) {
    v1::CancelJobRequest req;
    if (int rc = ResolveJob(job_arg, req.mutable_name()); rc != kOk) return rc;
    v1::Job job;
    grpc::Status s = jobs->CancelJob(conn.Context().get(), req, &job);
    if (!s.ok()) return Report(s, "cancel " + req.name());
    // Cancel is best effort: wait (within the call timeout) until the job reached a final state.
    auto until = std::chrono::steady_clock::now() +
                 std::chrono::milliseconds(static_cast<int64_t>(g.timeout_s * 1000));
    while (job.state() == v1::RUNNING || job.state() == v1::QUEUED) {
      if (std::chrono::steady_clock::now() > until) {
        PrintJobLine(job);
        return kTimeout;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      v1::GetJobRequest greq;
      greq.set_name(req.name());
      s = jobs->GetJob(conn.Context().get(), greq, &job);
      if (!s.ok()) return Report(s, "status " + req.name());
    }
    PrintJobLine(job);
    return kOk;
  }

  if (*retry) {
    v1::RetryJobRequest req;
    if (int rc = ResolveJob(job_arg, req.mutable_name()); rc != kOk) return rc;
    v1::Job job;
    grpc::Status s = jobs->RetryJob(conn.Context().get(), req, &job);
    if (!s.ok()) return Report(s, "retry " + req.name());
    PrintJobLine(job);
    if (!watch_flag) return kOk;
    v1::Job final;
    return Watch(job.name(), &final);
  }

  if (*fetch) {
    v1::GetJobRequest req;
    if (int rc = ResolveJob(job_arg, req.mutable_name()); rc != kOk) return rc;
    v1::Job job;
    grpc::Status s = WithRetry([&] { return jobs->GetJob(conn.Context().get(), req, &job); });
    if (!s.ok()) return Report(s, "fetch " + req.name());
    return Fetch(job, out, only);
  }

  auto volumes = v1::Volumes::NewStub(conn.channel);
  // Deletes the volumes in `candidates` that no remaining job uses; returns bytes freed.
  auto delete_unused_volumes = [&](const std::set<std::string>& candidates, bool dry_run,
                                   int64_t* freed) -> int {
    std::vector<v1::Job> remaining;
    if (int rc = ListAllJobs({}, &remaining); rc != kOk) return rc;
    std::set<std::string> used;
    for (const auto& j : remaining) {
      used.insert(j.spec().volume());
      if (!j.spec().label_map().empty()) used.insert(j.spec().label_map());
    }
    for (const auto& v : candidates) {
      if (used.count(v) != 0) continue;
      const v1::Volume* vol = GetVolume(v);
      if (vol == nullptr) continue;
      if (!dry_run) {
        v1::DeleteVolumeRequest dreq;
        dreq.set_name(v);
        v1::DeleteVolumeResponse dresp;
        grpc::Status s = volumes->DeleteVolume(conn.Context().get(), dreq, &dresp);
        if (!s.ok()) return Report(s, "delete " + v);
      }
      *freed += vol->size_bytes();
      if (JsonOut()) {
        std::printf("{\"deleted\":%s,\"dry_run\":%s,\"bytes\":%lld}\n", JsonString(v).c_str(),
                    dry_run ? "true" : "false", static_cast<long long>(vol->size_bytes()));
      } else {
        std::printf("%s%s (%s, %s)\n", dry_run ? "would delete " : "deleted ", v.c_str(),
                    TerminalSafe(vol->display_name()).c_str(),
                    FormatBytes(vol->size_bytes()).c_str());
      }
    }
    return kOk;
  };

  if (*del) {
    int64_t freed = 0;
    std::set<std::string> vols;
    for (const auto& arg : job_args) {
      std::string name;
      if (int rc = ResolveJob(arg, &name); rc != kOk) return rc;
      v1::GetJobRequest greq;
      greq.set_name(name);
      v1::Job job;
      grpc::Status s = jobs->GetJob(conn.Context().get(), greq, &job);
      if (!s.ok()) return Report(s, "delete " + name);
      v1::DeleteJobRequest dreq;
      dreq.set_name(name);
      v1::DeleteJobResponse dresp;
      s = jobs->DeleteJob(conn.Context().get(), dreq, &dresp);
      if (!s.ok()) return Report(s, "delete " + name);
      const int64_t bytes = SummarizeJob(job, 0).artifact_bytes;
      freed += bytes;
      if (JsonOut()) {
        std::printf("{\"deleted\":%s,\"bytes\":%lld}\n", JsonString(name).c_str(),
                    static_cast<long long>(bytes));
      } else {
        std::printf("deleted %s (%s of artifacts)\n", name.c_str(), FormatBytes(bytes).c_str());
      }
      vols.insert(job.spec().volume());
      if (!job.spec().label_map().empty()) vols.insert(job.spec().label_map());
    }
    if (with_volume) {
      if (int rc = delete_unused_volumes(vols, false, &freed); rc != kOk) return rc;
    }
    if (!Quiet()) std::fprintf(stderr, "decima: freed %s\n", FormatBytes(freed).c_str());
    return kOk;
  }

  if (*prune) {
    std::vector<v1::JobState> want;
    for (const auto& st : prune_states) {
      v1::JobState v;
      if (!ParseJobState(st, &v) || v == v1::QUEUED || v == v1::RUNNING) {
        std::fprintf(stderr, "decima: prune --state %s: not one of succeeded, failed, cancelled\n",
                     st.c_str());
        return kUsage;
      }
      want.push_back(v);
    }
    if (want.empty()) want = {v1::SUCCEEDED, v1::FAILED, v1::CANCELLED};
    double age = 0;
    if (!older_than.empty() && !ParseAge(older_than, &age)) {
      std::fprintf(stderr, "decima: prune --older-than %s: expected a number and s, m, h or d\n",
                   older_than.c_str());
      return kUsage;
    }
    std::vector<v1::Job> found;
    if (int rc = ListAllJobs(want, &found); rc != kOk) return rc;
    int64_t freed = 0;
    int count = 0;
    std::set<std::string> vols;
    // Every volume is a candidate: one left by a deleted job earlier is unused as well.
    {
      auto stub = v1::Volumes::NewStub(conn.channel);
      v1::ListVolumesRequest vreq;
      vreq.set_page_size(1000);
      for (int page = 0; page < 1000; ++page) {
        v1::ListVolumesResponse vresp;
        grpc::Status s = stub->ListVolumes(conn.Context().get(), vreq, &vresp);
        if (!s.ok()) return Report(s, "prune: list volumes");
        for (const auto& v : vresp.volumes()) {
          g_volumes[v.name()] = v;
          vols.insert(v.name());
        }
        if (vresp.next_page_token().empty()) break;
        vreq.set_page_token(vresp.next_page_token());
      }
    }
    std::set<std::string> pruned;
    for (const auto& j : found) {
      if (age > 0 && SecondsSince(j.end_time()) < age) continue;
      const int64_t bytes = SummarizeJob(j, 0).artifact_bytes;
      if (force) {
        v1::DeleteJobRequest dreq;
        dreq.set_name(j.name());
        v1::DeleteJobResponse dresp;
        grpc::Status s = jobs->DeleteJob(conn.Context().get(), dreq, &dresp);
        if (!s.ok()) return Report(s, "prune " + j.name());
      }
      pruned.insert(j.name());
      freed += bytes;
      ++count;
      if (JsonOut()) {
        std::printf("{\"deleted\":%s,\"dry_run\":%s,\"bytes\":%lld}\n",
                    JsonString(j.name()).c_str(), force ? "false" : "true",
                    static_cast<long long>(bytes));
      } else {
        std::printf("%s%s (%s, %s)\n", force ? "deleted " : "would delete ", j.name().c_str(),
                    v1::JobState_Name(j.state()).c_str(), FormatBytes(bytes).c_str());
      }
    }
    if (force) {
      if (int rc = delete_unused_volumes(vols, false, &freed); rc != kOk) return rc;
    } else {
      // Dry run: the volumes that would be unused once these jobs are gone.
      std::vector<v1::Job> remaining;
      if (int rc = ListAllJobs({}, &remaining); rc != kOk) return rc;
      std::set<std::string> used;
      for (const auto& j : remaining) {
        if (pruned.count(j.name()) != 0) continue;
        used.insert(j.spec().volume());
        if (!j.spec().label_map().empty()) used.insert(j.spec().label_map());
      }
      for (const auto& v : vols) {
        if (used.count(v) != 0) continue;
        const v1::Volume& vol = g_volumes[v];
        freed += vol.size_bytes();
        if (JsonOut()) {
          std::printf("{\"deleted\":%s,\"dry_run\":true,\"bytes\":%lld}\n", JsonString(v).c_str(),
                      static_cast<long long>(vol.size_bytes()));
        } else {
          std::printf("would delete %s (%s, %s)\n", v.c_str(),
                      TerminalSafe(vol.display_name()).c_str(),
                      FormatBytes(vol.size_bytes()).c_str());
        }
      }
    }
    if (!Quiet()) {
      std::fprintf(stderr, "decima: %s %d job(s) and the unused volumes, %s%s\n",
                   force ? "deleted" : "would delete", count, FormatBytes(freed).c_str(),
                   force ? " freed" : "; run with --force to delete");
      // What a prune cannot free at once (issue 35 part 7: an empty server still held 147 MB),
      // so nobody takes the rest for a leak.
      if (force) {
        std::fprintf(stderr,
                     "decima: the server's disk gets the rest back later: uploads no volume uses "
                     "are kept for its --blob-grace-seconds (1 h by default) and then collected; "
                     "its --disk-reserve-mb (64 MB) and the job store's own files (SQLite's WAL) "
                     "stay\n");
      }
    }
    return kOk;
  }
  return kUsage;
}
