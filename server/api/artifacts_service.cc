// decima.v1.Artifacts: a SUCCEEDED job's files, streamed in chunks with offsets.
#include <fstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "decima/v1/artifacts.grpc.pb.h"
#include "server/api/grpc_util.h"
#include "server/api/handler.h"
#include "server/api/service.h"

namespace decima::server {
namespace {

// An open artifact and the byte range [begin, end) to send.
struct ArtifactRange {
  std::ifstream file;
  int64_t begin = 0, end = 0, total = 0;
};

// "jobs/{id}/artifacts/{file}" of a SUCCEEDED job, opened at `offset`, up to `limit` bytes
// (0 = to the end). INVALID_ARGUMENT for a malformed name or a negative offset or limit,
// NOT_FOUND, FAILED_PRECONDITION for a job that did not succeed, OUT_OF_RANGE past the end,
// DATA_LOSS when the file is gone from the data dir.
absl::StatusOr<ArtifactRange> OpenArtifact(const ServiceDeps& d, const Principal& caller,
                                           const std::string& name, int64_t offset, int64_t limit) {
  std::vector<std::string> parts = absl::StrSplit(name, '/');
  if (parts.size() != 4 || parts[0] != "jobs" || parts[2] != "artifacts") {
    return absl::InvalidArgumentError(
        absl::StrCat("name: expected 'jobs/{id}/artifacts/{file}', got '", name, "'"));
  }
  auto id = ParseName("jobs/" + parts[1], "jobs", "name");
  if (!id.ok()) return id.status();
  if (offset < 0 || limit < 0) {
    return absl::InvalidArgumentError("read_offset: offset and limit must be >= 0");
  }
  auto job = d.jobs->GetJob(*id);
  if (!job.ok()) return job.status();
  if (auto may = CallGuard::MayRead(caller, job->creator(), job->name()); !may.ok()) {
    return absl::PermissionDeniedError(may.error_message());
  }
  if (job->state() != v1::SUCCEEDED) {
    return absl::FailedPreconditionError(absl::StrCat(job->name(), " is ",
                                                      v1::JobState_Name(job->state()),
                                                      "; artifacts exist only for SUCCEEDED jobs"));
  }
  const v1::Artifact* art = nullptr;
  for (const auto& a : job->artifacts()) {
    if (a.name() == name) art = &a;
  }
  if (art == nullptr) return absl::NotFoundError(absl::StrCat(name, " not found"));
  ArtifactRange r;
  r.file.open(d.options->data_dir.ArtifactsDir(*id) / art->file_name(), std::ios::binary);
  if (!r.file)
    return absl::DataLossError(absl::StrCat(name, ": the file is missing on the server"));
  r.total = art->size_bytes();
  if (offset > r.total) {
    return absl::OutOfRangeError(
        absl::StrCat("read_offset ", offset, " is past the end (", r.total, " bytes)"));
  }
  r.begin = offset;
  // limit <= total - offset, so offset + limit cannot overflow.
  r.end = limit > 0 && limit < r.total - offset ? offset + limit : r.total;
  r.file.seekg(offset);
  return r;
}

class ArtifactsService final : public v1::Artifacts::Service {
 public:
  explicit ArtifactsService(const ServiceDeps& d) : d_(d) {}

  grpc::Status ReadArtifact(grpc::ServerContext* ctx, const v1::ReadArtifactRequest* req,
                            grpc::ServerWriter<v1::ReadArtifactResponse>* writer) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      auto r = OpenArtifact(d_, caller, req->name(), req->read_offset(), req->read_limit());
      if (!r.ok()) return ToGrpc(r.status());
      v1::ReadArtifactResponse chunk;
      std::string buf;
      int64_t pos = r->begin;
      do {  // at least one message, also for an empty range
        const auto n = static_cast<size_t>(std::min<int64_t>(kMaxChunkBytes, r->end - pos));
        buf.resize(n);
        if (n > 0 && !r->file.read(buf.data(), static_cast<std::streamsize>(n))) {
          return grpc::Status(grpc::StatusCode::DATA_LOSS,
                              absl::StrCat(req->name(), ": short read on the server"));
        }
        chunk.set_offset(pos);
        chunk.set_total_size(r->total);
        chunk.set_data(buf);
        if (!writer->Write(chunk)) return grpc::Status::CANCELLED;
        pos += static_cast<int64_t>(n);
      } while (pos < r->end);
      return grpc::Status::OK;
    });
  }

 private:
  const ServiceDeps d_;
};

}  // namespace

std::unique_ptr<grpc::Service> MakeArtifactsService(const ServiceDeps& deps) {
  return std::make_unique<ArtifactsService>(deps);
}

}  // namespace decima::server
