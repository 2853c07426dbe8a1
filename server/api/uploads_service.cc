// decima.v1.Uploads: resumable, content-addressed blob uploads (blob_store.h).
#include <functional>

#include "absl/strings/str_cat.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "server/api/grpc_util.h"
#include "server/api/handler.h"
#include "server/api/service.h"
#include "server/util/sha256.h"

namespace decima::server {
namespace {

// Stores one upload: `first` declares sha256, size and offset (and may carry data), `next`
// yields the following messages. Fills `blob`; on error `detail` names the field or the offset
// to resume from.
absl::Status ReceiveUpload(BlobStore& blobs, DiskSpace& disk, int64_t max_bytes,
                           const v1::UploadRequest& first,
                           const std::function<bool(v1::UploadRequest*)>& next, v1::Blob* blob,
                           v1::ErrorDetail* detail) {
  const std::string& sha = first.sha256();
  const int64_t size = first.size_bytes();
  auto invalid = [&](const char* field, const std::string& message) {
    detail->set_field(field);
    return absl::InvalidArgumentError(absl::StrCat(field, ": ", message));
  };
  if (!IsSha256Hex(sha)) return invalid("sha256", "expected 64 lower-case hex digits");
  if (size < 0) return invalid("size_bytes", "must be >= 0");
  if (size > max_bytes) {
    detail->set_limit("max_upload_mb");
    detail->set_limit_value(max_bytes >> 20);
    return invalid("size_bytes", absl::StrCat(size, " bytes exceed the server's upload limit of ",
                                              max_bytes, " bytes (--max-upload-mb ",
                                              max_bytes >> 20, "); nothing was stored"));
  }
  blob->set_name("blobs/" + sha);
  blob->set_sha256(sha);
  blob->set_size_bytes(size);
  if (blobs.Has(sha)) {
    blobs.Claim(sha);  // held for this client's CreateVolume like a fresh upload
    blob->set_deduplicated(true);
    return absl::OkStatus();
  }
  if (first.write_offset() >= 0 && first.write_offset() <= size) {
    if (absl::Status st =
            disk.Admit(size - first.write_offset(), absl::StrCat("upload of blob ", sha));
        !st.ok()) {
      detail->set_limit("disk_free_bytes");
      detail->set_limit_value(disk.Free());
      return st;
    }
  }
  auto writer = blobs.OpenWriter(sha, size, first.write_offset());
  if (!writer.ok()) {
    detail->set_field("write_offset");
    detail->set_resume_offset(blobs.Status(sha, size).committed_size);
    return writer.status();
  }
  BlobWriter& w = **writer;
  v1::UploadRequest req = first;
  do {
    if (req.data().size() > kMaxChunkBytes) {
      w.Discard();
      return invalid("data", absl::StrCat("chunk of ", req.data().size(),
                                          " bytes exceeds 1 MiB; nothing was stored"));
    }
    if (!req.data().empty()) {
      absl::Status st = w.Append(req.data().data(), req.data().size());
      if (absl::IsResourceExhausted(st)) {
        detail->set_limit("disk_free_bytes");
        detail->set_limit_value(disk.Free());
        return st;
      }
      if (!st.ok()) return invalid("data", std::string(st.message()));
    }
  } while (next(&req));
  if (w.written() < size) {
    detail->set_resume_offset(w.written());
    return absl::AbortedError(absl::StrCat("the stream ended after ", w.written(), " of ", size,
                                           " bytes; resume with write_offset=", w.written()));
  }
  absl::Status st = w.Commit();
  if (absl::IsResourceExhausted(st)) {
    detail->set_limit("disk_free_bytes");
    detail->set_limit_value(disk.Free());
  } else if (!st.ok()) {
    detail->set_field("sha256");
  }
  return st;
}

class UploadsService final : public v1::Uploads::Service {
 public:
  explicit UploadsService(const ServiceDeps& d) : d_(d) {}

  grpc::Status Upload(grpc::ServerContext* ctx, grpc::ServerReader<v1::UploadRequest>* reader,
                      v1::Blob* blob) override {
    return Audited(
        d_, ctx, "Upload", "", [&](const Principal& caller, std::string& resource) -> grpc::Status {
          v1::UploadRequest first;
          if (!reader->Read(&first)) {
            return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "empty upload stream");
          }
          // Blobs are content-addressed and shared (deduplicated), so they have no creator; the
          // volume made of them has.
          if (IsSha256Hex(first.sha256())) resource = "blobs/" + first.sha256();
          if (auto may = CallGuard::MayCreate(caller, "uploads"); !may.ok()) return may;
          v1::ErrorDetail detail;
          absl::Status st = ReceiveUpload(
              *d_.blobs, *d_.disk, d_.options->max_upload_bytes, first,
              [reader](v1::UploadRequest* r) { return reader->Read(r); }, blob, &detail);
          return st.ok() ? grpc::Status::OK : Fail(ctx, st, detail);
        });
  }

  grpc::Status GetUploadStatus(grpc::ServerContext* ctx, const v1::GetUploadStatusRequest* req,
                               v1::UploadStatus* resp) override {
    // Every role: it tells only whether bytes with this hash are stored.
    return Guarded(d_, ctx, [&](const Principal&) -> grpc::Status {
      if (!IsSha256Hex(req->sha256())) {
        return InvalidField(ctx, "sha256", "expected 64 lower-case hex digits");
      }
      const BlobStatus st = d_.blobs->Status(req->sha256(), req->size_bytes());
      // A client that sees "complete" skips the upload and names the blob in CreateVolume next.
      if (st.complete) d_.blobs->Claim(req->sha256());
      resp->set_name("blobs/" + req->sha256());
      resp->set_complete(st.complete);
      resp->set_committed_size(st.committed_size);
      return grpc::Status::OK;
    });
  }

 private:
  const ServiceDeps d_;
};

}  // namespace

std::unique_ptr<grpc::Service> MakeUploadsService(const ServiceDeps& deps) {
  return std::make_unique<UploadsService>(deps);
}

}  // namespace decima::server
