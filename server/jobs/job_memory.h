// How much memory a job may take. A job's peak is about proportional to its voxel count (the
// level set, the tetrahedral mesh and the simplifier's quadrics all scale with it), so the
// runner estimates it from the volume's declared size before anything is decoded: a job whose
// estimate exceeds the cap fails at once with "needs N, limit M" instead of meeting the OOM
// killer, and every other job runs under an address-space limit sized from its estimate.
// Figures behind the constants are in core/pipeline/README.md ("Memory").
#pragma once

#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "decima/v1/errors.pb.h"
#include "decima/v1/jobs.pb.h"
#include "decima/v1/volumes.pb.h"

namespace decima::server {

// The slab depth of a job the server chooses to simplify in slabs (its spec leaves
// stream_slab_voxels unset and the job does not fit in memory): at 16 voxel layers the CT heads
// and the 511x511x225 CT measured 0.2 to 1.7 % below the in-memory PSNR, at 8 up to 4 % below
// for little less memory (core/simplify/README.md "Streamed simplification").
inline constexpr int kServerStreamSlabVoxels = 16;

// Estimated peak resident bytes of a job on `volume`, simplified in memory (stream_slab_voxels
// 0) or in slabs, at target_reduction: the largest over the stages of a fixed part plus a cost
// per tet of the 5-tet grid mesh (and, for the stages after simplify, per tet it keeps), fitted
// to measured stage peaks (figures in core/pipeline/README.md "Memory"). The voxel count comes
// from the parsed dims or, when the server defers parsing (DICOM), from the files' size at two
// bytes per voxel.
int64_t EstimateJobMemoryBytes(const v1::Volume& volume, int stream_slab_voxels = 0,
                               double target_reduction = 0.5);

// How a job runs as far as memory goes, and what that is estimated to need.
struct JobMemoryPlan {
  int stream_slab_voxels = 0;  // 0: in memory
  int64_t estimate_bytes = 0;
  // Why the job cannot be simplified in slabs (pipeline::StreamingRefusal), "" when it can.
  std::string streaming_refusal;
  int64_t streamed_estimate_bytes = 0;  // the estimate in slabs of kServerStreamSlabVoxels
  // In slabs: the disk its slab records and simplify checkpoint take at most on the data dir
  // (pipeline::StreamRecordBytes), which CreateJob admits like an upload; 0 in memory.
  int64_t stream_record_bytes = 0;
};

// The plan for a job with `spec` (as CreateJob receives or stores it; its volume may be empty)
// on `volume` under `cap`: the spec's stream_slab_voxels when set; unset, in memory when that
// fits (or cap <= 0 admits everything), else in slabs of kServerStreamSlabVoxels when the spec
// can be streamed and that needs less. A spec the pipeline would refuse is planned in memory
// (CreateJob names its field).
JobMemoryPlan PlanJobMemory(const v1::Volume& volume, const v1::JobSpec& spec, int64_t cap);

// The default cap of one job: 80 % of the machine's physical memory.
int64_t DefaultJobMemoryCapBytes();

// The cap of one job: `worker_memory_mb` (decima-server --worker-memory-mb) when above 0, else
// the default.
int64_t JobMemoryCapBytes(int64_t worker_memory_mb);

// OK when a job on `volume` (called `volume_name` in the message) planned as `plan` fits under
// `cap`; otherwise ResourceExhausted naming the volume's size, the estimate (in memory or in
// slabs), the limit and the flag that raises it, and what simplifying in slabs would change.
// Checked when a job is submitted and again by the runner (another replica's limit may be
// lower than the one that took the job).
absl::Status CheckJobMemory(const v1::Volume& volume, const std::string& volume_name, int64_t cap,
                            const JobMemoryPlan& plan);

// The one submit-time decision, shared by CreateJob (on the stored volume) and CheckJobMemory
// (on the dims a client read from a file's header before uploading it): PlanJobMemory and
// CheckJobMemory under `cap`, and on refusal `detail` names `field` and the limit
// (worker_memory_mb, in MiB). A cap of 0 or less admits every job. `plan` receives the plan.
absl::Status CheckJobFits(const v1::Volume& volume, const std::string& volume_name,
                          const v1::JobSpec& spec, int64_t cap, const std::string& field,
                          v1::ErrorDetail* detail, JobMemoryPlan* plan);

// The largest count along one axis and in all a client may declare before uploading: above
// what core/io accepts (kMaxVoxels, 2^31 in all), so every file the server would take passes,
// and low enough that the estimate cannot overflow.
inline constexpr int64_t kMaxVolumeDim = int64_t{1} << 31;
inline constexpr int64_t kMaxVolumeVoxels = int64_t{1} << 40;

// Dims a client declares (CheckJobMemory): exactly three, each in [1, kMaxVolumeDim], product
// at most kMaxVolumeVoxels, and size_bytes >= 0. On error InvalidArgument whose message starts
// with the field, and `field` set to it ("dims" or "size_bytes").
absl::Status ValidateVolumeSize(const google::protobuf::RepeatedField<int64_t>& dims,
                                int64_t size_bytes, std::string* field);

// The address-space limit for a job with estimate `needed` under `cap`: room for twice the
// estimate plus the runtime's fixed mappings, never above the cap.
int64_t JobAddressSpaceLimitBytes(int64_t needed, int64_t cap);

}  // namespace decima::server
