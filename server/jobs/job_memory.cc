#include "server/jobs/job_memory.h"

#include <unistd.h>

#include <algorithm>

namespace decima::server {
namespace {

constexpr int64_t kBaseBytes = int64_t{256} << 20;
constexpr int64_t kBytesPerVoxel = 512;
constexpr int64_t kRuntimeBytes = int64_t{1} << 30;  // libraries, thread stacks, malloc arenas

}  // namespace

int64_t EstimateJobMemoryBytes(const v1::Volume& volume) {
  int64_t voxels = 0;
  if (volume.dims_size() == 3) {
    voxels = 1;
    for (int64_t d : volume.dims()) {
      if (d <= 0) return kBaseBytes;
      // Saturate instead of overflowing: such a volume is refused anyway.
      voxels = voxels > (int64_t{1} << 50) / d ? (int64_t{1} << 50) : voxels * d;
    }
  } else {
    voxels = std::max<int64_t>(volume.size_bytes(), 0) / 2;
  }
  const int64_t per_voxel = std::min(voxels, (int64_t{1} << 50) / kBytesPerVoxel) * kBytesPerVoxel;
  return kBaseBytes + per_voxel;
}

int64_t DefaultJobMemoryCapBytes() {
  const long pages = ::sysconf(_SC_PHYS_PAGES);
  const long page = ::sysconf(_SC_PAGESIZE);
  if (pages <= 0 || page <= 0) return int64_t{8} << 30;
  return static_cast<int64_t>(pages) * page / 10 * 8;
}

int64_t JobAddressSpaceLimitBytes(int64_t needed, int64_t cap) {
  return std::min(cap, 2 * needed + kRuntimeBytes);
}

}  // namespace decima::server
