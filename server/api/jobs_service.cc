// decima.v1.Jobs: queue, cancel, retry, delete, watch.
#include <google/protobuf/util/message_differencer.h>

#include <string_view>

#include "absl/strings/str_cat.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "server/api/grpc_util.h"
#include "server/api/handler.h"
#include "server/api/service.h"
#include "server/api/watch_loop.h"
#include "server/dicom/dicom_receiver.h"
#include "server/jobs/faults.h"
#include "server/jobs/job_memory.h"
#include "server/jobs/job_spec.h"
#include "server/util/ids.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace {

// Validates and normalizes the spec (job_spec.h), checks its volumes exist, keeps a test fault
// beside the job when the server allows faults, and queues it. `detail` names the bad field or
// the limit hit.
// The caller must be allowed to read the volumes (a submitter: its own).
absl::StatusOr<v1::Job> SubmitJob(const ServiceDeps& d, const Principal& caller,
                                  const v1::CreateJobRequest& req, const std::string& fault,
                                  v1::ErrorDetail* detail) {
  if (req.request_id().size() > 128) {
    detail->set_field("request_id");
    return absl::InvalidArgumentError("request_id: too long (at most 128 bytes)");
  }
  if (auto st = RefuseReceiverRequestId(req.request_id()); !st.ok()) {
    detail->set_field("request_id");
    return st;
  }
  std::string field;
  v1::JobSpec asked = req.spec();
  if (!asked.levels_of().empty()) {
    // A level of another job: that job must be the caller's to read, and its spec completes
    // this one (volume, segmentation).
    auto pid = ParseName(asked.levels_of(), "jobs", "spec.levels_of");
    if (!pid.ok()) {
      detail->set_field("spec.levels_of");
      return pid.status();
    }
    auto parent = d.jobs->GetJob(*pid);
    if (absl::IsNotFound(parent.status())) {
      detail->set_field("spec.levels_of");
      return absl::NotFoundError(absl::StrCat("spec.levels_of: ", asked.levels_of(), " not found"));
    }
    if (!parent.ok()) return parent.status();
    if (auto may = CallGuard::MayRead(caller, parent->creator(), asked.levels_of()); !may.ok()) {
      detail->set_field("spec.levels_of");
      return absl::PermissionDeniedError(may.error_message());
    }
    auto completed = LevelJobSpec(asked, *parent, &field);
    if (!completed.ok()) {
      detail->set_field(field);
      return completed.status();
    }
    asked = std::move(*completed);
  }
  auto spec = NormalizeJobSpec(asked, &field);
  if (!spec.ok()) {
    detail->set_field(field);
    return spec.status();
  }
  JobMemoryPlan plan;
  // The volumes must exist now (NOT_FOUND); their files are resolved when the job runs.
  for (const auto& [name, value] :
       {std::pair<const char*, const std::string&>{"spec.volume", spec->volume()},
        {"spec.label_map", spec->label_map()}}) {
    if (value.empty()) continue;
    auto id = ParseName(value, "volumes", name);
    if (!id.ok()) return id.status();
    auto vol = d.jobs->GetVolume(*id);
    // Only a volume the store says is missing is NOT_FOUND; a store that cannot answer is its
    // own error (UNAVAILABLE: retry), never "not found" for a volume that exists.
    if (absl::IsNotFound(vol.status())) {
      return absl::NotFoundError(absl::StrCat(name, ": ", value, " not found"));
    }
    if (!vol.ok()) return vol.status();
    if (auto may = CallGuard::MayRead(caller, vol->creator(), value); !may.ok()) {
      detail->set_field(name);
      return absl::PermissionDeniedError(may.error_message());
    }
    // Refused now rather than failed when a worker takes it: nothing is queued. The estimate
    // is the volume's (a label map is small beside the job).
    if (std::string_view(name) == "spec.volume") {
      if (auto fits = CheckJobFits(*vol, value, *spec, d.options->job_memory_cap_bytes, name,
                                   detail, &plan);
          !fits.ok()) {
        return fits;
      }
    }
  }
  // In memory or in slabs, decided once here and stored, so every replica runs the job the same
  // way and GetJob shows how.
  if (!spec->has_stream_slab_voxels()) spec->set_stream_slab_voxels(plan.stream_slab_voxels);
  // In slabs, the job keeps records of them beside its checkpoints while it simplifies, so that
  // a stopped attempt resumes after the last slab: their disk is admitted like an upload's.
  if (plan.stream_record_bytes > 0) {
    if (auto room = d.disk->Admit(plan.stream_record_bytes,
                                  absl::StrCat("simplifying ", spec->volume(),
                                               " in slabs (records of its slabs to resume from)"));
        !room.ok()) {
      detail->set_field("spec.stream_slab_voxels");
      return room;
    }
  }
  const std::string id = NewId();
  const DataDir& dd = d.options->data_dir;
  if (!fault.empty()) {
    // Written before the job is queued, so a worker never claims it without its fault.
    if (auto st = ValidateFaults(fault); !st.ok()) return st;
    if (auto st = dd.WriteFileAtomically(dd.job_fault(id), fault); !st.ok()) return st;
  }
  bool created = false;
  auto job =
      d.jobs->CreateJob(id, *spec, req.request_id(), d.options->max_queued, caller.name, &created);
  if (!created) dd.RemoveJob(id);
  if (!job.ok()) {
    if (job.status().code() == absl::StatusCode::kResourceExhausted) {
      detail->set_limit("max_queued");
      detail->set_limit_value(d.options->max_queued);
    }
    return job.status();
  }
  // A request_id another principal used returns that principal's job: not to be revealed.
  if (!created) {
    if (auto may = CallGuard::MayRead(caller, job->creator(), "request_id " + req.request_id());
        !may.ok()) {
      detail->set_field("request_id");
      return absl::PermissionDeniedError(may.error_message());
    }
  }
  // AIP-155: a request id names one request. Reused with another spec it is a client error,
  // not a retry: answering with the old job would silently run other parameters.
  if (!created && !google::protobuf::util::MessageDifferencer::Equals(job->spec(), *spec)) {
    detail->set_field("request_id");
    return absl::AlreadyExistsError(
        absl::StrCat("request_id: '", req.request_id(), "' was used for ", job->name(),
                     " with a different spec; use a new request id for a different job"));
  }
  if (created) {
    spdlog::info("job {} QUEUED volume {}", id, spec->volume());
    d.pool->Notify();
  }
  return job;
}

class JobsService final : public v1::Jobs::Service {
 public:
  explicit JobsService(const ServiceDeps& d)
      : d_(d),
        watch_(d.jobs, d.bus,
               WatchOptions{.heartbeat = std::chrono::milliseconds(d.options->heartbeat_ms)}) {}

  grpc::Status CreateJob(grpc::ServerContext* ctx, const v1::CreateJobRequest* req,
                         v1::Job* resp) override {
    return Audited(d_, ctx, "CreateJob", "", [&](const Principal& caller, std::string& resource) {
      grpc::Status st = DoCreateJob(ctx, caller, *req, resp);
      if (st.ok()) resource = resp->name();
      return st;
    });
  }

  grpc::Status DoCreateJob(grpc::ServerContext* ctx, const Principal& caller,
                           const v1::CreateJobRequest& request, v1::Job* resp) {
    const v1::CreateJobRequest* req = &request;
    if (auto may = CallGuard::MayCreate(caller, "jobs"); !may.ok()) return may;
    // The test seam: without --allow-faults the key is never looked at.
    std::string fault;
    if (d_.options->allow_faults) {
      auto it = ctx->client_metadata().find(kFaultMetadataKey);
      if (it != ctx->client_metadata().end()) fault.assign(it->second.data(), it->second.size());
    }
    v1::ErrorDetail detail;
    auto job = SubmitJob(d_, caller, *req, fault, &detail);
    if (!job.ok()) return Fail(ctx, job.status(), detail);
    *resp = std::move(*job);
    return grpc::Status::OK;
  }

  // CreateJob's memory check before the volume exists: a caller that may create jobs asks with
  // the dims of a file's header, and nothing is stored or audited (it changes nothing).
  grpc::Status CheckJobMemory(grpc::ServerContext* ctx, const v1::CheckJobMemoryRequest* req,
                              v1::CheckJobMemoryResponse* resp) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      if (auto may = CallGuard::MayCreate(caller, "jobs"); !may.ok()) return may;
      if (req->display_name().size() > 1024) {
        return InvalidField(ctx, "display_name", "too long (at most 1024 bytes)");
      }
      std::string field;
      if (auto st = ValidateVolumeSize(req->dims(), req->size_bytes(), &field); !st.ok()) {
        v1::ErrorDetail detail;
        detail.set_field(field);
        return Fail(ctx, st, detail);
      }
      v1::Volume volume;
      *volume.mutable_dims() = req->dims();
      volume.set_size_bytes(req->size_bytes());
      const int64_t cap = d_.options->job_memory_cap_bytes;
      const std::string name = req->display_name().empty() ? "the volume" : req->display_name();
      v1::ErrorDetail detail;
      JobMemoryPlan plan;
      auto fits = CheckJobFits(volume, name, req->spec(), cap, "dims", &detail, &plan);
      if (!fits.ok()) return Fail(ctx, fits, detail);
      resp->set_fits(true);
      resp->set_estimate_mb((plan.estimate_bytes + (int64_t{1} << 20) - 1) >> 20);
      resp->set_limit_mb(cap > 0 ? cap >> 20 : 0);
      resp->set_stream_slab_voxels(plan.stream_slab_voxels);
      return grpc::Status::OK;
    });
  }

  grpc::Status GetJob(grpc::ServerContext* ctx, const v1::GetJobRequest* req,
                      v1::Job* resp) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      auto id = ParseName(req->name(), "jobs", "name");
      if (!id.ok()) return ToGrpc(id.status());
      auto job = d_.jobs->GetJob(*id);
      if (!job.ok()) return ToGrpc(job.status());
      if (auto may = CallGuard::MayRead(caller, job->creator(), req->name()); !may.ok()) return may;
      *resp = std::move(*job);
      return grpc::Status::OK;
    });
  }

  grpc::Status ListJobs(grpc::ServerContext* ctx, const v1::ListJobsRequest* req,
                        v1::ListJobsResponse* resp) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      if (req->page_size() < 0) return InvalidField(ctx, "page_size", "must be >= 0");
      std::vector<v1::JobState> states;
      for (int s : req->states()) {
        if (s < v1::QUEUED || s > v1::CANCELLED) {
          return InvalidField(ctx, "states", absl::StrCat(s, " is not a job state"));
        }
        states.push_back(static_cast<v1::JobState>(s));
      }
      auto page = d_.jobs->ListJobs(states, CallGuard::ListFilter(caller), req->page_size(),
                                    req->page_token());
      if (!page.ok()) return ToGrpc(page.status());
      for (auto& j : page->jobs) *resp->add_jobs() = std::move(j);
      resp->set_next_page_token(page->next_page_token);
      return grpc::Status::OK;
    });
  }

  grpc::Status CancelJob(grpc::ServerContext* ctx, const v1::CancelJobRequest* req,
                         v1::Job* resp) override {
    return Audited(d_, ctx, "CancelJob", req->name(), [&](const Principal& caller, std::string&) {
      return DoCancelJob(caller, *req, resp);
    });
  }

  grpc::Status DoCancelJob(const Principal& caller, const v1::CancelJobRequest& request,
                           v1::Job* resp) {
    const v1::CancelJobRequest* req = &request;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    if (auto may = MayWriteJob(caller, *id, req->name()); !may.ok()) return may;
    auto job = d_.jobs->Cancel(*id);
    if (!job.ok()) return ToGrpc(job.status());
    // Running here: stop its child now (a runner elsewhere sees the request when it polls).
    if (job->state() == v1::RUNNING) d_.pool->Cancel(*id);
    *resp = std::move(*job);
    return grpc::Status::OK;
  }

  grpc::Status RetryJob(grpc::ServerContext* ctx, const v1::RetryJobRequest* req,
                        v1::Job* resp) override {
    return Audited(d_, ctx, "RetryJob", req->name(), [&](const Principal& caller, std::string&) {
      return DoRetryJob(caller, *req, resp);
    });
  }

  grpc::Status DoRetryJob(const Principal& caller, const v1::RetryJobRequest& request,
                          v1::Job* resp) {
    const v1::RetryJobRequest* req = &request;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    if (auto may = MayWriteJob(caller, *id, req->name()); !may.ok()) return may;
    auto job = d_.jobs->Retry(*id, d_.options->max_queued);
    if (!job.ok()) return ToGrpc(job.status());
    spdlog::info("job {} QUEUED again (retry)", *id);
    d_.pool->Notify();
    *resp = std::move(*job);
    return grpc::Status::OK;
  }

  grpc::Status DeleteJob(grpc::ServerContext* ctx, const v1::DeleteJobRequest* req,
                         v1::DeleteJobResponse*) override {
    return Audited(d_, ctx, "DeleteJob", req->name(), [&](const Principal& caller, std::string&) {
      return DoDeleteJob(caller, *req);
    });
  }

  grpc::Status DoDeleteJob(const Principal& caller, const v1::DeleteJobRequest& request) {
    const v1::DeleteJobRequest* req = &request;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    if (auto may = MayWriteJob(caller, *id, req->name()); !may.ok()) return may;
    if (auto st = NoLevelJobReads(req->name()); !st.ok()) return ToGrpc(st);
    d_.disk->BeforeDelete();
    if (auto st = d_.jobs->DeleteJob(*id); !st.ok()) return ToGrpc(st);
    d_.options->data_dir.RemoveJob(*id);
    spdlog::info("job {} deleted", *id);
    return grpc::Status::OK;
  }

  grpc::Status WatchJob(grpc::ServerContext* ctx, const v1::WatchJobRequest* req,
                        grpc::ServerWriter<v1::JobEvent>* writer) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      auto id = ParseName(req->name(), "jobs", "name");
      if (!id.ok()) return ToGrpc(id.status());
      {
        auto job = d_.jobs->GetJob(*id);
        if (!job.ok()) return ToGrpc(job.status());
        if (auto may = CallGuard::MayRead(caller, job->creator(), req->name()); !may.ok()) {
          return may;
        }
      }
      if (req->after_sequence() < 0) return InvalidField(ctx, "after_sequence", "must be >= 0");
      WatchControls controls;
      controls.send = [writer](const v1::JobEvent& ev) { return writer->Write(ev); };
      controls.cancelled = [ctx] { return ctx->IsCancelled(); };
      controls.draining = [this] { return d_.guard->draining(); };
      return ToGrpc(watch_.Run(*id, req->after_sequence(), controls));
    });
  }

 private:
  // FAILED_PRECONDITION while a queued or running level job (spec.levels_of) reads its mesh from
  // the record of job `name`: deleting the record would fail that job when it runs. Any caller's
  // level job counts, and the caller is told only its name and state.
  absl::Status NoLevelJobReads(const std::string& name) const {
    std::string token;
    for (int page = 0; page < 10000; ++page) {
      auto jobs = d_.jobs->ListJobs({v1::QUEUED, v1::RUNNING}, "", 500, token);
      if (!jobs.ok()) return jobs.status();
      for (const v1::Job& j : jobs->jobs) {
        if (j.spec().levels_of() != name) continue;
        return absl::FailedPreconditionError(absl::StrCat(
            name, " is read by the level job ", j.name(), " (", v1::JobState_Name(j.state()),
            "); delete it once that job has ended, or cancel that job first"));
      }
      if (jobs->next_page_token.empty()) return absl::OkStatus();
      token = jobs->next_page_token;
    }
    return absl::OkStatus();
  }

  // NOT_FOUND for a missing job, PERMISSION_DENIED when `caller` may not change it.
  grpc::Status MayWriteJob(const Principal& caller, const std::string& id,
                           const std::string& name) const {
    auto job = d_.jobs->GetJob(id);
    if (!job.ok()) return ToGrpc(job.status());
    return CallGuard::MayWrite(caller, job->creator(), name);
  }

  const ServiceDeps d_;
  WatchLoop watch_;
};

}  // namespace

std::unique_ptr<grpc::Service> MakeJobsService(const ServiceDeps& deps) {
  return std::make_unique<JobsService>(deps);
}

}  // namespace decima::server
