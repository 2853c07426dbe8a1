// Linked instead of core/pipeline when this build has no decima_pipeline target: every job
// then fails with a clear reason, and the rest of the service works.
#include "core/pipeline/pipeline.h"

namespace decima::pipeline {

absl::StatusOr<JobResult> RunJob(const JobSpec&, const std::filesystem::path&, const ProgressFn&,
                                 const CancelToken*) {
  return absl::UnimplementedError("this decima-server was built without core/pipeline");
}

}  // namespace decima::pipeline
