// K-class k-means on intensities: the initial class means c_i and the initial partition of the
// level set (paper §2.1; Samson et al. assume the classes known, we estimate them).
//
// Everything runs on a histogram, so the cost is independent of the voxel count: in 1D every
// cluster is an interval of intensities, and with prefix sums of count, count*x and count*x^2
// the squared error of any interval is O(1). A dynamic program finds the optimal partition of
// a coarse histogram, Lloyd's algorithm then refines it on the full histogram.
#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/strings/str_cat.h"
#include "core/segment/internal.h"
#include "core/segment/segment.h"

namespace decima {
namespace segment_internal {

namespace {

constexpr int64_t kFloatBins = 4096;
constexpr int64_t kMaxExactBins = int64_t{1} << 16;
constexpr int kMaxLloydIterations = 500;
constexpr int64_t kCoarseBins = 512;

}  // namespace

absl::StatusOr<KMeans1D> RunKMeans(const float* v, int64_t n, int k, bool integer_valued,
                                   const CancelToken* cancel) {
  if (n <= 0) return absl::InvalidArgumentError("k-means: empty image");
  float lo = v[0], hi = v[0];
  for (int64_t x = 1; x < n; ++x) {
    lo = std::min(lo, v[x]);
    hi = std::max(hi, v[x]);
  }
  const bool exact = integer_valued && static_cast<double>(hi) - lo + 1 <= kMaxExactBins;
  const int64_t bins = exact ? static_cast<int64_t>(hi - lo) + 1 : kFloatBins;
  const double width = exact ? 1.0 : std::max<double>(hi - lo, 1e-30) / kFloatBins;
  std::vector<double> count(bins, 0.0);
  for (int64_t x = 0; x < n; ++x) {
    const int64_t b = std::min<int64_t>(bins - 1, static_cast<int64_t>((v[x] - lo) / width));
    count[b] += 1;
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));
  auto centre = [&](int64_t b) {
    return exact ? lo + static_cast<double>(b) : lo + (b + 0.5) * width;
  };
  // Distinct occupied bins bound K.
  int64_t occupied = 0;
  for (double c : count) occupied += c > 0;
  if (occupied < k) {
    return absl::InvalidArgumentError(absl::StrCat(
        "segment: the image has only ", occupied, " distinct intensity level(s), fewer than ",
        "regions = ", k, " (choose fewer regions or give class_means)"));
  }
  // Prefix sums over bins: P0 = count, P1 = count * x, P2 = count * x^2 (double: exact enough
  // for 2^31 voxels of 16-bit values).
  std::vector<double> p0(bins + 1, 0), p1(bins + 1, 0), p2(bins + 1, 0);
  for (int64_t b = 0; b < bins; ++b) {
    const double x = centre(b);
    p0[b + 1] = p0[b] + count[b];
    p1[b + 1] = p1[b] + count[b] * x;
    p2[b + 1] = p2[b] + count[b] * x * x;
  }
  // Initialization: the globally optimal K-class partition of a histogram of at most
  // 2 * kCoarseBins units by dynamic programming over interval ends (1D k-means clusters are
  // intervals; O(K U^2)). Lloyd from quantile seeds falls into poor local minima
  // on CT, e.g. splitting the air peak and merging soft tissue with bone.
  std::vector<double> means(k);
  {
    // DP units: the occupied fine bins when there are few, else groups of equal width (then
    // at least K groups are occupied, since each holds at most bins / kCoarseBins fine bins).
    std::vector<int64_t> edges;  // unit u = fine bins [edges[u], edges[u + 1])
    if (occupied <= 2 * kCoarseBins) {
      for (int64_t q = 0; q < bins; ++q)
        if (count[q] > 0) edges.push_back(q);
      edges.push_back(bins);
      edges[0] = 0;
    } else {
      const int64_t group = (bins + kCoarseBins - 1) / kCoarseBins;
      for (int64_t q = 0; q < bins; q += group) edges.push_back(q);
      edges.push_back(bins);
    }
    const int64_t nc = static_cast<int64_t>(edges.size()) - 1;
    std::vector<double> c0(nc + 1), c1(nc + 1), c2(nc + 1);
    for (int64_t q = 0; q <= nc; ++q) {
      c0[q] = p0[edges[q]];
      c1[q] = p1[edges[q]];
      c2[q] = p2[edges[q]];
    }
    auto sse = [&](int64_t a, int64_t b) {  // units [a, b)
      const double m0 = c0[b] - c0[a];
      if (m0 <= 0) return 0.0;
      const double m1 = c1[b] - c1[a];
      return std::max(0.0, (c2[b] - c2[a]) - m1 * m1 / m0);
    };
    const double inf = std::numeric_limits<double>::infinity();
    std::vector<std::vector<double>> cost(k + 1, std::vector<double>(nc + 1, inf));
    std::vector<std::vector<int64_t>> arg(k + 1, std::vector<int64_t>(nc + 1, 0));
    cost[0][0] = 0;
    for (int i = 1; i <= k; ++i) {
      for (int64_t b = i; b <= nc; ++b) {
        double best = inf;
        int64_t best_a = i - 1;
        for (int64_t a = i - 1; a < b; ++a) {
          // Only non-empty clusters: the interval must hold voxels.
          if (c0[b] - c0[a] <= 0 || cost[i - 1][a] == inf) continue;
          const double v = cost[i - 1][a] + sse(a, b);
          if (v < best) {
            best = v;
            best_a = a;
          }
        }
        cost[i][b] = best;
        arg[i][b] = best_a;
      }
    }
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));
    int64_t b = nc;
    for (int i = k; i >= 1; --i) {
      const int64_t a = arg[i][b];
      const double m0 = c0[b] - c0[a];
      means[i - 1] = m0 > 0 ? (c1[b] - c1[a]) / m0 : centre(edges[a]);
      b = a;
    }
    // Keep the means strictly increasing (they are, unless rounding ties two of them).
    for (int i = 1; i < k; ++i) means[i] = std::max(means[i], std::nextafter(means[i - 1], inf));
  }

  // Lloyd: cluster i = bins whose centre lies in [t_{i-1}, t_i), t_i = midpoint of means.
  std::vector<int64_t> cut(k + 1), prev_cut;
  for (int it = 0; it < kMaxLloydIterations; ++it) {
    cut[0] = 0;
    cut[k] = bins;
    for (int i = 0; i + 1 < k; ++i) {
      const double t = 0.5 * (means[i] + means[i + 1]);
      // First bin whose centre is > t goes to the upper cluster (ties to the lower index).
      int64_t b = static_cast<int64_t>(std::floor(exact ? t - lo : (t - lo) / width - 0.5)) + 1;
      b = std::clamp<int64_t>(b, 0, bins);
      while (b > 0 && centre(b - 1) > t) --b;
      while (b < bins && centre(b) <= t) ++b;
      cut[i + 1] = std::max(b, cut[i]);
    }
    if (cut == prev_cut) break;
    prev_cut = cut;
    for (int i = 0; i < k; ++i) {
      const double c0 = p0[cut[i + 1]] - p0[cut[i]];
      if (c0 > 0) means[i] = (p1[cut[i + 1]] - p1[cut[i]]) / c0;
    }
    std::sort(means.begin(), means.end());
  }
  return KMeans1D{means};
}

void AssignNearest(const float* v, int64_t n, const std::vector<double>& means, uint8_t* labels,
                   int threads) {
  const int k = static_cast<int>(means.size());
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t x = 0; x < n; ++x) {
    int best = 0;
    double best_d = std::abs(v[x] - means[0]);
    for (int i = 1; i < k; ++i) {
      const double d = std::abs(v[x] - means[i]);
      if (d < best_d) {
        best_d = d;
        best = i;
      }
    }
    labels[x] = static_cast<uint8_t>(best);
  }
}

double PooledVariance(const float* v, int64_t n, const uint8_t* labels,
                      const std::vector<double>& means) {
  double sum = 0;
  for (int64_t x = 0; x < n; ++x) {
    const double d = v[x] - means[labels[x]];
    sum += d * d;
  }
  return n > 0 ? sum / static_cast<double>(n) : 0.0;
}

}  // namespace segment_internal

absl::StatusOr<KMeansResult> KMeansIntensities(const Volume& image, int k,
                                               const CancelToken* cancel) {
  if (k < 2 || k > 8) {
    return absl::InvalidArgumentError(absl::StrCat("k-means: k = ", k, ", expected 2..8"));
  }
  DECIMA_RETURN_IF_ERROR(Validate(image, "k-means: image"));
  const std::vector<float> v = image.ToFloat();
  const bool integer_valued =
      image.type != VoxelType::kFloat32 && image.type != VoxelType::kFloat64;
  DECIMA_ASSIGN_OR_RETURN(auto km, segment_internal::RunKMeans(v.data(), image.voxel_count(), k,
                                                               integer_valued, cancel));
  DECIMA_ASSIGN_OR_RETURN(Volume labels, MakeVolume(image.dims, VoxelType::kUInt8, image.spacing));
  labels.origin = image.origin;
  labels.direction = image.direction;
  segment_internal::AssignNearest(v.data(), image.voxel_count(), km.means,
                                  labels.mutable_data<uint8_t>(),
                                  segment_internal::ResolveThreads(0));
  KMeansResult result;
  result.within_class_sigma = std::sqrt(segment_internal::PooledVariance(
      v.data(), image.voxel_count(), labels.data<uint8_t>(), km.means));
  result.means = std::move(km.means);
  result.labels = std::move(labels);
  return result;
}

}  // namespace decima
