// Least-squares refit of a simplified mesh's vertex values to the original samples.
// Internal to core/simplify (used by the field policy); README.md "Refit" says why.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"

namespace decima::simplify_internal {

struct RefitStats {
  int64_t samples = 0;    // original vertices located in the simplified mesh
  int64_t unlocated = 0;  // outside every cell (left out of the fit)
  int64_t walked = 0;     // not in the cells of the vertex it became: found by a walk from there
  int64_t searched = 0;   // not placed through vertex_map: went through the whole-mesh search
  double rms_before = 0;  // RMS deviation at the located samples, image units
  double rms_after = 0;
  int iterations = 0;
};

// Changes simplified->scalars so that the piecewise-linear field best matches, in the least-
// squares sense, the value of every vertex of `original` at its position (the original samples):
// each sample is located in the simplified mesh (at its own vertex if it survived in place
// according to `vertex_map`, the simplification's map from input to output vertices, which may
// be empty; else in a cell that holds it, looked for around the vertex it became first) and the
// normal equations are solved by Jacobi-preconditioned conjugate gradients (CGLS) from the
// current values, at most `iterations` steps. Positions, cells and labels are untouched; a
// linear field stays exact. The location, A x and A^T y run on `threads`; every sum has a fixed
// order, so the result does not depend on the thread count.
absl::Status RefitValues(const TetMesh& original, const std::vector<int32_t>& vertex_map,
                         TetMesh* simplified, int iterations, int threads,
                         const CancelToken* cancel, RefitStats* stats);

// RefitValues with `iterations` > 0 (nothing otherwise), then its progress event (stage
// "simplify", at 1.0, the sample count and the RMS before and after): what a field run, a
// streamed run and a level extraction do last.
absl::Status RefitAndReport(const TetMesh& original, const std::vector<int32_t>& vertex_map,
                            TetMesh* simplified, int iterations, int threads,
                            const CancelToken* cancel, const ProgressFn& progress);

}  // namespace decima::simplify_internal
