#include "server/jobs/job_memory.h"

#include <unistd.h>

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "server/files/disk_space.h"

namespace decima::server {
namespace {

// The job's peak is the largest of its stages' peaks (core/pipeline/README.md, "Memory"), each a
// fixed part plus a cost per tet of the original 5-tet grid mesh, fitted to the stage peaks that
// `decima-bench --job-out` measured on the CT head at 128x128x53 and 256x256x113 (50 %, field):
// simplify holds the original mesh's per-vertex arrays and the engine's arrays (the original's
// cells, 17 bytes per tet, are dropped while it runs and computed from the grid: issue 30; the
// line was 32 MiB + 73 B/tet before), render measures the fidelity against the original mesh and
// then renders the original straight from the voxel grid (RenderableGrid, 16 bytes per voxel, the
// original mesh freed first; issue 30): 100 MiB + 44 B/tet, fitted to its measured peaks on the
// two CT heads (273.5 and 1607 MiB; 128x128x113: 496.5 measured, 479 estimated). It was
// 144 MiB + 67 B/tet with the materialized renderable mesh, then the job's peak; simplify is now.
// The other stages stay below these two (segment ~30, tetra ~120 bytes per voxel). Checked on
// ch2 (simplify 2 % below its measured 2034 MiB) and ch2better.
struct StageModel {
  int64_t base_bytes;
  int64_t bytes_per_tet;
};
constexpr StageModel kStages[] = {
    {int64_t{60} << 20, 58},   // simplify
    {int64_t{100} << 20, 44},  // render
};
constexpr int64_t kSaturated = int64_t{1} << 50;
constexpr int64_t kRuntimeBytes = int64_t{1} << 30;  // libraries, thread stacks, malloc arenas

// Tets of the 5-tet decomposition of the voxel grid: 5 per cube between voxel centres.
int64_t GridTets(const v1::Volume& volume, int64_t voxels) {
  if (volume.dims_size() != 3) return 5 * voxels;  // DICOM before parsing: about 5 per voxel
  int64_t cubes = 1;
  for (int64_t d : volume.dims()) cubes *= std::max<int64_t>(d - 1, 1);
  return 5 * cubes;
}

}  // namespace

int64_t EstimateJobMemoryBytes(const v1::Volume& volume) {
  int64_t voxels = 0;
  if (volume.dims_size() == 3) {
    voxels = 1;
    for (int64_t d : volume.dims()) {
      if (d <= 0) return kStages[0].base_bytes;
      // Saturate instead of overflowing: such a volume is refused anyway.
      voxels = voxels > kSaturated / d ? kSaturated : voxels * d;
    }
  } else {
    voxels = std::max<int64_t>(volume.size_bytes(), 0) / 2;
  }
  if (voxels >= kSaturated / 5) return kSaturated;
  const int64_t tets = GridTets(volume, voxels);
  int64_t peak = 0;
  for (const StageModel& s : kStages) {
    const int64_t stage = tets >= (kSaturated - s.base_bytes) / s.bytes_per_tet
                              ? kSaturated
                              : s.base_bytes + tets * s.bytes_per_tet;
    peak = std::max(peak, stage);
  }
  return peak;
}

int64_t DefaultJobMemoryCapBytes() {
  const long pages = ::sysconf(_SC_PHYS_PAGES);
  const long page = ::sysconf(_SC_PAGESIZE);
  if (pages <= 0 || page <= 0) return int64_t{8} << 30;
  return static_cast<int64_t>(pages) * page / 10 * 8;
}

int64_t JobMemoryCapBytes(int64_t worker_memory_mb) {
  return worker_memory_mb > 0 ? worker_memory_mb << 20 : DefaultJobMemoryCapBytes();
}

absl::Status CheckJobMemory(const v1::Volume& volume, const std::string& volume_name, int64_t cap) {
  const int64_t needed = EstimateJobMemoryBytes(volume);
  if (needed <= cap) return absl::OkStatus();
  std::string dims;
  for (int64_t d : volume.dims()) absl::StrAppend(&dims, dims.empty() ? "" : "x", d);
  return absl::ResourceExhaustedError(
      absl::StrCat(volume_name, " (", dims.empty() ? HumanBytes(volume.size_bytes()) : dims,
                   dims.empty() ? "" : " voxels", ") needs about ", HumanBytes(needed),
                   " of memory, more than the job limit of ", HumanBytes(cap),
                   " (decima-server --worker-memory-mb); nothing was run"));
}

absl::Status CheckJobFits(const v1::Volume& volume, const std::string& volume_name, int64_t cap,
                          const std::string& field, v1::ErrorDetail* detail, int64_t* needed) {
  if (needed) *needed = EstimateJobMemoryBytes(volume);
  if (cap <= 0) return absl::OkStatus();
  absl::Status fits = CheckJobMemory(volume, volume_name, cap);
  if (!fits.ok()) {
    detail->set_field(field);
    detail->set_limit("worker_memory_mb");
    detail->set_limit_value(cap >> 20);
  }
  return fits;
}

absl::Status ValidateVolumeSize(const google::protobuf::RepeatedField<int64_t>& dims,
                                int64_t size_bytes, std::string* field) {
  *field = "dims";
  if (dims.size() != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("dims: expected 3 counts (x, y, z), got ", dims.size()));
  }
  constexpr const char* kAxes[] = {"x", "y", "z"};
  int64_t voxels = 1;
  for (int i = 0; i < 3; ++i) {
    const int64_t d = dims[i];
    if (d < 1 || d > kMaxVolumeDim) {
      return absl::InvalidArgumentError(
          absl::StrCat("dims: ", kAxes[i], " is ", d, ", expected 1 to ", kMaxVolumeDim));
    }
    // Compared before multiplying, so the product never overflows.
    if (voxels > kMaxVolumeVoxels / d) {
      return absl::InvalidArgumentError(absl::StrCat("dims: ", dims[0], "x", dims[1], "x", dims[2],
                                                     " is more than ", kMaxVolumeVoxels,
                                                     " voxels"));
    }
    voxels *= d;
  }
  if (size_bytes < 0) {
    *field = "size_bytes";
    return absl::InvalidArgumentError(absl::StrCat("size_bytes: ", size_bytes, " is negative"));
  }
  field->clear();
  return absl::OkStatus();
}

int64_t JobAddressSpaceLimitBytes(int64_t needed, int64_t cap) {
  return std::min(cap, 2 * needed + kRuntimeBytes);
}

}  // namespace decima::server
