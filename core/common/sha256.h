// SHA-256 over OpenSSL's libcrypto (already a dependency of gRPC): incremental, for data hashed
// as it arrives or as it is written (uploads in chunks, a checkpoint streamed to its file).
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>

#include "absl/status/status.h"

namespace decima {

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

// Feeds the first `limit` bytes of `path` (all when limit < 0) into `hash`; `hashed`, when given,
// gets the number of bytes fed. NotFound when the file cannot be opened, DataLoss on a read error
// or when the file is shorter than `limit`; both name the file.
absl::Status HashFilePrefix(const std::filesystem::path& path, int64_t limit, Sha256& hash,
                            int64_t* hashed = nullptr);

}  // namespace decima
