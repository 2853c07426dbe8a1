#include "server/jobs/job_memory.h"

#include <unistd.h>

#include <algorithm>
#include <span>

#include "absl/strings/str_cat.h"
#include "server/files/disk_space.h"
#include "server/jobs/job_spec.h"

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
// The other stages stay below these two (segment ~30, tetra ~40 bytes per voxel). Checked on
// ch2 (simplify 2 % below its measured 2034 MiB) and ch2better.
struct StageModel {
  int64_t base_bytes;
  double bytes_per_tet;       // per tet of the grid mesh
  double bytes_per_kept_tet;  // per tet of it the simplified mesh keeps, (1 - reduction) of them
  double bytes_per_window_voxel = 0;  // per voxel of one slab (slab_voxels layers), streamed
};
constexpr StageModel kInMemoryStages[] = {
    {int64_t{60} << 20, 58, 0},   // simplify
    {int64_t{100} << 20, 44, 0},  // render
};
// Simplified in slabs (core/simplify/stream.h), fitted to the whole-job peaks of `decima-bench
// --job-out DIR --stream-slab-voxels 16` (2026-11-29, after the refit's rows shrank and the write
// and render stages stopped holding what they do not read): the CT head 256x256x113 at 80 and
// 50 % (simplify 1127 and 1497 MiB, both exact here) and the 511x511x225 CT at 80 % (simplify
// 5999 MiB measured, 6508 estimated, +8.5 %). Per kept tet (35.5 B) from the 256 pair; per
// window voxel (450 B: one window's engine state and mesh, carried cells included) set so the
// 511 CT stays on the high side; per tet (9.5 B: the input's vertex arrays, the run's whole-grid
// arrays, image and labels) from the 256 head at 80 %. The render line is the earlier fit (256
// head, before the render stage shed ~20 %: 740 MiB at 80 % now, 3410 on the 511 CT): it
// overestimates that stage, which errs on the safe side.
constexpr StageModel kStreamedStages[] = {
    {int64_t{100} << 20, 9.5, 35.5, 450},  // simplify
    {int64_t{100} << 20, 5.5, 74.9, 0},    // render
};
constexpr int64_t kSaturated = int64_t{1} << 50;
constexpr int64_t kRuntimeBytes = int64_t{1} << 30;  // libraries, thread stacks, malloc arenas

}  // namespace

int64_t EstimateJobMemoryBytes(const v1::Volume& volume, int stream_slab_voxels,
                               double target_reduction) {
  int64_t voxels = 0;
  if (volume.dims_size() == 3) {
    voxels = 1;
    for (int64_t d : volume.dims()) {
      if (d <= 0) return kInMemoryStages[0].base_bytes;
      // Saturate instead of overflowing: such a volume is refused anyway.
      voxels = voxels > kSaturated / d ? kSaturated : voxels * d;
    }
  } else {
    voxels = std::max<int64_t>(volume.size_bytes(), 0) / 2;
  }
  if (voxels >= kSaturated / 5) return kSaturated;
  // Tets of the 5-tet decomposition of the voxel grid: 5 per cube between voxel centres (about 5
  // per voxel for DICOM before parsing), and the voxels of one slab of cube layers.
  double tets = 5.0 * double(voxels), window_voxels = 0;
  int64_t cube_layers = 0;
  if (volume.dims_size() == 3) {
    double cubes = 1;
    for (int64_t d : volume.dims()) cubes *= double(std::max<int64_t>(d - 1, 1));
    tets = 5 * cubes;
    cube_layers = std::max<int64_t>(volume.dims(2) - 1, 1);
    window_voxels = double(volume.dims(0)) * double(volume.dims(1)) *
                    double(std::min<int64_t>(stream_slab_voxels, cube_layers));
  } else {
    // Shape unknown: slices of 512x512 voxels (a CT's).
    window_voxels = 512.0 * 512.0 * stream_slab_voxels;
  }
  // A slab holding every cube layer is the in-memory run (SimplifyStreamed calls Simplify).
  const bool streamed =
      stream_slab_voxels > 0 && (cube_layers == 0 || stream_slab_voxels < cube_layers);
  const double kept = 1 - std::clamp(target_reduction, 0.0, 1.0);
  double peak = 0;
  for (const StageModel& s : streamed ? std::span<const StageModel>(kStreamedStages)
                                      : std::span<const StageModel>(kInMemoryStages)) {
    peak = std::max(peak, double(s.base_bytes) +
                              tets * (s.bytes_per_tet + kept * s.bytes_per_kept_tet) +
                              window_voxels * s.bytes_per_window_voxel);
  }
  return peak >= double(kSaturated) ? kSaturated : int64_t(peak);
}

JobMemoryPlan PlanJobMemory(const v1::Volume& volume, const v1::JobSpec& spec, int64_t cap) {
  JobMemoryPlan plan;
  v1::JobSpec named = spec;
  // CheckJobMemory asks before the volume exists; any well-formed name stands for it.
  if (named.volume().empty()) named.set_volume("volumes/pending");
  named.clear_stream_slab_voxels();
  const absl::StatusOr<pipeline::JobSpec> parsed = JobSpecFromProto(named);
  const double reduction =
      parsed.ok() ? parsed->target_reduction : pipeline::JobSpec{}.target_reduction;
  plan.streaming_refusal =
      parsed.ok() ? pipeline::StreamingRefusal(*parsed) : std::string(parsed.status().message());
  plan.streamed_estimate_bytes = EstimateJobMemoryBytes(volume, kServerStreamSlabVoxels, reduction);
  auto records = [&] {
    int64_t voxels = volume.dims_size() == 3 ? 1 : 0;
    for (int64_t d : volume.dims()) voxels *= d;
    return plan.stream_slab_voxels > 0 ? pipeline::StreamRecordBytes(voxels, reduction) : 0;
  };
  if (spec.has_stream_slab_voxels()) {
    plan.stream_slab_voxels = spec.stream_slab_voxels();
    plan.estimate_bytes = EstimateJobMemoryBytes(volume, plan.stream_slab_voxels, reduction);
    plan.stream_record_bytes = records();
    return plan;
  }
  plan.estimate_bytes = EstimateJobMemoryBytes(volume, 0, reduction);
  if (cap <= 0 || plan.estimate_bytes <= cap || !plan.streaming_refusal.empty() ||
      plan.streamed_estimate_bytes >= plan.estimate_bytes) {
    return plan;
  }
  plan.stream_slab_voxels = kServerStreamSlabVoxels;
  plan.estimate_bytes = plan.streamed_estimate_bytes;
  plan.stream_record_bytes = records();
  return plan;
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

absl::Status CheckJobMemory(const v1::Volume& volume, const std::string& volume_name, int64_t cap,
                            const JobMemoryPlan& plan) {
  if (plan.estimate_bytes <= cap) return absl::OkStatus();
  std::string dims;
  for (int64_t d : volume.dims()) absl::StrAppend(&dims, dims.empty() ? "" : "x", d);
  std::string how =
      plan.stream_slab_voxels > 0
          ? absl::StrCat(" simplified in slabs of ", plan.stream_slab_voxels, " voxel layers")
          : "";
  // What streaming would change, when it would make the job fit.
  std::string instead;
  if (plan.stream_slab_voxels == 0 && plan.streamed_estimate_bytes <= cap) {
    instead = plan.streaming_refusal.empty()
                  ? absl::StrCat("; simplified in slabs (stream_slab_voxels ",
                                 kServerStreamSlabVoxels, ", or left unset) it would need about ",
                                 HumanBytes(plan.streamed_estimate_bytes))
                  : absl::StrCat("; in slabs it would need about ",
                                 HumanBytes(plan.streamed_estimate_bytes), ", but ",
                                 plan.streaming_refusal);
  }
  return absl::ResourceExhaustedError(
      absl::StrCat(volume_name, " (", dims.empty() ? HumanBytes(volume.size_bytes()) : dims,
                   dims.empty() ? "" : " voxels", ") needs about ", HumanBytes(plan.estimate_bytes),
                   " of memory", how, ", more than the job limit of ", HumanBytes(cap),
                   " (decima-server --worker-memory-mb)", instead, "; nothing was run"));
}

absl::Status CheckJobFits(const v1::Volume& volume, const std::string& volume_name,
                          const v1::JobSpec& spec, int64_t cap, const std::string& field,
                          v1::ErrorDetail* detail, JobMemoryPlan* plan) {
  *plan = PlanJobMemory(volume, spec, cap);
  if (cap <= 0) return absl::OkStatus();
  absl::Status fits = CheckJobMemory(volume, volume_name, cap, *plan);
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
