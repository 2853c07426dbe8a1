// SHA-256 over OpenSSL's libcrypto (already a dependency of gRPC): incremental hashing for
// uploads that arrive in chunks and resume from a prefix already on disk.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace decima::server {

class Sha256 {
 public:
  Sha256();
  ~Sha256();
  Sha256(const Sha256&) = delete;
  Sha256& operator=(const Sha256&) = delete;

  void Update(const void* data, size_t size);
  // Lower-case hex digest of everything passed to Update(); the object is spent afterwards.
  std::string HexDigest();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Feeds the first `limit` bytes of `path` (all when limit < 0) into `hash`.
absl::Status HashFilePrefix(const std::filesystem::path& path, int64_t limit, Sha256& hash);

// Hex sha256 of a whole file.
absl::StatusOr<std::string> Sha256OfFile(const std::filesystem::path& path);

// True for 64 lower-case hex characters.
bool IsSha256Hex(absl::string_view s);

}  // namespace decima::server
