// A simplification's outcome as JSON: the one spelling of the "simplification" section shared by
// a job's metrics.json and decima-bench (as fidelity_json.h is for the fidelity metrics).
#pragma once

#include <cstdint>

#include <nlohmann/json.hpp>

#include "core/simplify/simplify.h"

namespace decima {

// The object {policy, target_reduction, achieved_reduction, reached_target, stop_reason,
// stop_message, passes, cells_before, cells_after, vertices_before, vertices_after}, in that
// order. `options` are the ones `result` was simplified with (its policy and target);
// `vertices_before` is the input mesh's vertex count, which the result does not keep.
nlohmann::ordered_json SimplifyResultToJson(const SimplifyResult& result,
                                            const SimplifyOptions& options,
                                            int64_t vertices_before);

}  // namespace decima
