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
#include "decima/v1/volumes.pb.h"

namespace decima::server {

// Estimated peak resident bytes of a job on `volume`: the largest over the stages (simplify,
// render) of a fixed part plus a cost per tet of the 5-tet grid mesh, fitted to measured stage
// peaks (figures in core/pipeline/README.md). The voxel count comes from the parsed dims or,
// when the server defers parsing (DICOM), from the files' size at two bytes per voxel.
int64_t EstimateJobMemoryBytes(const v1::Volume& volume);

// The default cap of one job: 80 % of the machine's physical memory.
int64_t DefaultJobMemoryCapBytes();

// The cap of one job: `worker_memory_mb` (decima-server --worker-memory-mb) when above 0, else
// the default.
int64_t JobMemoryCapBytes(int64_t worker_memory_mb);

// OK when a job on `volume` (called `volume_name` in the message) fits under `cap`; otherwise
// ResourceExhausted naming the volume's size, the estimate, the limit and the flag that raises
// it. Checked when a job is submitted and again by the runner (another replica's limit may be
// lower than the one that took the job).
absl::Status CheckJobMemory(const v1::Volume& volume, const std::string& volume_name, int64_t cap);

// The one submit-time decision, shared by CreateJob (on the stored volume) and CheckJobMemory
// (on the dims a client read from a file's header before uploading it): CheckJobMemory under
// `cap`, and on refusal `detail` names `field` and the limit (worker_memory_mb, in MiB). A cap of
// 0 or less admits every job. `needed` (may be null) receives the estimate.
absl::Status CheckJobFits(const v1::Volume& volume, const std::string& volume_name, int64_t cap,
                          const std::string& field, v1::ErrorDetail* detail,
                          int64_t* needed = nullptr);

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
