// Multiphase level-set segmentation (paper §2.1, after Samson et al. 2000): partitions a volume
// into K homogeneous regions and gives every voxel its region label and its distance to the
// nearest interface between regions, which the mesher stores per vertex.
//
// Invariants of a SegmentResult:
//  - `labels` is uint8 on exactly the image's grid; every value is in 0..K-1;
//  - interface distances are >= 0 (see SegmentResult), one per voxel in storage order;
//  - class_means, region_voxels and region_volumes_mm3 have K entries, region_voxels sums to the
//    voxel count.
// All functions are pure: they read their inputs and return values; they are thread-compatible
// (concurrent calls on different or the same const inputs are safe).
#pragma once

#include <cstdint>
#include <filesystem>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/volume/volume.h"

namespace decima {

// Parameters of Eq. (4). Lengths are in "voxel units": multiples of the smallest voxel spacing,
// so the same defaults fit 0.5 mm and 2 mm data; anisotropic spacing is respected in every
// derivative and distance. Intensities are used in their own units; the fitting term is divided
// by the pooled within-class variance of the initial partition (see README.md), which makes the
// weights dimensionless and the defaults work on CT (0..3272) and MRI (0..255) alike.
struct SegmentOptions {
  // K, the number of regions and level set functions, 2..8.
  int regions = 3;
  // c_i in image units, one per region (region i gets class_means[i]). Empty: estimated by
  // K-class k-means on the intensities, sorted ascending (region 0 = darkest). When given they
  // stay fixed; when estimated they are updated every iteration as the H_a(phi_i)-weighted mean
  // of the image (Samson's c_i), unless `fix_class_means` is true.
  std::vector<double> class_means;
  bool fix_class_means = false;
  // nu_i, weight of the curvature (length) term. Larger: smoother boundaries, small islands
  // removed; it competes with the noise-normalized fitting term, so nu = 1 removes features
  // whose intensity advantage over the neighbouring class is below about one noise sigma per
  // voxel of radius. >= 0.
  double curvature_weight = 1.0;
  // e_i, weight of the fitting term e_i (I - c_i)^2 / s^2 (s^2 = pooled within-class variance).
  // >= 0, at least one region > 0.
  double fitting_weight = 1.0;
  // Optional per-region overrides of the two weights above (size K or empty).
  std::vector<double> curvature_weights;
  std::vector<double> fitting_weights;
  // beta (the paper's lambda in Eq. 3), weight of the non-overlap/no-vacuum penalty
  // beta/2 (sum_j H_a(phi_j) - 1)^2. Larger: regions fill gaps and stop overlapping faster, but
  // the term is stiff, so a larger beta lowers the stable time step. >= 0.
  double overlap_weight = 1.0;
  // alpha, half width of the smoothed Heaviside H_a and Dirac delta_a, in voxel units. Only
  // voxels with |phi_i| < alpha move in an iteration. > 0.
  double alpha = 1.5;
  // Delta t, the explicit time step. 0 = automatic: 0.9 x the stability bound
  // dt_max = 1 / (2 max(nu_i) sum_c h_c^-2 / alpha + beta / (2 alpha^2)) (h_c = spacing of axis c
  // in voxel units, only axes with more than one voxel). A larger value is InvalidArgument.
  double dt = 0.0;
  // Re-initialize every phi_i to a signed distance (fast marching) every this many iterations.
  // >= 1.
  int reinit_interval = 5;
  // Iteration cap. 0 returns the k-means (or nearest-class-mean) partition unchanged.
  int max_iterations = 300;
  // Converged when the labels that changed in an iteration, as a fraction of the interface
  // (the voxel faces between two different labels), stay below this for `convergence_window`
  // consecutive iterations. In [0, 1). Relative to the interface because labels only change
  // next to it: the same value fits small and large images. At the default 0.4 % the interfaces
  // move by ~0.004 voxel per iteration on average; it is reached after ~9 iterations on the CT
  // heads and ~25 on the Colin27 MRI (whose rate decays from 2 % to 0.3 % over 50 iterations).
  // Noise keeps 0.05-0.1 % of the CT interfaces flickering (and more right after each
  // re-initialization), so much smaller values may never be reached on noisy data (README.md).
  double convergence_threshold = 4e-3;
  int convergence_window = 3;
  // Half width of the narrow band in voxel units: phi_i is kept as a signed distance only
  // within this distance of its zero level set and clamped to +-band_width beyond. 0 =
  // automatic: alpha + 1.5 x the largest axis spacing ratio (so the curvature stencil of every
  // moving voxel reads true distances). Explicit values must be >= alpha + max_c h_c.
  double band_width = 0.0;
  // Worker threads; 0 = all hardware threads. Results do not depend on it.
  int threads = 0;
};

struct SegmentResult {
  Volume labels;  // uint8 region index per voxel, the image's grid
  // Distance from every voxel centre to the nearest interface between two different labels.
  // The interface is voxel-centred: it lies halfway between two 6-neighbours of different
  // labels, so a voxel next to an interface has 0.5 (voxels) and the next one 1.5. Exact
  // Euclidean distance to the nearest such face centre. Values are >= 0: the sign convention
  // is "positive = away from the interface" on both sides (with K regions there is no single
  // inside; `labels` says which region a voxel is in). +infinity if the volume has one label.
  std::vector<float> interface_distance_voxels;  // in index space (voxel steps, unit per axis)
  std::vector<float> interface_distance_mm;      // in millimetres (spacing respected)
  std::vector<double> class_means;               // final c_i, image units
  std::vector<int64_t> region_voxels;            // voxels per label
  std::vector<double> region_volumes_mm3;        // region_voxels x voxel volume
  int iterations = 0;
  bool converged = false;
  // Final value of Eq. (3) with the fitting term divided by the within-class variance (so it
  // is dimensionless), in voxel-unit volume. 0 for SegmentationFromLabelMap.
  double energy = 0.0;
  double within_class_sigma = 0.0;  // s, image units (see SegmentOptions)
};

// The checks of `options` that need no image (regions, class_means, weights, alpha, dt >= 0,
// iteration and convergence settings, threads): OK or InvalidArgument naming the option
// ("segment: regions = 9, expected 2 to 8"). Segment adds the grid-dependent checks (dt against
// the stability bound, band_width). For callers that validate a request before any image exists.
absl::Status ValidateSegmentOptions(const SegmentOptions& options);

// Segments `image` into options.regions regions by Eq. (4), starting from k-means (or from the
// nearest given class mean). Reports Progress{stage "segment", metrics iteration, energy,
// changed_fraction} after every iteration and polls `cancel` (nullptr = never) every iteration
// and between the phases of the set-up. Errors: InvalidArgument naming the parameter (K outside
// 2..8, negative or non-finite weights, dt above the stability bound, ...) or the image
// (invalid Volume); Cancelled. Deterministic: same inputs, same labels for any thread count.
absl::StatusOr<SegmentResult> Segment(const Volume& image, const SegmentOptions& options,
                                      const ProgressFn& progress, const CancelToken* cancel);

// The largest stable Delta t for these options on this grid (the bound Segment checks).
double MaxStableTimeStep(const SegmentOptions& options, const Volume& image);

// A label map the user already has, instead of the level set: `label_map` must lie on the
// image's grid (SameGrid) and hold integer values (any voxel type); its distinct values are
// remapped to 0..K-1 in ascending order (K <= 8). Class means and volumes are measured on
// `image`. iterations = 0, converged = true, energy = 0. InvalidArgument otherwise, naming the
// problem (grid mismatch with both grids described, non-integer value, too many labels).
absl::StatusOr<SegmentResult> SegmentationFromLabelMap(const Volume& image,
                                                       const Volume& label_map);

// Plain K-class k-means on the intensities, on a histogram (exact for integer images of <= 2^16
// distinct levels, else 4096 bins): the optimal 1D partition of a coarse histogram by dynamic
// programming, refined by Lloyd's algorithm on the full one. Deterministic. Means ascending;
// each voxel gets its nearest mean.
struct KMeansResult {
  std::vector<double> means;
  Volume labels;                  // uint8, image grid
  double within_class_sigma = 0;  // sqrt of the pooled within-class variance
};
absl::StatusOr<KMeansResult> KMeansIntensities(const Volume& image, int k,
                                               const CancelToken* cancel = nullptr);

// Signed-free interface distance of a label volume (as in SegmentResult), in voxels and mm.
// `labels` must be uint8.
absl::Status ComputeInterfaceDistance(const Volume& labels, std::vector<float>* voxels,
                                      std::vector<float>* mm, int threads = 0,
                                      const CancelToken* cancel = nullptr);

}  // namespace decima
