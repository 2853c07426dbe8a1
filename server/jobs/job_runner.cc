#include "server/jobs/job_runner.h"

#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <fstream>
#include <optional>
#include <thread>

#include "absl/strings/str_cat.h"
#include "core/pipeline/levels_output.h"
#include "server/files/volume_probe.h"
#include "server/jobs/child_process.h"
#include "server/jobs/job_memory.h"
#include "server/jobs/worker_process.h"
#include "server/jobs/worker_protocol.h"
#include "server/util/sha256.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace fs = std::filesystem;
namespace {

using Clock = std::chrono::steady_clock;

int64_t MsSince(Clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - t).count();
}

// The last non-empty line of a log file (at most 300 bytes), for crash reports.
std::string LogTail(const fs::path& log) {
  std::ifstream in(log, std::ios::binary);
  if (!in) return {};
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  const std::streamoff start = size > 300 ? size - 300 : 0;
  in.seekg(start);
  std::string s(static_cast<size_t>(size - start), '\0');
  in.read(s.data(), static_cast<std::streamsize>(s.size()));
  while (!s.empty() && (s.back() == '\n' || s.back() == '\r')) s.pop_back();
  const size_t nl = s.rfind('\n');
  return nl == std::string::npos ? s : s.substr(nl + 1);
}

v1::Job Outcome(absl::StatusCode code, const std::string& message) {
  v1::Job outcome;
  outcome.mutable_error()->set_code(static_cast<int>(code));
  outcome.mutable_error()->set_message(message);
  return outcome;
}

// The input part of a job's checkpoint key: the blob (sha256) of every file of its volume and
// label map, so a checkpoint never outlives a change of what the job reads.
std::string CheckpointKey(const v1::Job& job, JobStore* store) {
  std::string key;
  for (const std::string& name : {job.spec().volume(), job.spec().label_map()}) {
    if (name.empty()) continue;
    absl::StrAppend(&key, name, ":");
    auto id = ParseName(name, "volumes", "spec.volume");
    if (!id.ok()) continue;
    auto vol = store->GetVolume(*id);
    if (!vol.ok()) continue;
    for (const auto& f : vol->files()) absl::StrAppend(&key, f.path(), "=", f.blob(), ";");
    absl::StrAppend(&key, "series=", vol->series_instance_uid(), "|");
  }
  if (!job.spec().levels_of().empty()) absl::StrAppend(&key, "levels_of=", job.spec().levels_of());
  return key;
}

// Which stage a requeued job will resume after, for the requeue's message.
std::string ResumePoint(const fs::path& checkpoints) {
  std::error_code ec;
  if (fs::exists(checkpoints / "simplify.ckpt", ec)) return "simplify";
  // A streamed simplify stage's window records (core/pipeline, "Stage checkpoints").
  int64_t windows = 0;
  for (const auto& e : fs::directory_iterator(checkpoints, ec)) {
    windows += e.path().filename().string().rfind(pipeline::kSimplifyWindowRecordPrefix, 0) == 0;
  }
  if (fs::exists(checkpoints / "segment.ckpt", ec)) {
    return windows > 0 ? absl::StrCat("segment and the ", windows, " simplify slabs saved")
                       : "segment";
  }
  return "";
}

}  // namespace

struct JobRunner::ChildEnd {
  std::optional<worker::WorkerMessage> final;  // the result or error message, if one came
  absl::Status protocol;                       // a malformed or truncated message stream
  int wait_status = 0;
  std::string stage = "start";  // the last stage the child reported
  bool lost_lease = false;
};

JobRunner::JobRunner(JobStore* store, JobRunnerOptions options)
    : store_(store), options_(std::move(options)) {}

absl::StatusOr<JobRunner::Prepared> JobRunner::Prepare(const v1::Job& job, int64_t epoch) {
  const std::string id = job.name().substr(5);
  const DataDir& dd = options_.data_dir;
  if (auto st = dd.ResetJobOut(id, epoch); !st.ok()) return st;
  v1::Volume volume;
  auto resolve = [&](const std::string& name, const char* field) -> absl::StatusOr<fs::path> {
    auto vid = ParseName(name, "volumes", field);
    if (!vid.ok()) return vid.status();
    auto vol = store_->GetVolume(*vid);
    if (!vol.ok()) return vol.status();
    volume = *vol;
    return VolumeInput(dd.volume_files(*vid), *vol);
  };
  worker::RunRequest request;
  *request.mutable_spec() = job.spec();
  auto input = resolve(job.spec().volume(), "spec.volume");
  if (!input.ok()) return input.status();
  request.set_input(input->string());
  request.set_series_instance_uid(volume.series_instance_uid());
  const int64_t cap = JobMemoryCapBytes(options_.worker_memory_mb);
  const JobMemoryPlan plan = PlanJobMemory(volume, job.spec(), cap);
  if (auto fits = CheckJobMemory(volume, job.spec().volume(), cap, plan); !fits.ok()) return fits;
  // A job stored before CreateJob chose (spec without stream_slab_voxels) runs as planned here.
  request.mutable_spec()->set_stream_slab_voxels(plan.stream_slab_voxels);
  Prepared prepared;
#if !defined(__SANITIZE_ADDRESS__) && !defined(__SANITIZE_THREAD__)
  prepared.memory_limit_bytes = JobAddressSpaceLimitBytes(plan.estimate_bytes, cap);
#endif
  request.set_memory_limit_bytes(prepared.memory_limit_bytes);
  request.set_job_name(job.name());
  request.set_input_name(volume.display_name());
  if (!job.spec().label_map().empty()) {
    auto label_map = resolve(job.spec().label_map(), "spec.label_map");
    if (!label_map.ok()) return label_map.status();
    request.set_label_map(label_map->string());
  }
  if (!job.spec().levels_of().empty()) {
    // The record and the segmentation it was made on, read in place from the other job's
    // artifacts (a shared data dir has them for every replica).
    auto pid = ParseName(job.spec().levels_of(), "jobs", "spec.levels_of");
    if (!pid.ok()) return pid.status();
    const fs::path dir = dd.ArtifactsDir(*pid);
    for (const char* file : {pipeline::kLevelsFileName, "labels.nii.gz"}) {
      std::error_code ec;
      if (!fs::is_regular_file(dir / file, ec)) {
        return absl::FailedPreconditionError(absl::StrCat(
            job.spec().levels_of(), " has no ", file, " any more (deleted?); ", "nothing was run"));
      }
    }
    request.set_levels_file((dir / pipeline::kLevelsFileName).string());
    request.set_label_map((dir / "labels.nii.gz").string());
  }
  request.set_out_dir(dd.job_out(id, epoch).string());
  // Checkpoints outlive the attempt (and, in a shared data dir, the replica): a requeued or
  // reclaimed job resumes after its last finished stage. The key is what the input is (the
  // blobs of its files, by sha256); the pipeline adds the spec's parameters each stage uses.
  request.set_checkpoint_dir(dd.job_checkpoints(id).string());
  request.set_checkpoint_key(CheckpointKey(job, store_));
  if (options_.allow_faults) request.set_fault(dd.ReadJobFault(id));
  if (auto st = dd.WriteFileAtomically(dd.job_request(id, epoch), request.SerializeAsString());
      !st.ok()) {
    return st;
  }
  prepared.request = dd.job_request(id, epoch);
  return prepared;
}

JobRunner::ChildEnd JobRunner::Relay(ChildProcess& child, const Lease& lease, StopFlags& stop) {
  ChildEnd end;
  FrameReader reader;
  std::string last_stored_stage;
  v1::Progress last_seen;  // the child's latest progress, the base of the drain's events
  last_seen.set_stage("start");
  Clock::time_point last_renew = Clock::now(), last_poll = Clock::now(), last_progress{},
                    last_drain_report{};
  const auto grace = std::chrono::milliseconds(options_.cancel_grace_ms);
  auto handle = [&](const worker::WorkerMessage& m) {
    if (m.has_progress()) {
      const v1::Progress& p = m.progress();
      end.stage = p.stage();
      last_seen = p;
      // Stage changes and stage ends are always stored; within a stage, at most one event per
      // progress_interval_ms, so a chatty stage cannot flood the event log.
      const bool due = p.stage() != last_stored_stage || p.fraction() >= 1.0 ||
                       MsSince(last_progress) >= options_.progress_interval_ms;
      if (due) {
        absl::Status s = store_->AppendProgress(lease, p);
        if (!s.ok()) spdlog::warn("job {}: storing progress: {}", lease.job_id, s.ToString());
        last_stored_stage = p.stage();
        last_progress = Clock::now();
      }
    } else if (m.has_result() || m.has_error()) {
      end.final = m;
    }
  };
  bool eof = false;
  for (;;) {
    if (!eof) {
      pollfd pfd{child.fd(), POLLIN, 0};
      const int pr = ::poll(&pfd, 1, 50);
      if (pr > 0) {
        char buf[65536];
        const ssize_t n = ::read(child.fd(), buf, sizeof buf);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) {
          eof = true;
          child.CloseFd();
        } else {
          reader.Append(buf, static_cast<size_t>(n));
          worker::WorkerMessage m;
          while (reader.Next(&m)) handle(m);
        }
      }
    } else if (auto st = child.TryWait()) {
      end.wait_status = *st;
      break;
    } else {
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    if (MsSince(last_renew) >= options_.lease_ms / 3) {
      last_renew = Clock::now();
      absl::Status s = store_->RenewLease(lease, options_.lease_ms);
      // Only a refused lease is lost; a store that is unreachable for a while (a shared store
      // reconnecting) is asked again at the next renewal, and the reaper decides if it lapsed.
      if (absl::IsFailedPrecondition(s) || absl::IsNotFound(s)) {
        spdlog::warn("job {}: {}; stopping its worker", lease.job_id, s.ToString());
        end.lost_lease = true;
      }
    }
    if (MsSince(last_poll) >= 500) {
      last_poll = Clock::now();
      auto c = store_->CancelRequested(lease.job_id);
      if (c.ok() && *c) stop.cancel = true;
    }
    // While the server drains, watchers learn every second how long the job has left before
    // it is stopped and requeued: the job's own stage and fraction, with the time left.
    if (const int64_t until = stop.drain_deadline_ms.load();
        until > 0 && !stop.requeue && !eof && MsSince(last_drain_report) >= 1000) {
      last_drain_report = Clock::now();
      const int64_t now_ms =
          std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now().time_since_epoch())
              .count();
      const double left = std::max<int64_t>(0, until - now_ms) / 1000.0;
      v1::Progress p = last_seen;
      p.set_message(absl::StrCat("server draining: ", static_cast<int64_t>(std::ceil(left)),
                                 " s left to finish, then requeued to resume from its last "
                                 "finished stage"));
      p.mutable_metrics()->clear();
      (*p.mutable_metrics())["drain_remaining_s"] = left;
      absl::Status s = store_->AppendProgress(lease, p);
      if (!s.ok()) spdlog::warn("job {}: storing drain progress: {}", lease.job_id, s.ToString());
    }
    if (stop.cancel || stop.requeue || end.lost_lease) child.Terminate(grace);
    if (!eof) child.TryWait();  // escalates a due SIGKILL while the pipe is still open
  }
  end.protocol = reader.status();
  if (end.protocol.ok() && reader.pending() > 0) {
    end.protocol = absl::DataLossError("the worker's last message was cut off");
  }
  return end;
}

void JobRunner::Fail(const Lease& lease, absl::StatusCode code, const std::string& message,
                     double seconds) {
  // Clients see data-dir paths relative to the data dir ("volumes/<id>/files/head.nii"): where
  // the server keeps its files is the operator's business (the log keeps the full message).
  std::string shown = message;
  const std::string root = options_.data_dir.root().string() + "/";
  for (size_t at; !root.empty() && (at = shown.find(root)) != std::string::npos;) {
    shown.erase(at, root.size());
  }
  auto r = store_->Finish(lease, v1::FAILED, Outcome(code, shown));
  if (!r.ok()) spdlog::error("job {}: recording failure: {}", lease.job_id, r.status().ToString());
  if (r.ok()) {
    options_.data_dir.RemoveJobOut(lease.job_id, lease.epoch);
    options_.data_dir.RemoveJobCheckpoints(lease.job_id);
  }
  spdlog::info("job {} FAILED after {:.3f} s: {}", lease.job_id, seconds, message);
}

void JobRunner::RecordOutcome(const v1::Job& job, const Lease& lease, const ChildEnd& end,
                              const StopFlags& stop, double secs) {
  const std::string& id = lease.job_id;
  if (end.lost_lease) {  // another claim holds the job now; its folder is not ours to keep
    options_.data_dir.RemoveAttempt(id, lease.epoch);
    return;
  }
  if (stop.cancel) {
    auto r = store_->Finish(lease, v1::CANCELLED,
                            Outcome(absl::StatusCode::kCancelled,
                                    absl::StrCat("cancelled by request during ", end.stage)));
    if (!r.ok()) spdlog::error("job {}: recording cancel: {}", id, r.status().ToString());
    if (r.ok()) {
      options_.data_dir.RemoveJobOut(id, lease.epoch);
      options_.data_dir.RemoveJobCheckpoints(id);
    }
    spdlog::info("job {} CANCELLED after {:.3f} s in stage {}", id, secs, end.stage);
    return;
  }
  if (stop.requeue) {
    const std::string resume = ResumePoint(options_.data_dir.job_checkpoints(id));
    const std::string why =
        absl::StrCat("requeued: the server shut down while it ran; the next attempt ",
                     resume.empty() ? "starts from the beginning (no stage had finished)"
                                    : absl::StrCat("resumes after ", resume));
    auto r = store_->Requeue(lease, why);
    if (!r.ok()) spdlog::error("job {}: requeue: {}", id, r.status().ToString());
    spdlog::info("job {} QUEUED again after {:.3f} s (server shutting down; {})", id, secs, why);
    return;
  }
  const bool exited = WIFEXITED(end.wait_status);
  const int code = exited ? WEXITSTATUS(end.wait_status) : -1;
  if (end.final && end.final->has_result() && exited && code == kWorkerExitOk) {
    v1::Job outcome;
    std::error_code ec;
    const fs::path out_dir = fs::weakly_canonical(options_.data_dir.job_out(id, lease.epoch), ec);
    for (const auto& a : end.final->result().artifacts()) {
      const std::string& name = a.name();
      const fs::path path = fs::weakly_canonical(fs::path(a.path()), ec);
      // Only plain names of files inside out/ are served.
      if (name.empty() || name.find('/') != std::string::npos || name[0] == '.' ||
          path.parent_path() != out_dir || !fs::is_regular_file(path, ec)) {
        return Fail(lease, absl::StatusCode::kInternal,
                    absl::StrCat("pipeline returned artifact '", name, "' at ", path.string(),
                                 ", not a file in ", out_dir.string()),
                    secs);
      }
      auto sha = Sha256OfFile(path);
      if (!sha.ok())
        return Fail(lease, sha.status().code(), std::string(sha.status().message()), secs);
      auto* art = outcome.add_artifacts();
      art->set_name(absl::StrCat(job.name(), "/artifacts/", name));
      art->set_file_name(name);
      art->set_size_bytes(static_cast<int64_t>(fs::file_size(path, ec)));
      art->set_sha256(*sha);
    }
    outcome.set_metrics_json(end.final->result().metrics_json());
    auto r = store_->Finish(lease, v1::SUCCEEDED, outcome);
    if (!r.ok()) spdlog::error("job {}: recording success: {}", id, r.status().ToString());
    if (r.ok()) options_.data_dir.RemoveJobCheckpoints(id);  // the artifacts are the result now
    spdlog::info("job {} SUCCEEDED in {:.3f} s ({} artifacts)", id, secs, outcome.artifacts_size());
    return;
  }
  if (end.final && end.final->has_error()) {
    const auto& e = end.final->error();
    return Fail(lease, static_cast<absl::StatusCode>(e.code()), e.message(), secs);
  }
  std::string why = absl::StrCat("the worker ", DescribeWaitStatus(end.wait_status));
  if (!exited && WTERMSIG(end.wait_status) == SIGKILL)
    absl::StrAppend(&why, ", e.g. out of memory");
  absl::StrAppend(&why, " during stage ", end.stage);
  if (!end.protocol.ok()) absl::StrAppend(&why, " (", end.protocol.message(), ")");
  const std::string tail = LogTail(options_.data_dir.job_log(id, lease.epoch));
  if (!tail.empty()) absl::StrAppend(&why, "; last log line: ", tail);
  Fail(lease, absl::StatusCode::kInternal, why, secs);
}

void JobRunner::Run(const Claim& claim, StopFlags& stop) {
  const v1::Job& job = claim.job;
  const Lease& lease = claim.lease;
  const auto t0 = Clock::now();
  const double queued_s =
      static_cast<double>(job.start_time().seconds() - job.create_time().seconds()) +
      (job.start_time().nanos() - job.create_time().nanos()) * 1e-9;
  spdlog::info("job {} RUNNING attempt {} epoch {} (queued {:.3f} s)", lease.job_id, job.attempts(),
               lease.epoch, queued_s);
  auto secs = [&] { return MsSince(t0) / 1000.0; };

  auto request = Prepare(job, lease.epoch);
  if (!request.ok()) {
    return Fail(lease, request.status().code(), std::string(request.status().message()), secs());
  }
  ChildOptions co;
  co.argv = {options_.worker_exe.string(), "--run-job", request->request.string()};
  co.log = options_.data_dir.job_log(lease.job_id, lease.epoch);
  co.protocol_fd = kWorkerFd;
  co.memory_mb = request->memory_limit_bytes >> 20;
  auto child = ChildProcess::Spawn(co);
  if (!child.ok()) {
    return Fail(lease, child.status().code(), std::string(child.status().message()), secs());
  }
  const ChildEnd end = Relay(**child, lease, stop);
  RecordOutcome(job, lease, end, stop, secs());
}

}  // namespace decima::server
