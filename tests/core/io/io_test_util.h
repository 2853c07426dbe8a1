// Helpers for the core/io tests: tiny volumes with non-trivial geometry, raw file access, and
// hand-built NIfTI headers so broken files can be produced byte by byte.
#pragma once

#include <sys/resource.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/volume/volume.h"

namespace decima::io::testing {

// A dims volume of `type` whose voxel v holds a distinct pattern value (within the type's range),
// spacing (0.5, 1.25, 3), origin (-12.5, 40.25, 7), direction a rotation about an oblique axis.
// `left_handed` negates the third direction column.
Volume PatternVolume(std::array<int64_t, 3> dims, VoxelType type, bool left_handed = false);

// Asserts `s` is an error whose message names the file `p` and contains `what`.
void ExpectError(const absl::Status& s, const std::filesystem::path& p, const std::string& what);

std::vector<uint8_t> ReadAll(const std::filesystem::path& path);
void WriteAll(const std::filesystem::path& path, const std::vector<uint8_t>& bytes);
void WriteText(const std::filesystem::path& path, const std::string& text);

// gzip (gzip=true) or zlib stream of `bytes`.
std::vector<uint8_t> Compress(const std::vector<uint8_t>& bytes, bool gzip);

// Flips every bit of `count` bytes around the middle of the file region [begin, end).
void CorruptMiddle(std::vector<uint8_t>& bytes, size_t begin, size_t count = 16);

// While alive, the process may map at most `headroom` bytes more than it maps now (RLIMIT_AS),
// so a reader that allocates what a hostile header declares fails (std::bad_alloc, or an error
// that is not the refusal the test expects) instead of merely taking long: the tests of such
// headers assert the refusal without timing it. The previous limit is restored on destruction.
class AddressSpaceCap {
 public:
  explicit AddressSpaceCap(uint64_t headroom) {
    ::getrlimit(RLIMIT_AS, &saved_);
    uint64_t pages = 0;
    std::ifstream("/proc/self/statm") >> pages;  // first field: the mapped size, in pages
    rlimit cap = saved_;
    cap.rlim_cur = pages * static_cast<uint64_t>(::sysconf(_SC_PAGESIZE)) + headroom;
    if (saved_.rlim_max != RLIM_INFINITY && cap.rlim_cur > saved_.rlim_max) {
      cap.rlim_cur = saved_.rlim_max;
    }
    active_ = pages > 0 && ::setrlimit(RLIMIT_AS, &cap) == 0;
  }
  ~AddressSpaceCap() {
    if (active_) ::setrlimit(RLIMIT_AS, &saved_);
  }
  AddressSpaceCap(const AddressSpaceCap&) = delete;
  AddressSpaceCap& operator=(const AddressSpaceCap&) = delete;
  // Whether the cap is in force (a test that relies on it asserts this).
  bool active() const { return active_; }

 private:
  rlimit saved_{};
  bool active_ = false;
};

template <typename T>
void Poke(std::vector<uint8_t>& bytes, size_t offset, T value) {
  std::memcpy(bytes.data() + offset, &value, sizeof(T));
}
template <typename T>
T Peek(const std::vector<uint8_t>& bytes, size_t offset) {
  T v;
  std::memcpy(&v, bytes.data() + offset, sizeof(T));
  return v;
}

}  // namespace decima::io::testing
