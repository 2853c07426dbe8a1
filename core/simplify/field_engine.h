// The engine behind SimplifyPolicy::kField: greedy half-edge collapses ranked by the error of
// the piecewise-linear field (4-D quadrics, Garland & Zhou 2005 "Quadric-based simplification
// in any dimension", specialised to a scalar field over a fixed-position tetrahedral mesh).
// Internal to core/simplify; simplify.h states the guarantees, README.md the design.
#pragma once

#include <cstdint>

#include "absl/status/status.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima::simplify_internal {

// Runs the field policy on `mesh` (already validated) until `target` cells are removed, the
// error tolerance stops it (`tolerance` > 0: an RMS field error in image units) or no valid
// collapse is left. Fills every field of `result`. Cancelled if `cancel` fires.
absl::Status RunFieldSimplify(const TetMesh& mesh, const SimplifyOptions& options, int threads,
                              int64_t target, double tolerance, const ProgressFn& progress,
                              const CancelToken* cancel, SimplifyResult* result);

}  // namespace decima::simplify_internal
