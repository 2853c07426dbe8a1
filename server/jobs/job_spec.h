// The one door from the API's decima.v1.JobSpec to the core's pipeline::JobSpec. CreateJob calls
// NormalizeJobSpec once and stores its result; the job child converts that stored message with
// JobSpecFromProto again and runs exactly what was stored (every field is explicit by then, so
// the second conversion applies no default).
//
// Defaults live here and nowhere else in the server (documented in proto/decima/v1/jobs.proto);
// ranges live in the core validators (pipeline::ValidateJobSpec calls ValidateSegmentOptions,
// ValidateSimplifyOptions, ParseView, the transfer-function parser), so the API accepts exactly
// what the pipeline can run.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "core/pipeline/pipeline.h"
#include "decima/v1/jobs.pb.h"

namespace decima::server {

// Parameters of `spec` with the documented defaults applied, validated. `input` and
// `label_map` stay empty: resolving "volumes/{id}" to files is the job runner's business.
// INVALID_ARGUMENT whose message starts with the field ("spec.target_reduction: ...") for a
// value out of range (NaN, ±inf, negative, too large), an unknown enum value, or a malformed
// volume name; `*field` (when given) receives that field name for the error detail.
absl::StatusOr<pipeline::JobSpec> JobSpecFromProto(const v1::JobSpec& spec,
                                                   std::string* field = nullptr);

// `spec` with every default written out (optional fields set, policy named, views listed), or
// the JobSpecFromProto error. What CreateJob stores and GetJob shows.
absl::StatusOr<v1::JobSpec> NormalizeJobSpec(const v1::JobSpec& spec, std::string* field = nullptr);

// A spec with levels_of, completed from `parent` (the job it names, which the caller may read):
// the parent's volume, regions and class means, the field policy. FAILED_PRECONDITION when the
// parent did not succeed or kept no level record (mesh.levels and labels.nii.gz);
// INVALID_ARGUMENT naming the field for a volume other than the parent's, a label map, regions
// or class means of its own, another policy, or a reduction outside the range the parent
// recorded (the message gives the range). NormalizeJobSpec checks the rest.
absl::StatusOr<v1::JobSpec> LevelJobSpec(const v1::JobSpec& spec, const v1::Job& parent,
                                         std::string* field = nullptr);

// pipeline enum <-> API enum.
v1::SimplifyPolicy PolicyToProto(SimplifyPolicy policy);

}  // namespace decima::server
