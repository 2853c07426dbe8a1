// The one owner of the data-dir layout. Nothing else in the server joins path components under
// --data-dir.
//
//   LOCK                     flock: exclusive for the embedded SQLite store (one server per
//                            data dir; the kernel drops it on death), shared for replicas of a
//                            PostgreSQL store, which share the whole data dir (a ReadWriteMany
//                            volume): a job may run on any replica and its volumes, blobs and
//                            artifacts must be readable by every other
//   jobs.sqlite              the embedded job store (WAL); absent with --store postgresql://
//   blobs/                   the blob store (blob_store.h)
//   volumes/<id>/files/...   a volume's files under their manifest names (hard links to blobs)
//   jobs/<id>/fault          test-only fault (faults.h), written only with --allow-faults
//   dicom-spool/             C-STORE instances being received (dicom_receiver.h), then blobs
//   jobs/<id>/attempts/<epoch>/request.pb  what the child of that claim runs (worker.proto)
//   jobs/<id>/attempts/<epoch>/worker.log  the child's stdout and stderr
//   jobs/<id>/attempts/<epoch>/out/        the artifacts of that claim
//   jobs/<id>/checkpoints/   stage checkpoints (core/pipeline/checkpoint.h), kept across claims
//                            and replicas so a requeued job resumes; removed when it ends
// One folder per claim (the lease epoch): a replica that lost its lease while its child still
// writes cannot touch the files of the claim that replaced it. A SUCCEEDED job's artifacts are
// in its highest-numbered attempt: after the claim that succeeded no other claim is possible
// (Retry applies to FAILED and CANCELLED jobs only).
// Thread-safety: immutable after construction; the file operations touch one job or volume.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

#include "absl/status/status.h"

namespace decima::server {

class DataDir {
 public:
  explicit DataDir(std::filesystem::path root) : root_(std::move(root)) {}

  const std::filesystem::path& root() const { return root_; }
  std::filesystem::path lock_file() const { return root_ / "LOCK"; }
  std::filesystem::path job_store() const { return root_ / "jobs.sqlite"; }
  std::filesystem::path blobs() const { return root_ / "blobs"; }
  std::filesystem::path dicom_spool() const { return root_ / "dicom-spool"; }

  std::filesystem::path volume_dir(const std::string& id) const { return root_ / "volumes" / id; }
  std::filesystem::path volume_files(const std::string& id) const {
    return volume_dir(id) / "files";
  }

  std::filesystem::path job_dir(const std::string& id) const { return root_ / "jobs" / id; }
  std::filesystem::path job_attempt(const std::string& id, int64_t epoch) const {
    return job_dir(id) / "attempts" / std::to_string(epoch);
  }
  std::filesystem::path job_out(const std::string& id, int64_t epoch) const {
    return job_attempt(id, epoch) / "out";
  }
  std::filesystem::path job_log(const std::string& id, int64_t epoch) const {
    return job_attempt(id, epoch) / "worker.log";
  }
  std::filesystem::path job_request(const std::string& id, int64_t epoch) const {
    return job_attempt(id, epoch) / "request.pb";
  }
  std::filesystem::path job_fault(const std::string& id) const { return job_dir(id) / "fault"; }
  std::filesystem::path job_checkpoints(const std::string& id) const {
    return job_dir(id) / "checkpoints";
  }

  // An empty out/ for the claim `epoch`; the folders of earlier claims are removed.
  absl::Status ResetJobOut(const std::string& id, int64_t epoch) const;
  // The highest claim epoch with a folder, 0 if none.
  int64_t LatestAttempt(const std::string& id) const;
  // Where a SUCCEEDED job's artifacts are: the out/ of its highest claim, or jobs/<id>/out/ for
  // a job that finished before attempt folders existed (data dirs of older servers).
  std::filesystem::path ArtifactsDir(const std::string& id) const;
  // Removes the folder of one claim (a runner that lost its lease; best effort).
  void RemoveAttempt(const std::string& id, int64_t epoch) const;
  // Removes the out/ of claim `epoch`: a job that did not succeed serves no artifact, and its
  // partial output would only hold disk space (its worker.log stays for the record).
  void RemoveJobOut(const std::string& id, int64_t epoch) const;
  // Removes the stage checkpoints of a job that ended (succeeded, failed or cancelled): a Retry
  // starts from the beginning, and the simplified mesh of a large scan is hundreds of MB.
  void RemoveJobCheckpoints(const std::string& id) const;
  // Writes `bytes` to `path` through a temporary file and a rename.
  absl::Status WriteFileAtomically(const std::filesystem::path& path,
                                   const std::string& bytes) const;
  // The test fault of a job ("" if none).
  std::string ReadJobFault(const std::string& id) const;
  // Removes jobs/<id>/ or volumes/<id>/ (best effort: the store row is already gone).
  void RemoveJob(const std::string& id) const;
  void RemoveVolume(const std::string& id) const;

 private:
  std::filesystem::path root_;
};

}  // namespace decima::server
