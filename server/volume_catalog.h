// Volumes made of uploaded blobs: CreateVolume checks the manifest, materializes the files under
// volumes/<id>/files/ (hard links to the immutable blobs), reads the header (format, dims,
// spacing, modality; no voxel is decoded) and records the volume; DeleteVolume undoes it.
// Thread-safety: as the stores it uses (any thread).
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "decima/v1/errors.pb.h"
#include "decima/v1/volumes.pb.h"
#include "server/blob_store.h"
#include "server/data_dir.h"
#include "server/job_store.h"

namespace decima::server {

class VolumeCatalog {
 public:
  VolumeCatalog(const DataDir* data_dir, JobStore* jobs, BlobStore* blobs)
      : data_dir_(data_dir), jobs_(jobs), blobs_(blobs) {}

  // The stored volume (or the one created first with the same request_id). INVALID_ARGUMENT
  // for an unsafe or repeated path, a malformed blob name, or a header that does not parse
  // (`detail->field` names the field); NOT_FOUND for a blob that was not uploaded.
  // `creator` (the caller's principal) is recorded in Volume.creator.
  absl::StatusOr<v1::Volume> Create(const v1::CreateVolumeRequest& request,
                                    const std::string& creator, v1::ErrorDetail* detail);
  // FAILED_PRECONDITION while a queued or running job reads it.
  absl::Status Delete(const std::string& id);

 private:
  const DataDir* data_dir_;
  JobStore* jobs_;
  BlobStore* blobs_;
};

// A manifest path: relative, no "..", no empty or hidden components, printable.
bool SafeRelativePath(const std::string& path);

}  // namespace decima::server
