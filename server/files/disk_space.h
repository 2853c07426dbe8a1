// Free space of the data dir's filesystem, and a reserve that keeps deletes working when it is
// full. Uploads are admitted only while the bytes they declare fit (RESOURCE_EXHAUSTED naming
// free and needed bytes otherwise). The reserve is a preallocated file (data_dir/reserve): when
// something else filled the disk anyway (job outputs, another program), a delete releases it
// first so that SQLite has room for its journal and the delete can free space; it is allocated
// again once the disk has room.
// Thread-safety: every method may be called from any thread.
#pragma once

#include <cstdint>
#include <filesystem>
#include <mutex>
#include <string>

#include "absl/status/status.h"

namespace decima::server {

class DiskSpace {
 public:
  // `reserve_bytes` 0 disables the reserve file.
  DiskSpace(std::filesystem::path root, int64_t reserve_bytes);

  // Bytes available to this process on the data dir's filesystem (statvfs f_bavail), or -1.
  int64_t Free() const;
  // OK when `bytes` more fit on the filesystem; RESOURCE_EXHAUSTED "<what> needs N bytes, M are
  // free" otherwise.
  absl::Status Admit(int64_t bytes, const std::string& what) const;
  // Before a delete: drops the reserve file when the disk is nearly full.
  void BeforeDelete();
  // Allocates the reserve file if it is missing and the disk has room for it twice (called at
  // start and by the blob collector's timer). Returns whether the reserve is in place.
  bool Refill();

  std::filesystem::path reserve_file() const { return root_ / "reserve"; }
  int64_t reserve_bytes() const { return reserve_bytes_; }

 private:
  const std::filesystem::path root_;
  const int64_t reserve_bytes_;
  std::mutex mu_;
};

// "1.5 GB", "20 MB", "512 bytes": sizes in messages meant for people.
std::string HumanBytes(int64_t bytes);

}  // namespace decima::server
