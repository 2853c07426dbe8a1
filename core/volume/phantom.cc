#include "core/volume/phantom.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace decima {

uint64_t NormalSampler::NextBits() {
  // splitmix64: tiny, fast, and the same on every platform.
  uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

double NormalSampler::Next() {
  if (has_spare_) {
    has_spare_ = false;
    return spare_;
  }
  // Uniforms in (0, 1]: 53 random bits, never exactly 0 so log() is finite.
  const double u1 = (static_cast<double>(NextBits() >> 11) + 1.0) * 0x1.0p-53;
  const double u2 = static_cast<double>(NextBits() >> 11) * 0x1.0p-53;
  const double r = std::sqrt(-2.0 * std::log(u1));
  const double theta = 2.0 * M_PI * u2;
  spare_ = r * std::sin(theta);
  has_spare_ = true;
  return r * std::cos(theta);
}

namespace {

absl::StatusOr<Phantom> AllocatePhantom(const std::array<int64_t, 3>& dims,
                                        const Eigen::Vector3d& spacing) {
  auto image = MakeVolume(dims, VoxelType::kFloat32, spacing);
  if (!image.ok()) return image.status();
  auto labels = MakeVolume(dims, VoxelType::kUInt8, spacing);
  if (!labels.ok()) return labels.status();
  for (int c = 0; c < 3; ++c) {
    if (!(spacing[c] > 0) || !std::isfinite(spacing[c])) {
      return absl::InvalidArgumentError(absl::StrCat("phantom: spacing[", c, "] must be > 0"));
    }
  }
  // Centre the box on the origin so rendering and meshing see a symmetric object.
  Eigen::Vector3d origin;
  for (int c = 0; c < 3; ++c) origin[c] = -0.5 * (dims[c] - 1) * spacing[c];
  image->origin = labels->origin = origin;
  image->modality = "OT";
  return Phantom{*std::move(image), *std::move(labels)};
}

}  // namespace

absl::StatusOr<Phantom> MakeHeadPhantom(const HeadPhantomOptions& o) {
  const int k_regions = static_cast<int>(o.region_means.size());
  if (k_regions < 2 || k_regions > 8) {
    return absl::InvalidArgumentError(
        absl::StrCat("head phantom: ", k_regions, " region means given, expected 2 to 8"));
  }
  if (!(o.noise_sigma >= 0)) {
    return absl::InvalidArgumentError("head phantom: noise_sigma must be >= 0");
  }
  auto phantom = AllocatePhantom(o.dims, o.spacing);
  if (!phantom.ok()) return phantom.status();
  float* img = phantom->image.mutable_data<float>();
  uint8_t* lab = phantom->labels.mutable_data<uint8_t>();

  // Semi-axes of the outer ellipsoid (region 1) as a fraction of the half extents; inner shells
  // shrink linearly so every shell is at least a few voxels thick on a 32^3 grid.
  const Eigen::Vector3d half(0.5 * (o.dims[0] - 1) * o.spacing[0],
                             0.5 * (o.dims[1] - 1) * o.spacing[1],
                             0.5 * (o.dims[2] - 1) * o.spacing[2]);
  const Eigen::Vector3d outer = 0.85 * half.cwiseMax(Eigen::Vector3d::Constant(1e-9));
  NormalSampler noise(o.seed);
  for (int64_t k = 0; k < o.dims[2]; ++k) {
    for (int64_t j = 0; j < o.dims[1]; ++j) {
      for (int64_t i = 0; i < o.dims[0]; ++i) {
        const Eigen::Vector3d p(i * o.spacing[0] - half[0], j * o.spacing[1] - half[1],
                                k * o.spacing[2] - half[2]);
        // Normalized ellipsoidal radius: 1 on the outer shell.
        const double r = p.cwiseQuotient(outer).norm();
        int region = 0;
        for (int s = 1; s < k_regions; ++s) {
          const double shell = 1.0 - 0.8 * (s - 1) / std::max(1, k_regions - 1);
          if (r <= shell) region = s;
        }
        const int64_t idx = i + o.dims[0] * (j + o.dims[1] * k);
        lab[idx] = static_cast<uint8_t>(region);
        img[idx] = static_cast<float>(o.region_means[region] +
                                      (o.noise_sigma > 0 ? o.noise_sigma * noise.Next() : 0.0));
      }
    }
  }
  return phantom;
}

absl::StatusOr<Phantom> MakeGaussianBlobsPhantom(const GaussianBlobsOptions& o) {
  if (!(o.sigma >= 0) || !(o.radius_fraction > 0)) {
    return absl::InvalidArgumentError(
        "gaussian blobs phantom: sigma must be >= 0 and radius_fraction > 0");
  }
  auto phantom = AllocatePhantom(o.dims, o.spacing);
  if (!phantom.ok()) return phantom.status();
  float* img = phantom->image.mutable_data<float>();
  uint8_t* lab = phantom->labels.mutable_data<uint8_t>();
  double min_extent = 1e300;
  for (int c = 0; c < 3; ++c) {
    if (o.dims[c] > 1) min_extent = std::min(min_extent, (o.dims[c] - 1) * o.spacing[c]);
  }
  const double radius = o.radius_fraction * 0.5 * min_extent;
  const Eigen::Vector3d centre(
      0.5 * (o.dims[0] - 1) * o.spacing[0] + o.offset_fraction * (o.dims[0] - 1) * o.spacing[0],
      0.5 * (o.dims[1] - 1) * o.spacing[1], 0.5 * (o.dims[2] - 1) * o.spacing[2]);
  NormalSampler noise(o.seed);
  for (int64_t k = 0; k < o.dims[2]; ++k) {
    for (int64_t j = 0; j < o.dims[1]; ++j) {
      for (int64_t i = 0; i < o.dims[0]; ++i) {
        const Eigen::Vector3d p(i * o.spacing[0], j * o.spacing[1], k * o.spacing[2]);
        const int region = (p - centre).norm() <= radius ? 1 : 0;
        const int64_t idx = i + o.dims[0] * (j + o.dims[1] * k);
        lab[idx] = static_cast<uint8_t>(region);
        img[idx] = static_cast<float>((region ? o.mean1 : o.mean0) + o.sigma * noise.Next());
      }
    }
  }
  return phantom;
}

}  // namespace decima
