// Helpers shared by the files of core/segment; not part of the public API.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/parallel.h"
#include "core/common/progress.h"
#include "core/common/status.h"
#include "core/segment/segment.h"
#include "core/volume/volume.h"

namespace decima::segment_internal {

using ::decima::ResolveThreads;  // core/common/parallel.h

// 1D k-means on the float intensities `v` (n values). `integer_valued`: the values are integers
// (the image type is an integer type), which allows the exact histogram.
struct KMeans1D {
  std::vector<double> means;  // ascending
};
absl::StatusOr<KMeans1D> RunKMeans(const float* v, int64_t n, int k, bool integer_valued,
                                   const CancelToken* cancel);

// labels[x] = index of the nearest of `means` (ties: lowest index). Parallel, deterministic.
void AssignNearest(const float* v, int64_t n, const std::vector<double>& means, uint8_t* labels,
                   int threads);

// Pooled within-class variance sum_x (v_x - means[labels_x])^2 / n.
double PooledVariance(const float* v, int64_t n, const uint8_t* labels,
                      const std::vector<double>& means);

// Squared Euclidean distance from every voxel centre to the nearest centre of a voxel face
// normal to axis `a` that separates two labels (region < 0) or region from the rest, with
// per-axis weights w = spacing^2, min-combined into d2. `g` is scratch.
void ShiftedLatticeEdt(const uint8_t* labels, const std::array<int64_t, 3>& dims, int a,
                       const double w[3], int region, std::vector<float>& g, float* d2,
                       int threads);

// phi = the signed distance (positive inside `region`) from every voxel centre to the faces
// between `region` and the rest, in units where the spacing is h, clamped to +-clamp. Exact
// Euclidean; one scratch float per voxel.
void RegionSignedDistance(const uint8_t* labels, const std::array<int64_t, 3>& dims,
                          const double h[3], int region, float clamp, float* phi, int threads);

// Fills region_voxels and region_volumes_mm3 of `result` from result->labels (K regions).
void CountRegions(int k, SegmentResult* result);

// How many iterations the level set will run in all, forecast after the iterations whose
// interface changed fractions are `history` (oldest first) with `quiet` of the last ones below
// the threshold: the remaining ones from the geometric decay of the last few fractions toward
// options.convergence_threshold, plus the quiet window. options.max_iterations when no decay is
// seen yet (or none can converge); never more than that, never less than those done.
int ForecastIterations(const std::vector<double>& history, int quiet, const SegmentOptions& o);

}  // namespace decima::segment_internal
