// Content-addressed blob storage. Blobs are named by the sha256 of their bytes and written
// temp-then-rename, so a reader never sees a partial blob and the same scan is stored once.
// Interrupted uploads keep their prefix ("partial") so the client can resume.
//
// Lifetime: nothing deletes a blob on behalf of a request. A complete blob is claimed by the
// upload that stored it (or found it stored, Claim) for a grace period, during which the client
// names it in CreateVolume; after that it lives as long as a volume references it. Sweep (the
// server's collector timer, and DeleteVolume for the blobs it released) removes what nobody
// holds: blobs past their grace that no volume uses, and partial uploads idle past their expiry.
//
// Thread-safety: a BlobStore may be used from many threads, and a LocalBlobStore folder by many
// processes (replicas on a shared volume). Writing the same digest from two writers at once is
// refused (ABORTED) by OpenWriter, also when the other writer is in another process; Claim and
// Sweep exclude each other within a process (claims are file times, seen by every replica).
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"

namespace decima::server {

// Writes one blob. Append() data in order; Commit() verifies size and digest and makes the blob
// visible; destroying an uncommitted writer keeps the partial prefix for a later resume, unless
// Discard() was called.
class BlobWriter {
 public:
  virtual ~BlobWriter() = default;
  virtual int64_t written() const = 0;  // bytes held, including a resumed prefix
  // INVALID_ARGUMENT (and the partial is discarded) if the data would exceed the declared size.
  virtual absl::Status Append(const void* data, size_t size) = 0;
  // INVALID_ARGUMENT (and the partial is discarded) on a size or digest mismatch.
  virtual absl::Status Commit() = 0;
  virtual void Discard() = 0;
};

struct BlobStatus {
  bool complete = false;
  int64_t committed_size = 0;  // size when complete, else the partial prefix held
};

// What a sweep may remove.
struct BlobSweepPolicy {
  std::chrono::seconds grace{3600};            // a complete blob is held this long after a claim
  std::chrono::seconds partial_expiry{86400};  // a partial upload idle this long is abandoned
};

struct BlobSweepStats {
  int64_t blobs_removed = 0;
  int64_t partials_removed = 0;
  int64_t bytes_freed = 0;
};

class BlobStore {
 public:
  virtual ~BlobStore() = default;
  virtual bool Has(const std::string& sha256) const = 0;
  virtual BlobStatus Status(const std::string& sha256, int64_t size_bytes) const = 0;
  // Opens a writer that continues at `offset`, which must equal the partial prefix held
  // (FAILED_PRECONDITION otherwise, naming the size held). ABORTED while another writer is open.
  virtual absl::StatusOr<std::unique_ptr<BlobWriter>> OpenWriter(const std::string& sha256,
                                                                 int64_t size_bytes,
                                                                 int64_t offset) = 0;
  // A local path holding the blob's bytes (NOT_FOUND if absent). Shared storage implementations
  // materialize it into a cache first.
  virtual absl::StatusOr<std::filesystem::path> LocalPath(const std::string& sha256) const = 0;
  // Renews the claim of a complete blob (its grace starts again): an upload that found the blob
  // already stored, or a status call that reported it complete, keeps it for the CreateVolume
  // that follows. No effect on a missing blob.
  virtual void Claim(const std::string& sha256) = 0;
  // Removes every complete blob whose claim is older than `policy.grace` and for which
  // `in_use(sha256)` is false, and every partial upload idle past `policy.partial_expiry` that
  // no writer holds. With `only`, looks at those blobs (and no partial) only.
  virtual BlobSweepStats Sweep(const BlobSweepPolicy& policy,
                               const std::function<bool(const std::string&)>& in_use,
                               const std::vector<std::string>* only = nullptr) = 0;
};

// Blobs under `root`: root/sha256/ab/abcdef... and partials under root/partial/; a writer
// holds an flock on root/locks/<partial name>.lock.
class LocalBlobStore : public BlobStore {
 public:
  // Creates the folders; `fsync` makes Commit() flush data before the rename (durable blobs).
  static absl::StatusOr<std::unique_ptr<LocalBlobStore>> Open(const std::filesystem::path& root,
                                                              bool fsync = true);

  bool Has(const std::string& sha256) const override;
  BlobStatus Status(const std::string& sha256, int64_t size_bytes) const override;
  absl::StatusOr<std::unique_ptr<BlobWriter>> OpenWriter(const std::string& sha256,
                                                         int64_t size_bytes,
                                                         int64_t offset) override;
  absl::StatusOr<std::filesystem::path> LocalPath(const std::string& sha256) const override;
  void Claim(const std::string& sha256) override;
  BlobSweepStats Sweep(const BlobSweepPolicy& policy,
                       const std::function<bool(const std::string&)>& in_use,
                       const std::vector<std::string>* only = nullptr) override;

  std::filesystem::path BlobPath(const std::string& sha256) const;
  std::filesystem::path PartialPath(const std::string& sha256, int64_t size_bytes) const;

 private:
  friend class LocalBlobWriter;
  LocalBlobStore(std::filesystem::path root, bool fsync) : root_(std::move(root)), fsync_(fsync) {}
  void Release(const std::string& sha256);

  const std::filesystem::path root_;
  const bool fsync_;
  std::mutex mu_;
  std::set<std::string> writing_ ABSL_GUARDED_BY(mu_);
  std::mutex sweep_mu_;  // Claim vs Sweep
};

}  // namespace decima::server
