// SHA-256 over OpenSSL's libcrypto (already a dependency of gRPC): incremental, for data hashed
// as it arrives or as it is written (uploads in chunks, a checkpoint streamed to its file).
#pragma once

#include <cstddef>
#include <memory>
#include <string>

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

}  // namespace decima
