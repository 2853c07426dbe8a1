// Volumes made of uploaded blobs: CreateVolume checks the manifest, materializes the files under
// volumes/<id>/files/ (hard links to the immutable blobs), reads the header (format, dims,
// spacing, modality; no voxel is decoded) and records the volume; DeleteVolume undoes it and
// lets go of the blobs no other volume holds. The catalog is the one place that knows which
// blobs are referenced, so the blob collector runs here too. A failed CreateVolume deletes
// nothing: the blobs it named belong to their uploads (another client may be about to use them)
// and leave by the collector once their claim lapsed.
// Thread-safety: as the stores it uses (any thread).
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "decima/v1/errors.pb.h"
#include "decima/v1/volumes.pb.h"
#include "server/files/blob_store.h"
#include "server/files/data_dir.h"
#include "server/files/disk_space.h"
#include "server/store/job_store.h"

namespace decima::server {

class VolumeCatalog {
 public:
  VolumeCatalog(const DataDir* data_dir, JobStore* jobs, BlobStore* blobs, DiskSpace* disk,
                BlobSweepPolicy sweep)
      : data_dir_(data_dir), jobs_(jobs), blobs_(blobs), disk_(disk), sweep_(sweep) {}

  // The stored volume: a new one, or with `reused` set the one created first with the same
  // request_id, or `creator`'s live volume of the same content (VolumeContentKey; its
  // display_name stays the first one's). INVALID_ARGUMENT for an unsafe or repeated path, a
  // malformed blob name, or a header that does not parse (`detail->field` names the field);
  // NOT_FOUND for a blob that was not uploaded. `creator` (the caller's principal) is recorded
  // in Volume.creator.
  absl::StatusOr<v1::Volume> Create(const v1::CreateVolumeRequest& request,
                                    const std::string& creator, v1::ErrorDetail* detail);
  // FAILED_PRECONDITION while a queued or running job reads it (as its volume or label map).
  // Its blobs that no other volume uses and whose upload claim lapsed are removed at once.
  absl::Status Delete(const std::string& id);
  // Removes the blobs nobody holds and abandoned partial uploads (blob_store.h).
  BlobSweepStats CollectGarbage();

 private:
  std::function<bool(const std::string&)> InUse() const;

  const DataDir* data_dir_;
  JobStore* jobs_;
  BlobStore* blobs_;
  DiskSpace* disk_;
  const BlobSweepPolicy sweep_;
};

// A manifest path: relative, no "..", no empty or hidden components, printable.
bool SafeRelativePath(const std::string& path);

// What makes two volumes the same content: the sha256 of the parsed format, the
// series_instance_uid and the manifest's (path, blob) pairs in path order (the order a client
// lists its files in does not matter; a renamed file does, since names pick the header file).
std::string VolumeContentKey(const v1::Volume& volume);

}  // namespace decima::server
