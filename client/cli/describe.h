// `decima status` as kubectl describe, and the summary at the end of a watch.
#pragma once

#include "client/cli/context.h"

namespace decima::client {

// The job's state, input, spec, times and, when it succeeded, its result and artifacts.
void DescribeJob(CliContext& ctx, const v1::Job& j);
// The end of a watch: achieved reduction, sizes, bytes ratio, and the warning. Returns
// kTargetNotReached when the target was missed, kOk otherwise.
int PrintSummary(CliContext& ctx, const v1::Job& job);

}  // namespace decima::client
