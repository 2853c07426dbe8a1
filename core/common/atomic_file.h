// The write-then-rename file every writer of the core uses (volumes, meshes, surfaces, level
// records), so a failed or interrupted write never leaves a half file under the real name.
#pragma once

#include <cstdio>
#include <filesystem>
#include <string_view>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace decima {

// The errno `err` as a Status naming `path` and what failed ("path: what: strerror").
absl::Status IoError(int err, absl::string_view what, const std::filesystem::path& path);

// A file written under a hidden temporary name in the destination folder and renamed over
// `path` by Commit(); destroyed without Commit() it removes the temporary file.
class AtomicFile {
 public:
  AtomicFile() = default;
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;
  ~AtomicFile();

  absl::Status Open(const std::filesystem::path& path);
  absl::Status Write(const void* data, size_t bytes);
  absl::Status Write(std::string_view s) { return Write(s.data(), s.size()); }
  absl::Status Commit();

 private:
  std::filesystem::path path_, tmp_;
  std::FILE* file_ = nullptr;
  bool committed_ = false;
};

}  // namespace decima
