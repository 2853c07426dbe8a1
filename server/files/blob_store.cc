#include "server/files/blob_store.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "server/util/sha256.h"

namespace decima::server {
namespace fs = std::filesystem;

namespace {
// root/partial/<sha>-<size> -> root/locks/<sha>-<size>.lock: the flock its writer holds, kept
// out of partial/ so that folder holds upload data only.
fs::path LockOf(const fs::path& partial) {
  return partial.parent_path().parent_path() / "locks" / (partial.filename().string() + ".lock");
}
}  // namespace
namespace {

// A write error as a status: a full disk (or quota) is RESOURCE_EXHAUSTED, everything else
// INTERNAL. Names the blob, not the server's path.
absl::Status WriteError(const std::string& what, const std::string& sha, int err) {
  if (err == ENOSPC || err == EDQUOT) {
    return absl::ResourceExhaustedError(
        absl::StrCat(what, " blob ", sha,
                     ": the server's disk is full; nothing was kept, retry after "
                     "deleting jobs or volumes"));
  }
  return absl::InternalError(absl::StrCat(what, " blob ", sha, ": ", std::strerror(err)));
}

}  // namespace

class LocalBlobWriter : public BlobWriter {
 public:
  LocalBlobWriter(LocalBlobStore* store, std::string sha, int64_t size, fs::path partial, int fd,
                  int lock_fd, int64_t offset, std::unique_ptr<Sha256> hash)
      : store_(store),
        sha_(std::move(sha)),
        size_(size),
        partial_(std::move(partial)),
        fd_(fd),
        lock_fd_(lock_fd),
        written_(offset),
        hash_(std::move(hash)) {}

  ~LocalBlobWriter() override {
    if (fd_ >= 0) ::close(fd_);
    ::close(lock_fd_);  // releases the flock: the next writer, on any replica, may start
    store_->Release(sha_);
  }

  int64_t written() const override { return written_; }

  absl::Status Append(const void* data, size_t size) override {
    if (fd_ < 0) return absl::FailedPreconditionError("blob writer is closed");
    if (written_ + static_cast<int64_t>(size) > size_) {
      Discard();
      return absl::InvalidArgumentError(
          absl::StrCat("upload of ", sha_, ": more data than the ", size_, " bytes declared"));
    }
    const char* p = static_cast<const char*>(data);
    size_t left = size;
    while (left > 0) {
      ssize_t n = ::write(fd_, p, left);
      if (n < 0) {
        if (errno == EINTR) continue;
        const int err = errno;
        // A full disk is not healed by keeping a prefix the client cannot finish now.
        if (err == ENOSPC || err == EDQUOT) Discard();
        return WriteError("writing", sha_, err);
      }
      p += n;
      left -= static_cast<size_t>(n);
    }
    hash_->Update(data, size);
    written_ += static_cast<int64_t>(size);
    return absl::OkStatus();
  }

  absl::Status Commit() override {
    if (fd_ < 0) return absl::FailedPreconditionError("blob writer is closed");
    if (written_ != size_) {
      return absl::FailedPreconditionError(
          absl::StrCat("upload of ", sha_, " holds ", written_, " of ", size_, " bytes"));
    }
    std::string digest = hash_->HexDigest();
    if (digest != sha_) {
      Discard();
      return absl::InvalidArgumentError(absl::StrCat("checksum mismatch: the data's sha256 is ",
                                                     digest, ", the upload declared ", sha_,
                                                     "; nothing was stored"));
    }
    if (store_->fsync_ && ::fdatasync(fd_) != 0) {
      const int err = errno;
      if (err == ENOSPC || err == EDQUOT) Discard();
      return WriteError("flushing", sha_, err);
    }
    ::close(fd_);
    fd_ = -1;
    fs::path final_path = store_->BlobPath(sha_);
    std::error_code ec;
    fs::create_directories(final_path.parent_path(), ec);
    fs::rename(partial_, final_path, ec);
    if (ec) return WriteError("committing", sha_, ec.value());
    // The upload's claim starts now (rename kept the partial's times).
    ::utimensat(AT_FDCWD, final_path.c_str(), nullptr, 0);
    fs::remove(LockOf(partial_), ec);
    return absl::OkStatus();
  }

  void Discard() override {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    std::error_code ec;
    fs::remove(partial_, ec);
    fs::remove(LockOf(partial_), ec);
  }

 private:
  LocalBlobStore* store_;
  std::string sha_;
  int64_t size_;
  fs::path partial_;
  int fd_;
  int lock_fd_;
  int64_t written_;
  std::unique_ptr<Sha256> hash_;
};

absl::StatusOr<std::unique_ptr<LocalBlobStore>> LocalBlobStore::Open(const fs::path& root,
                                                                     bool fsync) {
  std::error_code ec;
  fs::create_directories(root / "sha256", ec);
  if (!ec) fs::create_directories(root / "partial", ec);
  if (!ec) fs::create_directories(root / "locks", ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("creating blob store ", root.string(), ": ", ec.message()));
  }
  return std::unique_ptr<LocalBlobStore>(new LocalBlobStore(root, fsync));
}

fs::path LocalBlobStore::BlobPath(const std::string& sha) const {
  return root_ / "sha256" / sha.substr(0, 2) / sha;
}

fs::path LocalBlobStore::PartialPath(const std::string& sha, int64_t size) const {
  return root_ / "partial" / absl::StrCat(sha, "-", size);
}

bool LocalBlobStore::Has(const std::string& sha) const {
  std::error_code ec;
  return IsSha256Hex(sha) && fs::is_regular_file(BlobPath(sha), ec);
}

BlobStatus LocalBlobStore::Status(const std::string& sha, int64_t size) const {
  BlobStatus st;
  if (!IsSha256Hex(sha)) return st;
  std::error_code ec;
  auto full = fs::file_size(BlobPath(sha), ec);
  if (!ec) {
    st.complete = true;
    st.committed_size = static_cast<int64_t>(full);
    return st;
  }
  auto part = fs::file_size(PartialPath(sha, size), ec);
  if (!ec) st.committed_size = static_cast<int64_t>(part);
  return st;
}

absl::StatusOr<std::unique_ptr<BlobWriter>> LocalBlobStore::OpenWriter(const std::string& sha,
                                                                       int64_t size,
                                                                       int64_t offset) {
  if (!IsSha256Hex(sha)) {
    return absl::InvalidArgumentError("sha256 must be 64 lower-case hex characters");
  }
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (!writing_.insert(sha).second) {
      return absl::AbortedError(
          absl::StrCat("another upload of blob ", sha, " is in progress; retry later"));
    }
  }
  auto fail = [&](absl::Status s) -> absl::StatusOr<std::unique_ptr<BlobWriter>> {
    Release(sha);
    return s;
  };
  fs::path partial = PartialPath(sha, size);
  // Writers in other processes (replicas sharing this folder) are excluded by an flock on a
  // lock file beside the partial: released by the kernel when the writer's process dies, and
  // honoured across NFS clients (Linux maps flock to NFS byte-range locks).
  const fs::path lock_path = LockOf(partial);
  int lock_fd = ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (lock_fd < 0) {
    return fail(absl::InternalError(
        absl::StrCat("opening ", lock_path.string(), ": ", std::strerror(errno))));
  }
  if (::flock(lock_fd, LOCK_EX | LOCK_NB) != 0) {
    ::close(lock_fd);
    return fail(
        absl::AbortedError(absl::StrCat("another upload of blob ", sha,
                                        " is in progress (perhaps through another replica); "
                                        "retry later")));
  }
  auto fail_locked = [&](absl::Status s) {
    ::close(lock_fd);
    return fail(std::move(s));
  };
  std::error_code ec;
  int64_t held = 0;
  if (fs::exists(partial, ec)) held = static_cast<int64_t>(fs::file_size(partial, ec));
  if (offset != held) {
    return fail_locked(absl::FailedPreconditionError(
        absl::StrCat("upload of ", sha, " starts at byte ", offset, " but the server holds ", held,
                     " bytes; resume with write_offset=", held)));
  }
  int flags = O_WRONLY | O_CREAT | O_CLOEXEC | (offset == 0 ? O_TRUNC : O_APPEND);
  int fd = ::open(partial.c_str(), flags, 0644);
  if (fd < 0) return fail_locked(WriteError("opening", sha, errno));
  auto hash = std::make_unique<Sha256>();
  if (offset > 0) {
    absl::Status s = HashFilePrefix(partial, offset, *hash);
    if (!s.ok()) {
      ::close(fd);
      return fail_locked(s);
    }
  }
  // The writer releases the digest when destroyed.
  return std::unique_ptr<BlobWriter>(
      new LocalBlobWriter(this, sha, size, partial, fd, lock_fd, offset, std::move(hash)));
}

absl::StatusOr<fs::path> LocalBlobStore::LocalPath(const std::string& sha) const {
  if (!Has(sha)) return absl::NotFoundError(absl::StrCat("blob ", sha, " was not uploaded"));
  return BlobPath(sha);
}

void LocalBlobStore::Claim(const std::string& sha) {
  if (!IsSha256Hex(sha)) return;
  std::lock_guard<std::mutex> lock(sweep_mu_);
  ::utimensat(AT_FDCWD, BlobPath(sha).c_str(), nullptr, 0);
}

BlobSweepStats LocalBlobStore::Sweep(const BlobSweepPolicy& policy,
                                     const std::function<bool(const std::string&)>& in_use,
                                     const std::vector<std::string>* only) {
  BlobSweepStats stats;
  const auto now = fs::file_time_type::clock::now();
  auto idle_past = [&](const fs::path& p, std::chrono::seconds limit, uintmax_t* size) {
    std::error_code ec;
    const auto t = fs::last_write_time(p, ec);
    if (ec) return false;
    *size = fs::file_size(p, ec);
    return !ec && now - t >= limit;
  };
  auto sweep_blob = [&](const std::string& sha) {
    std::lock_guard<std::mutex> lock(sweep_mu_);
    const fs::path p = BlobPath(sha);
    uintmax_t size = 0;
    if (!idle_past(p, policy.grace, &size) || in_use(sha)) return;
    std::error_code ec;
    if (fs::remove(p, ec)) {
      ++stats.blobs_removed;
      stats.bytes_freed += static_cast<int64_t>(size);
    }
  };
  std::error_code ec;
  if (only != nullptr) {
    for (const auto& sha : *only)
      if (IsSha256Hex(sha)) sweep_blob(sha);
    return stats;
  }
  for (fs::recursive_directory_iterator it(root_ / "sha256", ec), end; !ec && it != end;
       it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (it->is_regular_file(ec) && IsSha256Hex(name)) sweep_blob(name);
  }
  for (fs::directory_iterator it(root_ / "partial", ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    const std::string sha = name.substr(0, name.find('-'));
    // Held across the check and the removal: an upload that resumes now either is seen here or
    // finds the partial gone (and is told to start at 0).
    std::lock_guard<std::mutex> lock(mu_);
    if (writing_.count(sha)) continue;  // an upload is appending to it now
    uintmax_t size = 0;
    if (!idle_past(it->path(), policy.partial_expiry, &size)) continue;
    // A writer in another process (a replica sharing this folder) holds the partial's flock.
    const std::string lock_path = LockOf(it->path()).string();
    const int lock_fd = ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (lock_fd < 0) continue;
    if (::flock(lock_fd, LOCK_EX | LOCK_NB) != 0) {
      ::close(lock_fd);
      continue;
    }
    std::error_code rec;
    if (fs::remove(it->path(), rec)) {
      ++stats.partials_removed;
      stats.bytes_freed += static_cast<int64_t>(size);
    }
    fs::remove(lock_path, rec);
    ::close(lock_fd);
  }
  return stats;
}

void LocalBlobStore::Release(const std::string& sha) {
  std::lock_guard<std::mutex> lock(mu_);
  writing_.erase(sha);
}

}  // namespace decima::server
