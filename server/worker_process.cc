#include "server/worker_process.h"

#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "core/common/progress.h"
#include "core/pipeline/pipeline.h"
#include "decima/v1/jobs.pb.h"

namespace decima::server {
namespace {

CancelToken g_cancel;

void OnTerm(int) { g_cancel.Cancel(); }

void WriteLine(int fd, const nlohmann::json& j) {
  std::string line = j.dump() + "\n";
  const char* p = line.data();
  size_t left = line.size();
  while (left > 0) {
    ssize_t n = ::write(fd, p, left);
    if (n < 0) {
      if (errno == EINTR) continue;
      std::_Exit(kWorkerExitError);  // parent gone: nobody needs the result
    }
    p += n;
    left -= static_cast<size_t>(n);
  }
}

void SendProgress(int fd, const Progress& p) {
  nlohmann::json m = nlohmann::json::object();
  for (const auto& [k, v] : p.metrics) m[k] = v;
  WriteLine(fd, {{"type", "progress"},
                 {"stage", p.stage},
                 {"fraction", p.fraction},
                 {"message", p.message},
                 {"metrics", m}});
}

int SendError(int fd, absl::StatusCode code, const std::string& message) {
  WriteLine(fd, {{"type", "error"}, {"code", static_cast<int>(code)}, {"message", message}});
  return code == absl::StatusCode::kCancelled ? kWorkerExitCancelled : kWorkerExitError;
}

// Test-only faults, comma separated: "sleep:S" spends S seconds in a cancellable "prepare"
// stage reporting progress every 50 ms; "crash" aborts the process once the job started.
absl::Status ApplyFaults(const std::string& faults, int fd, bool* crash) {
  for (absl::string_view f : absl::StrSplit(faults, ',', absl::SkipEmpty())) {
    if (f == "crash") {
      *crash = true;
    } else if (absl::ConsumePrefix(&f, "sleep:")) {
      double seconds = 0;
      if (!absl::SimpleAtod(f, &seconds)) return absl::InvalidArgumentError("fault: bad sleep");
      auto start = std::chrono::steady_clock::now();
      for (;;) {
        double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
        if (t >= seconds) break;
        if (g_cancel.cancelled()) return absl::CancelledError("prepare: cancelled");
        SendProgress(fd, {"prepare", t / seconds, "test fault: sleeping", {{"elapsed_s", t}}});
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
      }
    }
  }
  return absl::OkStatus();
}

}  // namespace

int RunJobProcess(const std::filesystem::path& job_dir, const std::filesystem::path& input,
                  const std::filesystem::path& label_map, int fd) {
  struct sigaction sa {};
  sa.sa_handler = OnTerm;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGTERM, &sa, nullptr);

  v1::JobSpec spec;
  {
    std::ifstream in(job_dir / "spec.pb", std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    if (!in || !spec.ParseFromString(ss.str())) {
      return SendError(fd, absl::StatusCode::kInternal,
                       "worker: cannot read " + (job_dir / "spec.pb").string());
    }
  }
  bool crash = false;
  absl::Status fs = ApplyFaults(spec.fault(), fd, &crash);
  if (!fs.ok()) return SendError(fd, fs.code(), std::string(fs.message()));
  SendProgress(fd, {"load", 0, "starting", {}});
  if (crash) std::abort();

  pipeline::JobSpec p;
  p.input = input;
  p.series_instance_uid = "";
  if (spec.regions() > 0) p.regions = spec.regions();
  p.class_means.assign(spec.class_means().begin(), spec.class_means().end());
  if (!label_map.empty()) p.label_map = label_map;
  if (spec.target_reduction() > 0) p.target_reduction = spec.target_reduction();
  if (!spec.policy().empty()) p.policy = spec.policy();
  p.error_tolerance = spec.error_tolerance();
  for (const auto& [k, v] : spec.weights()) p.weights[k] = v;
  if (!spec.views().empty()) p.views.assign(spec.views().begin(), spec.views().end());
  if (spec.image_size() > 0) p.image_size = spec.image_size();
  if (!spec.transfer_function().empty()) p.transfer_function = spec.transfer_function();

  auto result = pipeline::RunJob(
      p, job_dir / "out", [fd](const Progress& pr) { SendProgress(fd, pr); }, &g_cancel);
  if (!result.ok()) {
    return SendError(fd, result.status().code(), std::string(result.status().message()));
  }
  nlohmann::json arts = nlohmann::json::array();
  for (const auto& a : result->artifacts) {
    arts.push_back({{"name", a.name}, {"path", a.path.string()}, {"size", a.size_bytes}});
  }
  WriteLine(fd, {{"type", "result"}, {"artifacts", arts}, {"metrics_json", result->metrics_json}});
  return kWorkerExitOk;
}

}  // namespace decima::server
