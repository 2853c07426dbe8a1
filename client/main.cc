// decima: the command-line client of decima-server. Data on stdout, progress on stderr.
#include <unistd.h>

#include <google/protobuf/util/json_util.h>
#include <CLI/CLI.hpp>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <optional>
#include <random>
#include <thread>

#include "client/client_lib.h"
#include "grpc/health/v1/health.grpc.pb.h"

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

Environment: DECIMA_SERVER (default 127.0.0.1:50051), DECIMA_TOKEN, DECIMA_CA_CERT,
DECIMA_TLS_CERT, DECIMA_TLS_KEY.)";

struct Globals {
  std::string server = "127.0.0.1:50051";
  std::string token;
  bool json = false;
  bool tls = false;
  std::string ca_file, cert_file, key_file;
  double timeout_s = 30;
  double reconnect_s = 60;
  bool quiet = false;
};

Globals g;
Connection conn;
bool stderr_tty = false;

std::string ToJson(const google::protobuf::Message& m) {
  std::string out;
  google::protobuf::util::JsonPrintOptions o;
  o.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(m, &out, o);
  return out;
}

// Prints a failed call as "error: CODE: message" and returns its exit code.
int Report(const grpc::Status& s, const std::string& what) {
  std::fprintf(stderr, "decima: %s: %s: %s\n", what.c_str(), StatusCodeName(s.error_code()).c_str(),
               s.error_message().c_str());
  // gRPC reports a refused handshake as UNAVAILABLE with a generic text: say what to check.
  if (s.error_code() == grpc::StatusCode::UNAVAILABLE &&
      (g.tls || !g.ca_file.empty() || !g.cert_file.empty())) {
    std::fprintf(stderr,
                 "decima: over TLS this is also what a refused handshake looks like: check "
                 "--ca-cert (the server's CA), and under mutual TLS --tls-cert/--tls-key (a "
                 "client certificate the server's --tls-client-ca signed)\n");
  }
  return ExitCodeFor(s.error_code());
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

std::string JobName(const std::string& arg) {
  return arg.rfind("jobs/", 0) == 0 ? arg : "jobs/" + arg;
}

// Retries a unary call while the server is UNAVAILABLE (restarting), up to --reconnect.
template <typename F>
grpc::Status WithRetry(F call) {
  auto until = std::chrono::steady_clock::now() +
               std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
  int wait_ms = 100;
  for (;;) {
    grpc::Status s = call();
    if (s.error_code() != grpc::StatusCode::UNAVAILABLE ||
        std::chrono::steady_clock::now() > until) {
      return s;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms));
    wait_ms = std::min(wait_ms * 2, 2000);
  }
}

void ByteBar(const std::string& what, int64_t done, int64_t total) {
  if (g.quiet || g.json) return;
  if (stderr_tty) {
    double f = total > 0 ? static_cast<double>(done) / total : 1.0;
    std::fprintf(stderr, "\r%s %6.1f%% of %.1f MB", what.c_str(), f * 100, total / 1e6);
    if (done >= total) std::fprintf(stderr, "\n");
  }
}

// Watches a job until a final state, reconnecting with the last sequence on UNAVAILABLE.
// Returns the exit code and the final job in *final.
int Watch(const std::string& name, v1::Job* final) {
  auto stub = v1::Jobs::NewStub(conn.channel);
  int64_t last = 0;
  bool bar_open = false;
  auto give_up = std::chrono::steady_clock::now() +
                 std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
  int wait_ms = 100;
  std::string last_reconnect_reason;  // said once, not at every retry
  v1::JobState state = v1::JOB_STATE_UNSPECIFIED;
  for (;;) {
    v1::WatchJobRequest req;
    req.set_name(name);
    req.set_after_sequence(last);
    auto ctx = conn.Context(false);
    auto reader = stub->WatchJob(ctx.get(), req);
    v1::JobEvent ev;
    while (reader->Read(&ev)) {
      give_up = std::chrono::steady_clock::now() +
                std::chrono::milliseconds(static_cast<int64_t>(g.reconnect_s * 1000));
      wait_ms = 100;
      if (ev.has_snapshot()) {
        *final = ev.snapshot();
        state = ev.snapshot().state();
        if (last == 0) last = 0;  // events follow from after_sequence
      } else if (!ev.has_heartbeat()) {
        last = ev.sequence();
      }
      if (ev.has_state_change()) state = ev.state_change().state();
      if (ev.has_progress()) *final->mutable_progress() = ev.progress();
      if (g.json) {
        std::printf("%s\n", ToJson(ev).c_str());
        std::fflush(stdout);
      } else if (!g.quiet) {
        if (stderr_tty && ev.has_progress()) {
          std::fprintf(stderr, "\r\033[K%s", ProgressBar(ev.progress(), 30).c_str());
          bar_open = true;
        } else if (!ev.has_heartbeat() || !stderr_tty) {
          if (bar_open) std::fprintf(stderr, "\n");
          bar_open = false;
          std::fprintf(stderr, "%s\n", DescribeEvent(name, ev).c_str());
        }
      }
    }
    grpc::Status s = reader->Finish();
    if (bar_open) std::fprintf(stderr, "\n");
    bar_open = false;
    if (s.ok()) {
      // The stream ends after the final state (or at once for a job already final).
      v1::GetJobRequest greq;
      greq.set_name(name);
      grpc::Status gs = WithRetry([&] { return stub->GetJob(conn.Context().get(), greq, final); });
      if (!gs.ok()) return Report(gs, "get " + name);
      // -q hides progress, never why a job did not succeed.
      if (g.quiet && !g.json && final->state() != v1::SUCCEEDED) {
        std::fprintf(
            stderr, "decima: %s %s%s%s\n", name.c_str(), v1::JobState_Name(final->state()).c_str(),
            final->error().message().empty() ? "" : ": ", final->error().message().c_str());
      }
      return ExitCodeFor(final->state());
    }
    // UNAVAILABLE: the server is draining or restarting. CANCELLED: this client never cancels
    // a watch, so it is the server's shutdown cutting a call in flight; both end the same way.
    const bool server_went_away = s.error_code() == grpc::StatusCode::UNAVAILABLE ||
                                  s.error_code() == grpc::StatusCode::CANCELLED;
    if (server_went_away && std::chrono::steady_clock::now() < give_up) {
      const std::string why = s.error_code() == grpc::StatusCode::CANCELLED
                                  ? "the server closed the stream"
                                  : s.error_message();
      if (!g.quiet && !g.json && why != last_reconnect_reason) {
        std::fprintf(stderr, "decima: watch %s: %s; reconnecting after #%lld\n", name.c_str(),
                     why.c_str(), static_cast<long long>(last));
      }
      last_reconnect_reason = why;
      std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms));
      wait_ms = std::min(wait_ms * 2, 1000);
      continue;
    }
    (void)state;
    return Report(s, "watch " + name);
  }
}

int Fetch(const v1::Job& job, const fs::path& out) {
  if (job.state() != v1::SUCCEEDED) {
    std::fprintf(stderr, "decima: fetch %s: the job is %s%s%s\n", job.name().c_str(),
                 v1::JobState_Name(job.state()).c_str(), job.error().message().empty() ? "" : ": ",
                 job.error().message().c_str());
    int code = ExitCodeFor(job.state());
    return code == kOk ? kError : code;
  }
  for (const auto& a : job.artifacts()) {
    fs::path path;
    grpc::Status s = WithRetry([&] {
      return DownloadArtifact(
          conn, a, out, [&](int64_t d, int64_t t) { ByteBar("fetch " + a.file_name(), d, t); },
          &path);
    });
    if (!s.ok()) return Report(s, "fetch " + a.name());
    if (g.json) {
      std::printf("{\"artifact\":\"%s\",\"path\":\"%s\",\"size_bytes\":%lld}\n",
                  a.file_name().c_str(), path.c_str(), static_cast<long long>(a.size_bytes()));
    } else {
      std::printf("%s\n", path.c_str());
    }
  }
  if (!job.metrics_json().empty() && !fs::exists(out / "metrics.json")) {
    std::ofstream(out / "metrics.json") << job.metrics_json();
  }
  std::fflush(stdout);
  return kOk;
}

void PrintJob(const v1::Job& j) {
  if (g.json) {
    std::printf("%s\n", ToJson(j).c_str());
    return;
  }
  std::printf("%s %s", j.name().c_str(), v1::JobState_Name(j.state()).c_str());
  if (!j.progress().stage().empty() && j.state() == v1::RUNNING) {
    std::printf(" %s %d%%", j.progress().stage().c_str(),
                static_cast<int>(j.progress().fraction() * 100));
  }
  if (!j.error().message().empty()) std::printf(" (%s)", j.error().message().c_str());
  std::printf("\n");
}

// Uploads the files of INPUT and creates a volume (of DICOM series `series` when not empty);
// returns its name in *name.
int MakeVolume(const fs::path& input, const std::string& series, std::string* name) {
  std::vector<InputFile> files;
  std::string err;
  if (!CollectInputs(input, &files, &err) || !HashInputs(&files, &err)) {
    std::fprintf(stderr, "decima: %s\n", err.c_str());
    return kUsage;
  }
  v1::CreateVolumeRequest req;
  for (const auto& f : files) {
    int64_t resumed = 0;
    grpc::Status s = UploadBlob(
        conn, f, [&](int64_t d, int64_t t) { ByteBar("upload " + f.name, d, t); }, 4, &resumed);
    if (!s.ok()) return Report(s, "upload " + f.path.string());
    if (!g.quiet && !g.json) {
      if (resumed == f.size) {
        std::fprintf(stderr, "decima: %s already on the server (%lld bytes)\n", f.name.c_str(),
                     static_cast<long long>(f.size));
      } else if (resumed > 0) {
        std::fprintf(stderr, "decima: resumed upload of %s at byte %lld of %lld\n", f.name.c_str(),
                     static_cast<long long>(resumed), static_cast<long long>(f.size));
      }
    }
    auto* vf = req.mutable_volume()->add_files();
    vf->set_path(f.name);
    vf->set_blob("blobs/" + f.sha256);
  }
  req.mutable_volume()->set_display_name(input.filename().string());
  req.mutable_volume()->set_series_instance_uid(series);
  req.set_request_id(NewRequestId());
  auto stub = v1::Volumes::NewStub(conn.channel);
  v1::Volume vol;
  grpc::Status s = WithRetry([&] { return stub->CreateVolume(conn.Context().get(), req, &vol); });
  if (!s.ok()) return Report(s, "create volume from " + input.string());
  if (!g.quiet && !g.json) {
    std::fprintf(stderr, "decima: %s = %s", vol.name().c_str(),
                 v1::VolumeFormat_Name(vol.format()).c_str());
    if (vol.dims_size() == 3) {
      std::fprintf(stderr, " %lldx%lldx%lld voxels, %.3gx%.3gx%.3g mm",
                   static_cast<long long>(vol.dims(0)), static_cast<long long>(vol.dims(1)),
                   static_cast<long long>(vol.dims(2)), vol.spacing(0), vol.spacing(1),
                   vol.spacing(2));
    }
    if (!vol.modality().empty()) std::fprintf(stderr, " %s", vol.modality().c_str());
    std::fprintf(stderr, "\n");
  }
  *name = vol.name();
  return kOk;
}

}  // namespace

int main(int argc, char** argv) {
  stderr_tty = ::isatty(2) != 0;
  CLI::App app{
      "decima: submit medical volumes to a decima-server, watch the jobs, fetch the "
      "meshes and images"};
  app.footer(kExitCodes);
  app.require_subcommand(1);
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
                 "how long to keep retrying an unavailable server, seconds")
      ->capture_default_str();
  app.add_flag("-q,--quiet", g.quiet, "no progress on stderr");

  // submit
  auto* submit =
      app.add_subcommand("submit", "upload a volume (file or DICOM folder) and queue a job");
  std::string input, label_map, series, policy = "field", tf, fault, request_id;
  fs::path out;
  // Unset options stay unset in the request: the server owns the defaults.
  std::optional<int> regions, image_size;
  std::optional<double> reduction, tolerance;
  std::vector<double> means;
  std::vector<std::string> weights, views;
  bool watch_flag = false;
  submit
      ->add_option("INPUT", input, "volume file (.nii, .nii.gz, .mha, .mhd, .nrrd) or DICOM folder")
      ->required();
  submit->add_option("--regions,-k", regions, "K regions of the segmentation (2..8, default 3)");
  submit->add_option("--class-means", means, "K class means instead of k-means")->delimiter(',');
  submit->add_option("--label-map", label_map,
                     "a label map on the same grid (replaces the level set)");
  submit->add_option("--reduction", reduction,
                     "target_reduction: fraction of cells to remove (0..0.99, default 0.5; 0 = "
                     "no target, stop on --tolerance)");
  submit->add_option("--policy", policy, "simplification policy: paper, tetfusion or field")
      ->check(CLI::IsMember({"paper", "tetfusion", "field"}))
      ->capture_default_str();
  submit->add_option("--tolerance", tolerance, "error tolerance (>= 0; default 0 = none)");
  submit->add_option("--weight", weights,
                     "weight override NAME=VALUE (w_r/regional, w_g/gradient, w_s/shape, "
                     "w_v/volume, w_n/neighbour)");
  submit->add_option("--views", views, "render views (default anterior)")->delimiter(',');
  submit->add_option("--image-size", image_size, "rendered image size, pixels (default 512)");
  submit->add_option("--transfer-function", tf, "preset name, auto, or JSON");
  submit->add_option("--series", series,
                     "DICOM folder with several series: the SeriesInstanceUID to process");
  submit->add_option("--request-id", request_id, "idempotency key (default: a new UUID)");
  // Test seam (server/faults.h): sent as metadata, read only by a server run with --allow-faults.
  submit->add_option("--fault", fault, "test-only fault injection")->group("");
  submit->add_flag("--watch", watch_flag, "watch the job until it ends");
  submit->add_option("--out", out,
                     "download the artifacts here when it succeeds (implies --watch)");

  auto* watch = app.add_subcommand("watch", "stream a job's progress until it ends");
  std::string job_arg;
  watch->add_option("JOB", job_arg, "job id or jobs/{id}")->required();
  auto* status = app.add_subcommand("status", "show a job");
  status->add_option("JOB", job_arg, "job id or jobs/{id}")->required();
  auto* list = app.add_subcommand("list", "list jobs, newest first");
  std::vector<std::string> states;
  int page_size = 50;
  std::string page_token;
  bool all = false;
  list->add_option("--state", states, "only these states (QUEUED, RUNNING, ...)")->delimiter(',');
  list->add_option("--page-size", page_size, "jobs per page")->capture_default_str();
  list->add_option("--page-token", page_token, "continue a listing");
  list->add_flag("--all", all, "follow every page");
  auto* cancel = app.add_subcommand("cancel", "cancel a job (waits until it stopped)");
  cancel->add_option("JOB", job_arg, "job id or jobs/{id}")->required();
  auto* retry = app.add_subcommand("retry", "queue a failed or cancelled job again");
  retry->add_option("JOB", job_arg, "job id or jobs/{id}")->required();
  retry->add_flag("--watch", watch_flag, "watch the job until it ends");
  auto* fetch = app.add_subcommand("fetch", "download a succeeded job's artifacts");
  fetch->add_option("JOB", job_arg, "job id or jobs/{id}")->required();
  fetch->add_option("--out", out, "destination folder")->required();
  auto* health = app.add_subcommand("health", "check that the server is serving");

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    int rc = app.exit(e);
    return rc == 0 ? kOk : kUsage;
  }

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

  if (*health) {
    auto stub = grpc::health::v1::Health::NewStub(conn.channel);
    grpc::health::v1::HealthCheckRequest req;
    grpc::health::v1::HealthCheckResponse resp;
    grpc::Status s = stub->Check(conn.Context().get(), req, &resp);
    if (!s.ok()) return Report(s, "health " + g.server);
    std::string st = grpc::health::v1::HealthCheckResponse::ServingStatus_Name(resp.status());
    if (g.json) {
      std::printf("{\"server\":\"%s\",\"status\":\"%s\"}\n", g.server.c_str(), st.c_str());
    } else {
      std::printf("%s %s\n", g.server.c_str(), st.c_str());
    }
    return resp.status() == grpc::health::v1::HealthCheckResponse::SERVING ? kOk : kUnavailable;
  }

  if (*submit) {
    v1::CreateJobRequest req;
    auto* spec = req.mutable_spec();
    int rc = MakeVolume(input, series, spec->mutable_volume());
    if (rc != kOk) return rc;
    if (!label_map.empty()) {
      rc = MakeVolume(label_map, "", spec->mutable_label_map());
      if (rc != kOk) return rc;
    }
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
      const std::string name = w.substr(0, eq);
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
    for (const auto& v : views) spec->add_views(v);
    if (image_size) spec->set_image_size(*image_size);
    spec->set_transfer_function(tf);
    req.set_request_id(request_id.empty() ? NewRequestId() : request_id);
    v1::Job job;
    grpc::Status s = WithRetry([&] {
      auto ctx = conn.Context();
      if (!fault.empty()) ctx->AddMetadata("decima-test-fault", fault);
      return jobs->CreateJob(ctx.get(), req, &job);
    });
    if (!s.ok()) {
      // The volumes were made for this job only: a refused job leaves none behind.
      auto vstub = v1::Volumes::NewStub(conn.channel);
      for (const std::string& name : {spec->volume(), spec->label_map()}) {
        if (name.empty()) continue;
        v1::DeleteVolumeRequest dreq;
        dreq.set_name(name);
        v1::DeleteVolumeResponse dresp;
        (void)vstub->DeleteVolume(conn.Context().get(), dreq, &dresp);
      }
      return Report(s, "submit");
    }
    if (g.json) {
      std::printf("%s\n", ToJson(job).c_str());
    } else {
      std::printf("%s\n", job.name().c_str());
    }
    std::fflush(stdout);
    if (!watch_flag && out.empty()) return kOk;
    v1::Job final;
    rc = Watch(job.name(), &final);
    if (rc != kOk || out.empty()) return rc;
    return Fetch(final, out);
  }

  if (*watch) {
    v1::Job final;
    return Watch(JobName(job_arg), &final);
  }

  if (*status) {
    v1::GetJobRequest req;
    req.set_name(JobName(job_arg));
    v1::Job job;
    grpc::Status s = jobs->GetJob(conn.Context().get(), req, &job);
    if (!s.ok()) return Report(s, "status " + req.name());
    PrintJob(job);
    return kOk;
  }

  if (*list) {
    v1::ListJobsRequest req;
    for (const auto& st : states) {
      v1::JobState v;
      if (!v1::JobState_Parse(st, &v) || v == v1::JOB_STATE_UNSPECIFIED) {
        std::fprintf(
            stderr,
            "decima: --state %s: not one of QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED\n",
            st.c_str());
        return kUsage;
      }
      req.add_states(v);
    }
    req.set_page_size(page_size);
    req.set_page_token(page_token);
    for (;;) {
      v1::ListJobsResponse resp;
      grpc::Status s = jobs->ListJobs(conn.Context().get(), req, &resp);
      if (!s.ok()) return Report(s, "list");
      for (const auto& j : resp.jobs()) PrintJob(j);
      if (resp.next_page_token().empty()) break;
      if (!all) {
        if (g.json) {
          std::printf("{\"next_page_token\":\"%s\"}\n", resp.next_page_token().c_str());
        } else {
          std::fprintf(stderr, "more: --page-token %s\n", resp.next_page_token().c_str());
        }
        break;
      }
      req.set_page_token(resp.next_page_token());
    }
    return kOk;
  }

  if (*cancel) {
    v1::CancelJobRequest req;
    req.set_name(JobName(job_arg));
    v1::Job job;
    grpc::Status s = jobs->CancelJob(conn.Context().get(), req, &job);
    if (!s.ok()) return Report(s, "cancel " + req.name());
    // Cancel is best effort: wait (within the call timeout) until the job reached a final state.
    auto until = std::chrono::steady_clock::now() +
                 std::chrono::milliseconds(static_cast<int64_t>(g.timeout_s * 1000));
    while (job.state() == v1::RUNNING || job.state() == v1::QUEUED) {
      if (std::chrono::steady_clock::now() > until) {
        PrintJob(job);
        return kTimeout;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      v1::GetJobRequest greq;
      greq.set_name(req.name());
      s = jobs->GetJob(conn.Context().get(), greq, &job);
      if (!s.ok()) return Report(s, "status " + req.name());
    }
    PrintJob(job);
    return kOk;
  }

  if (*retry) {
    v1::RetryJobRequest req;
    req.set_name(JobName(job_arg));
    v1::Job job;
    grpc::Status s = jobs->RetryJob(conn.Context().get(), req, &job);
    if (!s.ok()) return Report(s, "retry " + req.name());
    PrintJob(job);
    if (!watch_flag) return kOk;
    v1::Job final;
    return Watch(job.name(), &final);
  }

  if (*fetch) {
    v1::GetJobRequest req;
    req.set_name(JobName(job_arg));
    v1::Job job;
    grpc::Status s = jobs->GetJob(conn.Context().get(), req, &job);
    if (!s.ok()) return Report(s, "fetch " + req.name());
    return Fetch(job, out);
  }
  return kUsage;
}
