#include "core/common/atomic_file.h"

#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdint>
#include <cstring>

#include "absl/strings/str_cat.h"

namespace decima {

absl::Status IoError(int err, absl::string_view what, const std::filesystem::path& path) {
  return absl::Status(absl::ErrnoToStatusCode(err),
                      absl::StrCat(path.string(), ": ", what, ": ", std::strerror(err)));
}

AtomicFile::~AtomicFile() {
  if (file_ != nullptr) std::fclose(file_);
  if (!committed_ && !tmp_.empty()) {
    std::error_code ec;
    std::filesystem::remove(tmp_, ec);
  }
}

absl::Status AtomicFile::Open(const std::filesystem::path& path) {
  static std::atomic<uint64_t> counter{0};
  path_ = path;
  // Hidden, in the destination folder (so the rename stays on one file system).
  const std::filesystem::path dir =
      path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  tmp_ = dir / absl::StrCat(".", path.filename().string(), ".tmp-", ::getpid(), "-",
                            counter.fetch_add(1));
  file_ = std::fopen(tmp_.c_str(), "wb");
  if (file_ == nullptr) {
    const int err = errno;
    tmp_.clear();
    return IoError(err, "cannot create file", path_);
  }
  return absl::OkStatus();
}

absl::Status AtomicFile::Write(const void* data, size_t bytes) {
  if (bytes == 0) return absl::OkStatus();
  if (std::fwrite(data, 1, bytes, file_) != bytes) return IoError(errno, "write failed", path_);
  return absl::OkStatus();
}

absl::Status AtomicFile::Commit() {
  std::FILE* f = file_;
  file_ = nullptr;
  if (std::fflush(f) != 0) {
    const int err = errno;
    std::fclose(f);
    return IoError(err, "write failed", path_);
  }
  if (std::fclose(f) != 0) return IoError(errno, "close failed", path_);
  if (std::rename(tmp_.c_str(), path_.c_str()) != 0) return IoError(errno, "rename failed", path_);
  committed_ = true;
  return absl::OkStatus();
}

}  // namespace decima
