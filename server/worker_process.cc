#include "server/worker_process.h"

#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "core/common/progress.h"
#include "core/pipeline/pipeline.h"
#include "decima/v1/jobs.pb.h"
#include "server/faults.h"
#include "server/job_spec.h"

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

}  // namespace

int RunJobProcess(const std::filesystem::path& job_dir, const std::filesystem::path& input,
                  const std::filesystem::path& label_map, const std::string& fault, int fd) {
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
  // The stored spec is normalized (CreateJob), so this applies no default: it runs what was stored.
  auto p = JobSpecFromProto(spec);
  if (!p.ok()) return SendError(fd, p.status().code(), std::string(p.status().message()));
  p->input = input;
  if (!label_map.empty()) p->label_map = label_map;

  bool crash = false;
  absl::Status fs = ApplyFaults(
      fault, [fd](const Progress& pr) { SendProgress(fd, pr); }, g_cancel, &crash);
  if (!fs.ok()) return SendError(fd, fs.code(), std::string(fs.message()));
  SendProgress(fd, {"load", 0, "starting", {}});
  if (crash) std::abort();

  auto result = pipeline::RunJob(
      *p, job_dir / "out", [fd](const Progress& pr) { SendProgress(fd, pr); }, &g_cancel);
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
