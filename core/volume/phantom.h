// Synthetic volumes with known ground truth: the backbone of the unit tests and benchmarks.
// Deterministic for a given options struct (own RNG and normal sampler, no std distributions
// whose output differs between standard libraries).
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "core/volume/volume.h"

namespace decima {

struct Phantom {
  Volume image;   // float32 intensities (truth + noise)
  Volume labels;  // uint8 ground-truth region per voxel, same grid as `image`
};

// A head-like phantom: K nested ellipsoidal shells centred in the box. Region 0 is the outside
// (air), region K-1 the innermost core; every region touches only its direct neighbours.
struct HeadPhantomOptions {
  std::array<int64_t, 3> dims{64, 64, 64};
  Eigen::Vector3d spacing{1, 1, 1};  // mm
  // Mean intensity of each region, outermost first; K = region_means.size(), 2..8.
  std::vector<double> region_means{0.0, 1000.0, 400.0};
  double noise_sigma = 0.0;  // Gaussian noise standard deviation
  uint64_t seed = 1;
};
absl::StatusOr<Phantom> MakeHeadPhantom(const HeadPhantomOptions& options);

// The paper's Fig. 1: two Gaussian blobs. Each region's intensities are drawn from its own
// Gaussian distribution N(mean_i, sigma); the means differ by less than the noise, so the shared
// border has no strong gradient while noise makes strong gradients everywhere. Region 1 is a
// ball of radius `radius_fraction` * (smallest extent / 2) centred at the box centre shifted by
// `offset_fraction` of the x extent; region 0 is the rest.
struct GaussianBlobsOptions {
  std::array<int64_t, 3> dims{96, 96, 1};  // z = 1 gives the paper's 2D case
  Eigen::Vector3d spacing{1, 1, 1};
  double mean0 = 100.0;
  double mean1 = 130.0;
  double sigma = 20.0;
  double radius_fraction = 0.6;
  double offset_fraction = 0.0;
  uint64_t seed = 1;
};
absl::StatusOr<Phantom> MakeGaussianBlobsPhantom(const GaussianBlobsOptions& options);

// Deterministic standard-normal sampler (splitmix64 + Box-Muller), exposed for tests that add
// their own noise.
class NormalSampler {
 public:
  explicit NormalSampler(uint64_t seed) : state_(seed) {}
  double Next();

 private:
  uint64_t NextBits();
  uint64_t state_;
  bool has_spare_ = false;
  double spare_ = 0;
};

}  // namespace decima
