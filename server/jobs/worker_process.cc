#include "server/jobs/worker_process.h"

#include <signal.h>

#include <cstdlib>
#include <fstream>
#include <new>
#include <sstream>
#include <string>

#include "absl/strings/str_cat.h"
#include "core/common/progress.h"
#include "core/common/utf8.h"
#include "core/pipeline/pipeline.h"
#include "server/files/disk_space.h"
#include "server/jobs/dicom_results.h"
#include "server/jobs/faults.h"
#include "server/jobs/job_spec.h"
#include "server/jobs/worker.pb.h"
#include "server/jobs/worker_protocol.h"

namespace decima::server {
namespace {

CancelToken g_cancel;

void OnTerm(int) { g_cancel.Cancel(); }

void Send(int fd, const worker::WorkerMessage& m) {
  // The parent is gone (or the pipe broke): nobody needs the result.
  if (!WriteFrame(fd, m).ok()) std::_Exit(kWorkerExitError);
}

void SendProgress(int fd, const Progress& p) {
  worker::WorkerMessage m;
  v1::Progress* out = m.mutable_progress();
  out->set_stage(p.stage);
  out->set_fraction(p.fraction);
  out->set_message(ValidUtf8(p.message));
  for (const auto& [k, v] : p.metrics) (*out->mutable_metrics())[k] = v;
  if (p.overall >= 0) out->set_overall_fraction(p.overall);
  if (p.eta_seconds >= 0) out->set_eta_seconds(p.eta_seconds);
  Send(fd, m);
}

int SendError(int fd, const absl::Status& status) {
  worker::WorkerMessage m;
  m.mutable_error()->set_code(static_cast<int>(status.code()));
  // A message may quote the input's own text; the frame is a protobuf, whose strings (and the
  // parent's parse of them) need valid UTF-8.
  m.mutable_error()->set_message(ValidUtf8(std::string(status.message())));
  Send(fd, m);
  return status.code() == absl::StatusCode::kCancelled ? kWorkerExitCancelled : kWorkerExitError;
}

}  // namespace

int RunJobProcess(const std::filesystem::path& request_file, int fd) {
  struct sigaction sa {};
  sa.sa_handler = OnTerm;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGTERM, &sa, nullptr);

  worker::RunRequest request;
  {
    std::ifstream in(request_file, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    if (!in || !request.ParseFromString(ss.str())) {
      return SendError(fd, absl::InternalError("worker: cannot read " + request_file.string()));
    }
  }
  // The stored spec is normalized (CreateJob), so this applies no default: it runs what was stored.
  auto spec = JobSpecFromProto(request.spec());
  if (!spec.ok()) return SendError(fd, spec.status());
  spec->input = request.input();
  spec->series_instance_uid = request.series_instance_uid();
  spec->job_name = request.job_name();
  spec->input_name = request.input_name();
  if (!request.label_map().empty()) spec->label_map = request.label_map();
  if (!request.levels_file().empty()) spec->levels_file = request.levels_file();

  auto progress = [fd](const Progress& p) { SendProgress(fd, p); };
  bool crash = false;
  if (auto st = ApplyFaults(request.fault(), progress, g_cancel, &crash); !st.ok()) {
    return SendError(fd, st);
  }
  SendProgress(fd, {"load", 0, "starting", {}});
  if (crash) std::abort();

  std::string stage = "load";
  auto tracked = [&](const Progress& p) {
    stage = p.stage;
    progress(p);
  };
  pipeline::CheckpointOptions checkpoints;
  checkpoints.dir = request.checkpoint_dir();
  checkpoints.key = request.checkpoint_key();
  // A failed pause (only a cancel) shows at the pipeline's next cancellation check.
  checkpoints.on_saved = [&](const std::string& saved) {
    (void)PauseAfterCheckpoint(request.fault(), saved, progress, g_cancel);
  };
  absl::StatusOr<pipeline::JobResult> result;
  try {
    result = pipeline::RunJob(*spec, request.out_dir(), tracked, &g_cancel, checkpoints);
  } catch (const std::bad_alloc&) {
    // RLIMIT_AS reached: the estimate was low for this volume. Say so rather than dying.
    result = absl::ResourceExhaustedError(absl::StrCat(
        "the job ran out of memory during stage ", stage, " at its limit of ",
        request.memory_limit_bytes() > 0 ? HumanBytes(request.memory_limit_bytes()) : "(none)",
        "; raise decima-server --worker-memory-mb or use a smaller volume"));
  }
  if (!result.ok()) return SendError(fd, result.status());
  // A DICOM input also gets its results as DICOM (SEG + Secondary Capture) for the PACS.
  if (auto st = AddDicomResults(*spec, request.out_dir(), &*result); !st.ok()) {
    return SendError(fd, st);
  }
  worker::WorkerMessage m;
  for (const auto& a : result->artifacts) {
    worker::Artifact* out = m.mutable_result()->add_artifacts();
    out->set_name(a.name);
    out->set_path(a.path.string());
    out->set_size_bytes(static_cast<int64_t>(a.size_bytes));
  }
  m.mutable_result()->set_metrics_json(result->metrics_json);
  Send(fd, m);
  return kWorkerExitOk;
}

}  // namespace decima::server
