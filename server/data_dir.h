// The one owner of the data-dir layout. Nothing else in the server joins path components under
// --data-dir; a second store (PostgreSQL, blobs on a shared volume) changes this class only.
//
//   LOCK                     one server per data dir (flock; the kernel drops it on death)
//   jobs.sqlite              the embedded job store (WAL)
//   blobs/                   the blob store (blob_store.h)
//   volumes/<id>/files/...   a volume's files under their manifest names (hard links to blobs)
//   jobs/<id>/request.pb     what the job child runs (server/worker.proto RunRequest)
//   jobs/<id>/worker.log     the child's stdout and stderr
//   jobs/<id>/fault          test-only fault (faults.h), written only with --allow-faults
//   jobs/<id>/out/           the artifacts of the current attempt
// Thread-safety: immutable after construction; the file operations touch one job or volume.
#pragma once

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

  std::filesystem::path volume_dir(const std::string& id) const { return root_ / "volumes" / id; }
  std::filesystem::path volume_files(const std::string& id) const {
    return volume_dir(id) / "files";
  }

  std::filesystem::path job_dir(const std::string& id) const { return root_ / "jobs" / id; }
  std::filesystem::path job_out(const std::string& id) const { return job_dir(id) / "out"; }
  std::filesystem::path job_log(const std::string& id) const { return job_dir(id) / "worker.log"; }
  std::filesystem::path job_request(const std::string& id) const {
    return job_dir(id) / "request.pb";
  }
  std::filesystem::path job_fault(const std::string& id) const { return job_dir(id) / "fault"; }

  // An empty jobs/<id>/out/ for a new attempt (what an earlier attempt left is removed).
  absl::Status ResetJobOut(const std::string& id) const;
  // Removes jobs/<id>/out/: a job that did not succeed serves no artifact, and its partial
  // output would only hold disk space (its worker.log stays for the record).
  void RemoveJobOut(const std::string& id) const;
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
