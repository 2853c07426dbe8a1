#include "server/service.h"

#include <google/protobuf/util/time_util.h>
#include <openssl/crypto.h>

#include <fstream>
#include <random>
#include <set>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "decima/v1/errors.pb.h"
#include "server/faults.h"
#include "server/job_spec.h"
#include "server/sha256.h"
#include "server/volume_probe.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace fs = std::filesystem;
using google::protobuf::util::TimeUtil;

grpc::Status ToGrpc(const absl::Status& s) {
  if (s.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(s.code()), std::string(s.message()));
}

std::string NewId() {
  thread_local std::mt19937_64 rng([] {
    std::random_device rd;
    std::seed_seq seq{rd(), rd(), rd(), rd()};
    return std::mt19937_64(seq);
  }());
  static const char kHex[] = "0123456789abcdef";
  uint64_t v = rng();
  std::string id(16, '0');
  for (int i = 0; i < 16; ++i) id[i] = kHex[(v >> (4 * i)) & 15];
  return id;
}

namespace {

// An error with a structured detail in the trailing metadata "decima-error-bin".
grpc::Status Fail(grpc::ServerContext* ctx, const absl::Status& s, const v1::ErrorDetail& d) {
  ctx->AddTrailingMetadata("decima-error-bin", d.SerializeAsString());
  return ToGrpc(s);
}

grpc::Status InvalidField(grpc::ServerContext* ctx, const std::string& field,
                          const std::string& message) {
  v1::ErrorDetail d;
  d.set_field(field);
  return Fail(ctx, absl::InvalidArgumentError(absl::StrCat(field, ": ", message)), d);
}

// A manifest path: relative, no "..", no empty or hidden components, printable.
bool SafeRelativePath(const std::string& p) {
  if (p.empty() || p.size() > 512 || p[0] == '/') return false;
  for (char c : p) {
    if (static_cast<unsigned char>(c) < 0x20 || c == '\\') return false;
  }
  for (absl::string_view part : absl::StrSplit(p, '/')) {
    if (part.empty() || part == "." || part == "..") return false;
  }
  return true;
}

}  // namespace

grpc::Status Services::Guard(grpc::ServerContext* ctx) const {
  if (!options_.token.empty()) {
    const auto& md = ctx->client_metadata();
    auto it = md.find("authorization");
    std::string want = "Bearer " + options_.token;
    bool ok = it != md.end() && it->second.size() == want.size() &&
              CRYPTO_memcmp(it->second.data(), want.data(), want.size()) == 0;
    if (!ok) {
      return grpc::Status(grpc::StatusCode::UNAUTHENTICATED,
                          it == md.end() ? "missing bearer token (metadata 'authorization')"
                                         : "wrong bearer token");
    }
  }
  if (draining_.load()) {
    return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                        "the server is shutting down; retry after it restarts");
  }
  return grpc::Status::OK;
}

// ---------------------------------------------------------------------------------- Uploads

class Services::UploadsImpl final : public v1::Uploads::Service {
 public:
  explicit UploadsImpl(Services* s) : s_(s) {}

  grpc::Status Upload(grpc::ServerContext* ctx, grpc::ServerReader<v1::UploadRequest>* reader,
                      v1::Blob* blob) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    v1::UploadRequest req;
    if (!reader->Read(&req)) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "empty upload stream");
    }
    const std::string sha = req.sha256();
    const int64_t size = req.size_bytes();
    if (!IsSha256Hex(sha)) return InvalidField(ctx, "sha256", "expected 64 lower-case hex digits");
    if (size < 0) return InvalidField(ctx, "size_bytes", "must be >= 0");
    if (size > s_->options_.max_upload_bytes) {
      v1::ErrorDetail d;
      d.set_field("size_bytes");
      d.set_limit("max_upload_mb");
      d.set_limit_value(s_->options_.max_upload_bytes >> 20);
      return Fail(ctx,
                  absl::InvalidArgumentError(absl::StrCat(
                      "size_bytes: ", size, " bytes exceed the server's upload limit of ",
                      s_->options_.max_upload_bytes, " bytes (--max-upload-mb ",
                      s_->options_.max_upload_bytes >> 20, "); nothing was stored")),
                  d);
    }
    blob->set_name("blobs/" + sha);
    blob->set_sha256(sha);
    blob->set_size_bytes(size);
    if (s_->blob_store_->Has(sha)) {
      blob->set_deduplicated(true);
      return grpc::Status::OK;
    }
    auto writer = s_->blob_store_->OpenWriter(sha, size, req.write_offset());
    if (!writer.ok()) {
      v1::ErrorDetail d;
      d.set_field("write_offset");
      d.set_resume_offset(s_->blob_store_->Status(sha, size).committed_size);
      return Fail(ctx, writer.status(), d);
    }
    BlobWriter& w = **writer;
    bool first = true;
    for (;;) {
      if (!first && !reader->Read(&req)) break;
      first = false;
      if (req.data().size() > kMaxChunkBytes) {
        w.Discard();
        return InvalidField(ctx, "data",
                            absl::StrCat("chunk of ", req.data().size(),
                                         " bytes exceeds 1 MiB; nothing was stored"));
      }
      if (!req.data().empty()) {
        absl::Status st = w.Append(req.data().data(), req.data().size());
        if (!st.ok()) return InvalidField(ctx, "data", std::string(st.message()));
      }
    }
    if (w.written() < size) {
      v1::ErrorDetail d;
      d.set_resume_offset(w.written());
      return Fail(
          ctx,
          absl::AbortedError(absl::StrCat("the stream ended after ", w.written(), " of ", size,
                                          " bytes; resume with write_offset=", w.written())),
          d);
    }
    absl::Status st = w.Commit();
    if (!st.ok()) {
      v1::ErrorDetail d;
      d.set_field("sha256");
      return Fail(ctx, st, d);
    }
    return grpc::Status::OK;
  }

  grpc::Status GetUploadStatus(grpc::ServerContext* ctx, const v1::GetUploadStatusRequest* req,
                               v1::UploadStatus* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    if (!IsSha256Hex(req->sha256())) {
      return InvalidField(ctx, "sha256", "expected 64 lower-case hex digits");
    }
    BlobStatus st = s_->blob_store_->Status(req->sha256(), req->size_bytes());
    resp->set_name("blobs/" + req->sha256());
    resp->set_complete(st.complete);
    resp->set_committed_size(st.committed_size);
    return grpc::Status::OK;
  }

 private:
  Services* s_;
};

// ---------------------------------------------------------------------------------- Volumes

class Services::VolumesImpl final : public v1::Volumes::Service {
 public:
  explicit VolumesImpl(Services* s) : s_(s) {}

  grpc::Status CreateVolume(grpc::ServerContext* ctx, const v1::CreateVolumeRequest* req,
                            v1::Volume* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    v1::Volume vol = req->volume();
    if (vol.files().empty()) return InvalidField(ctx, "volume.files", "at least one file needed");
    if (vol.files_size() > 100000) return InvalidField(ctx, "volume.files", "too many files");
    std::set<std::string> seen;
    std::vector<std::string> paths;
    std::vector<fs::path> sources;
    int64_t total = 0;
    for (int i = 0; i < vol.files_size(); ++i) {
      const auto& f = vol.files(i);
      std::string field = absl::StrCat("volume.files[", i, "]");
      if (!SafeRelativePath(f.path())) {
        return InvalidField(ctx, field + ".path",
                            absl::StrCat("'", f.path(), "' is not a safe relative file name"));
      }
      if (!seen.insert(f.path()).second) {
        return InvalidField(ctx, field + ".path", absl::StrCat("'", f.path(), "' appears twice"));
      }
      auto sha = ParseName(f.blob(), "blobs", field + ".blob");
      if (!sha.ok() || !IsSha256Hex(*sha)) {
        return InvalidField(ctx, field + ".blob", "expected 'blobs/{sha256}'");
      }
      auto path = s_->blob_store_->LocalPath(*sha);
      if (!path.ok()) {
        return grpc::Status(grpc::StatusCode::NOT_FOUND,
                            absl::StrCat(field, ".blob: ", f.blob(), " was not uploaded"));
      }
      std::error_code ec;
      total += static_cast<int64_t>(fs::file_size(*path, ec));
      paths.push_back(f.path());
      sources.push_back(*path);
    }
    const std::string id = NewId();
    fs::path root = s_->options_.data_dir.volume_dir(id);
    fs::path dir = s_->options_.data_dir.volume_files(id);
    // Materialize the files under their manifest names: hard links to the immutable blobs.
    for (size_t i = 0; i < paths.size(); ++i) {
      std::error_code ec;
      fs::create_directories((dir / paths[i]).parent_path(), ec);
      fs::create_hard_link(sources[i], dir / paths[i], ec);
      if (ec) {
        ec.clear();
        fs::copy_file(sources[i], dir / paths[i], ec);
      }
      if (ec) {
        fs::remove_all(root, ec);
        return grpc::Status(grpc::StatusCode::INTERNAL,
                            absl::StrCat("materializing ", paths[i], ": ", ec.message()));
      }
    }
    auto header = ProbeVolume(dir, paths, vol.format());
    if (!header.ok()) {
      std::error_code ec;
      fs::remove_all(root, ec);
      // Nothing stored: drop the blobs no other volume uses.
      for (const auto& f : vol.files()) {
        std::string sha = f.blob().substr(6);
        auto used = s_->jobs_store_->BlobInUse(sha);
        if (used.ok() && !*used) (void)s_->blob_store_->Delete(sha);
      }
      v1::ErrorDetail d;
      d.set_field("volume.files");
      return Fail(ctx, header.status(), d);
    }
    vol.set_name("volumes/" + id);
    vol.set_format(header->format);
    vol.clear_dims();
    vol.clear_spacing();
    if (header->parsed) {
      for (int i = 0; i < 3; ++i) {
        vol.add_dims(header->dims[i]);
        vol.add_spacing(header->spacing[i]);
      }
    }
    vol.set_modality(header->modality);
    vol.set_scalar_type(header->scalar_type);
    vol.set_size_bytes(total);
    *vol.mutable_create_time() = NowTimestamp();
    if (vol.display_name().empty()) vol.set_display_name(paths[0]);
    bool created = false;
    auto stored = s_->jobs_store_->CreateVolume(id, vol, req->request_id(), &created);
    if (!stored.ok() || !created) {
      std::error_code ec;
      fs::remove_all(root, ec);
    }
    if (!stored.ok()) return ToGrpc(stored.status());
    *resp = *stored;
    return grpc::Status::OK;
  }

  grpc::Status GetVolume(grpc::ServerContext* ctx, const v1::GetVolumeRequest* req,
                         v1::Volume* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "volumes", "name");
    if (!id.ok()) return ToGrpc(id.status());
    auto v = s_->jobs_store_->GetVolume(*id);
    if (!v.ok()) return ToGrpc(v.status());
    *resp = *v;
    return grpc::Status::OK;
  }

  grpc::Status ListVolumes(grpc::ServerContext* ctx, const v1::ListVolumesRequest* req,
                           v1::ListVolumesResponse* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    if (req->page_size() < 0) return InvalidField(ctx, "page_size", "must be >= 0");
    auto page = s_->jobs_store_->ListVolumes(req->page_size(), req->page_token());
    if (!page.ok()) return ToGrpc(page.status());
    for (auto& v : page->volumes) *resp->add_volumes() = std::move(v);
    resp->set_next_page_token(page->next_page_token);
    return grpc::Status::OK;
  }

  grpc::Status DeleteVolume(grpc::ServerContext* ctx, const v1::DeleteVolumeRequest* req,
                            v1::DeleteVolumeResponse*) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "volumes", "name");
    if (!id.ok()) return ToGrpc(id.status());
    absl::Status st = s_->jobs_store_->DeleteVolume(*id);
    if (!st.ok()) return ToGrpc(st);
    s_->options_.data_dir.RemoveVolume(*id);
    return grpc::Status::OK;
  }

 private:
  Services* s_;
};

// ------------------------------------------------------------------------------------- Jobs

class Services::JobsImpl final : public v1::Jobs::Service {
 public:
  explicit JobsImpl(Services* s) : s_(s) {}

  // The volumes a spec names must exist now (NOT_FOUND); their files are resolved at run time.
  grpc::Status CheckVolumes(const v1::JobSpec& spec) {
    for (const auto& [field, name] :
         {std::pair<const char*, const std::string&>{"spec.volume", spec.volume()},
          {"spec.label_map", spec.label_map()}}) {
      if (name.empty()) continue;
      auto id = ParseName(name, "volumes", field);
      if (!id.ok()) return ToGrpc(id.status());
      if (auto v = s_->jobs_store_->GetVolume(*id); !v.ok()) {
        return grpc::Status(grpc::StatusCode::NOT_FOUND,
                            absl::StrCat(field, ": ", name, " not found"));
      }
    }
    return grpc::Status::OK;
  }

  grpc::Status CreateJob(grpc::ServerContext* ctx, const v1::CreateJobRequest* req,
                         v1::Job* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    if (req->request_id().size() > 128) return InvalidField(ctx, "request_id", "too long");
    std::string field;
    auto spec = NormalizeJobSpec(req->spec(), &field);
    if (!spec.ok()) {
      v1::ErrorDetail d;
      d.set_field(field);
      return Fail(ctx, spec.status(), d);
    }
    if (auto st = CheckVolumes(*spec); !st.ok()) return st;
    const std::string id = NewId();
    // Test-only fault seam: never part of the API; without --allow-faults the key is ignored.
    if (s_->options_.allow_faults) {
      auto it = ctx->client_metadata().find(kFaultMetadataKey);
      if (it != ctx->client_metadata().end()) {
        const std::string fault(it->second.data(), it->second.size());
        if (auto st = ValidateFaults(fault); !st.ok()) return ToGrpc(st);
        const DataDir& dd = s_->options_.data_dir;
        if (auto st = dd.WriteFileAtomically(dd.job_fault(id), fault); !st.ok()) return ToGrpc(st);
      }
    }
    bool created = false;
    auto job =
        s_->jobs_store_->CreateJob(id, *spec, req->request_id(), s_->options_.max_queued, &created);
    if (!created) s_->options_.data_dir.RemoveJob(id);
    if (!job.ok()) {
      if (job.status().code() == absl::StatusCode::kResourceExhausted) {
        v1::ErrorDetail d;
        d.set_limit("max_queued");
        d.set_limit_value(s_->options_.max_queued);
        return Fail(ctx, job.status(), d);
      }
      return ToGrpc(job.status());
    }
    if (created) {
      spdlog::info("job {} QUEUED volume {}", job->name().substr(5), spec->volume());
      s_->pool_->Notify();
    }
    *resp = *job;
    return grpc::Status::OK;
  }

  grpc::Status GetJob(grpc::ServerContext* ctx, const v1::GetJobRequest* req,
                      v1::Job* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    auto job = s_->jobs_store_->GetJob(*id);
    if (!job.ok()) return ToGrpc(job.status());
    *resp = *job;
    return grpc::Status::OK;
  }

  grpc::Status ListJobs(grpc::ServerContext* ctx, const v1::ListJobsRequest* req,
                        v1::ListJobsResponse* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    if (req->page_size() < 0) return InvalidField(ctx, "page_size", "must be >= 0");
    std::vector<v1::JobState> states;
    for (int s : req->states()) {
      if (s < v1::QUEUED || s > v1::CANCELLED) {
        return InvalidField(ctx, "states", absl::StrCat(s, " is not a job state"));
      }
      states.push_back(static_cast<v1::JobState>(s));
    }
    auto page = s_->jobs_store_->ListJobs(states, req->page_size(), req->page_token());
    if (!page.ok()) return ToGrpc(page.status());
    for (auto& j : page->jobs) *resp->add_jobs() = std::move(j);
    resp->set_next_page_token(page->next_page_token);
    return grpc::Status::OK;
  }

  grpc::Status CancelJob(grpc::ServerContext* ctx, const v1::CancelJobRequest* req,
                         v1::Job* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    auto job = s_->jobs_store_->Cancel(*id);
    if (!job.ok()) return ToGrpc(job.status());
    if (job->state() == v1::RUNNING) {
      s_->pool_->Cancel(*id);
    } else if (job->state() == v1::CANCELLED) {
      spdlog::info("job {} CANCELLED while queued", *id);
    }
    *resp = *job;
    return grpc::Status::OK;
  }

  grpc::Status RetryJob(grpc::ServerContext* ctx, const v1::RetryJobRequest* req,
                        v1::Job* resp) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    auto job = s_->jobs_store_->Retry(*id, s_->options_.max_queued);
    if (!job.ok()) return ToGrpc(job.status());
    spdlog::info("job {} QUEUED again (retry)", *id);
    s_->pool_->Notify();
    *resp = *job;
    return grpc::Status::OK;
  }

  grpc::Status DeleteJob(grpc::ServerContext* ctx, const v1::DeleteJobRequest* req,
                         v1::DeleteJobResponse*) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    absl::Status st = s_->jobs_store_->DeleteJob(*id);
    if (!st.ok()) return ToGrpc(st);
    s_->options_.data_dir.RemoveJob(*id);
    spdlog::info("job {} deleted", *id);
    return grpc::Status::OK;
  }

  grpc::Status WatchJob(grpc::ServerContext* ctx, const v1::WatchJobRequest* req,
                        grpc::ServerWriter<v1::JobEvent>* writer) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    auto id = ParseName(req->name(), "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    if (req->after_sequence() < 0) return InvalidField(ctx, "after_sequence", "must be >= 0");
    // Subscribe before reading the store so that nothing committed in between is missed.
    auto channel = s_->bus_->Subscribe(*id);
    struct Unsub {
      EventBus* bus;
      std::string id;
      std::shared_ptr<EventBus::Channel> ch;
      ~Unsub() { bus->Unsubscribe(id, ch); }
    } unsub{s_->bus_, *id, channel};

    auto job = s_->jobs_store_->GetJob(*id);
    if (!job.ok()) return ToGrpc(job.status());
    int64_t last = req->after_sequence();
    {
      v1::JobEvent snap;
      snap.set_sequence(job->last_sequence());
      *snap.mutable_time() = NowTimestamp();
      *snap.mutable_snapshot() = *job;
      if (!writer->Write(snap)) return grpc::Status::CANCELLED;
    }
    // A job already final with nothing newer to send: the snapshot was the whole answer.
    if (IsFinal(job->state()) && last >= job->last_sequence()) return grpc::Status::OK;

    bool ended = false;
    // Sends `events` in order, skipping what was sent; true when a final state went out.
    auto send = [&](const std::vector<v1::JobEvent>& events) -> bool {
      for (const auto& ev : events) {
        if (ev.sequence() <= last) continue;
        if (ev.sequence() != last + 1) return false;  // a gap: the caller rereads the store
        if (!writer->Write(ev)) return false;
        last = ev.sequence();
        if (ev.has_state_change() && IsFinal(ev.state_change().state())) {
          auto now = s_->jobs_store_->GetJob(*id);
          if (now.ok() && now->last_sequence() == last) ended = true;
        }
        if (ended) return true;
      }
      return true;
    };
    auto last_write = std::chrono::steady_clock::now();
    bool need_store = true;
    for (;;) {
      if (ctx->IsCancelled()) return grpc::Status::CANCELLED;
      if (s_->draining()) {
        return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                            absl::StrCat("the server is shutting down; watch again with "
                                         "after_sequence=",
                                         last));
      }
      if (need_store) {
        auto events = s_->jobs_store_->ListEvents(*id, last, 1000);
        if (!events.ok()) return ToGrpc(events.status());
        int64_t before = last;
        send(*events);
        if (ended) return grpc::Status::OK;
        if (last != before) last_write = std::chrono::steady_clock::now();
        need_store = events->size() == 1000;
        if (need_store) continue;
      }
      std::vector<v1::JobEvent> events;
      auto wait = channel->WaitAfter(last, std::chrono::milliseconds(250), &events);
      switch (wait) {
        case EventBus::Channel::Wait::kEvents: {
          int64_t before = last;
          if (!send(events)) need_store = true;
          if (ended) return grpc::Status::OK;
          if (last == before && !need_store) need_store = true;
          if (last != before) last_write = std::chrono::steady_clock::now();
          break;
        }
        case EventBus::Channel::Wait::kGap:
          need_store = true;
          break;
        case EventBus::Channel::Wait::kClosed:
          break;  // the draining check above ends the stream
        case EventBus::Channel::Wait::kTimeout:
          break;
      }
      if (std::chrono::steady_clock::now() - last_write >=
          std::chrono::milliseconds(s_->options_.heartbeat_ms)) {
        v1::JobEvent hb;
        hb.set_sequence(last);
        *hb.mutable_time() = NowTimestamp();
        hb.mutable_heartbeat();
        if (!writer->Write(hb)) return grpc::Status::CANCELLED;
        last_write = std::chrono::steady_clock::now();
        // A heartbeat tick also rechecks the store: a cheap guard against any missed wake-up.
        need_store = true;
      }
    }
  }

 private:
  Services* s_;
};

// -------------------------------------------------------------------------------- Artifacts

class Services::ArtifactsImpl final : public v1::Artifacts::Service {
 public:
  explicit ArtifactsImpl(Services* s) : s_(s) {}

  grpc::Status ReadArtifact(grpc::ServerContext* ctx, const v1::ReadArtifactRequest* req,
                            grpc::ServerWriter<v1::ReadArtifactResponse>* writer) override {
    if (auto g = s_->Guard(ctx); !g.ok()) return g;
    // jobs/{id}/artifacts/{file}
    std::vector<std::string> parts = absl::StrSplit(req->name(), '/');
    if (parts.size() != 4 || parts[0] != "jobs" || parts[2] != "artifacts") {
      return InvalidField(
          ctx, "name",
          absl::StrCat("expected 'jobs/{id}/artifacts/{file}', got '", req->name(), "'"));
    }
    auto id = ParseName("jobs/" + parts[1], "jobs", "name");
    if (!id.ok()) return ToGrpc(id.status());
    if (req->read_offset() < 0 || req->read_limit() < 0) {
      return InvalidField(ctx, "read_offset", "offset and limit must be >= 0");
    }
    auto job = s_->jobs_store_->GetJob(*id);
    if (!job.ok()) return ToGrpc(job.status());
    if (job->state() != v1::SUCCEEDED) {
      return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                          absl::StrCat(job->name(), " is ", v1::JobState_Name(job->state()),
                                       "; artifacts exist only for SUCCEEDED jobs"));
    }
    const v1::Artifact* art = nullptr;
    for (const auto& a : job->artifacts()) {
      if (a.name() == req->name()) art = &a;
    }
    if (art == nullptr) {
      return grpc::Status(grpc::StatusCode::NOT_FOUND, absl::StrCat(req->name(), " not found"));
    }
    fs::path path = s_->options_.data_dir.job_out(*id) / art->file_name();
    std::ifstream in(path, std::ios::binary);
    if (!in) {
      return grpc::Status(grpc::StatusCode::DATA_LOSS,
                          absl::StrCat(req->name(), ": the file is missing on the server"));
    }
    const int64_t total = art->size_bytes();
    if (req->read_offset() > total) {
      return grpc::Status(
          grpc::StatusCode::OUT_OF_RANGE,
          absl::StrCat("read_offset ", req->read_offset(), " is past the end (", total, " bytes)"));
    }
    int64_t end =
        req->read_limit() > 0 ? std::min(total, req->read_offset() + req->read_limit()) : total;
    in.seekg(req->read_offset());
    int64_t pos = req->read_offset();
    v1::ReadArtifactResponse chunk;
    std::string buf;
    do {
      size_t n = static_cast<size_t>(std::min<int64_t>(kMaxChunkBytes, end - pos));
      buf.resize(n);
      if (n > 0 && !in.read(buf.data(), static_cast<std::streamsize>(n))) {
        return grpc::Status(grpc::StatusCode::DATA_LOSS,
                            absl::StrCat(req->name(), ": short read on the server"));
      }
      chunk.set_offset(pos);
      chunk.set_total_size(total);
      chunk.set_data(buf);
      if (!writer->Write(chunk)) return grpc::Status::CANCELLED;
      pos += static_cast<int64_t>(n);
    } while (pos < end);
    return grpc::Status::OK;
  }

 private:
  Services* s_;
};

// --------------------------------------------------------------------------------- Services

Services::Services(ServiceOptions options, JobStore* jobs, BlobStore* blobs, EventBus* bus,
                   WorkerPool* pool)
    : options_(std::move(options)),
      jobs_store_(jobs),
      blob_store_(blobs),
      bus_(bus),
      pool_(pool),
      uploads_(std::make_unique<UploadsImpl>(this)),
      volumes_(std::make_unique<VolumesImpl>(this)),
      jobs_(std::make_unique<JobsImpl>(this)),
      artifacts_(std::make_unique<ArtifactsImpl>(this)) {}

Services::~Services() = default;

void Services::StartDraining() { draining_ = true; }

grpc::Service* Services::uploads() { return uploads_.get(); }
grpc::Service* Services::volumes() { return volumes_.get(); }
grpc::Service* Services::jobs() { return jobs_.get(); }
grpc::Service* Services::artifacts() { return artifacts_.get(); }

}  // namespace decima::server
