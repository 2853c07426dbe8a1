// Internal to core/mesh: the write-then-rename file every mesh and surface writer uses, so a
// failed write leaves no half file behind.
#pragma once

#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string_view>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"

namespace decima::mesh_detail {

// The errno `err` as a Status naming `path` and what failed.
inline absl::Status IoError(int err, absl::string_view what, const std::filesystem::path& path) {
  return absl::Status(absl::ErrnoToStatusCode(err),
                      absl::StrCat(path.string(), ": ", what, ": ", std::strerror(err)));
}

// A file written under a temporary name and renamed over `path` by Commit(); destroyed without
// Commit() it removes the temporary file.
class AtomicFile {
 public:
  AtomicFile() = default;
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;
  ~AtomicFile() {
    if (file_ != nullptr) std::fclose(file_);
    if (!committed_ && !tmp_.empty()) {
      std::error_code ec;
      std::filesystem::remove(tmp_, ec);
    }
  }

  absl::Status Open(const std::filesystem::path& path) {
    static std::atomic<uint64_t> counter{0};
    path_ = path;
    tmp_ = path;
    tmp_ += absl::StrCat(".tmp-", ::getpid(), "-", counter.fetch_add(1));
    file_ = std::fopen(tmp_.c_str(), "wb");
    if (file_ == nullptr) {
      const int err = errno;
      tmp_.clear();
      return IoError(err, "cannot create file", path_);
    }
    return absl::OkStatus();
  }

  absl::Status Write(const void* data, size_t bytes) {
    if (bytes == 0) return absl::OkStatus();
    if (std::fwrite(data, 1, bytes, file_) != bytes) return IoError(errno, "write failed", path_);
    return absl::OkStatus();
  }
  absl::Status Write(std::string_view s) { return Write(s.data(), s.size()); }

  absl::Status Commit() {
    FILE* f = file_;
    file_ = nullptr;
    if (std::fflush(f) != 0) {
      const int err = errno;
      std::fclose(f);
      return IoError(err, "write failed", path_);
    }
    if (std::fclose(f) != 0) return IoError(errno, "close failed", path_);
    if (std::rename(tmp_.c_str(), path_.c_str()) != 0)
      return IoError(errno, "rename failed", path_);
    committed_ = true;
    return absl::OkStatus();
  }

 private:
  std::filesystem::path path_, tmp_;
  FILE* file_ = nullptr;
  bool committed_ = false;
};

}  // namespace decima::mesh_detail
