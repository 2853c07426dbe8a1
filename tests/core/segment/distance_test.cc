// Interface distance: exact Euclidean distance to the nearest face between different labels.
#include <cmath>
#include <limits>
#include <random>

#include <gtest/gtest.h>

#include "core/segment/internal.h"
#include "core/segment/segment.h"

namespace decima {
namespace {

Volume Labels(std::array<int64_t, 3> dims, Eigen::Vector3d spacing = Eigen::Vector3d::Ones()) {
  auto v = MakeVolume(dims, VoxelType::kUInt8, spacing);
  EXPECT_TRUE(v.ok());
  return *std::move(v);
}

TEST(InterfaceDistance, TwoHalvesGiveHalfVoxelSteps) {
  Volume lab = Labels({6, 3, 2}, Eigen::Vector3d(2, 1, 1));
  for (int64_t k = 0; k < 2; ++k)
    for (int64_t j = 0; j < 3; ++j)
      for (int64_t i = 3; i < 6; ++i) lab.mutable_data<uint8_t>()[lab.Index(i, j, k)] = 1;
  std::vector<float> vox, mm;
  ASSERT_TRUE(ComputeInterfaceDistance(lab, &vox, &mm).ok());
  const float expected[6] = {2.5f, 1.5f, 0.5f, 0.5f, 1.5f, 2.5f};
  for (int64_t k = 0; k < 2; ++k)
    for (int64_t j = 0; j < 3; ++j)
      for (int64_t i = 0; i < 6; ++i) {
        EXPECT_FLOAT_EQ(vox[lab.Index(i, j, k)], expected[i]) << i << "," << j << "," << k;
        EXPECT_FLOAT_EQ(mm[lab.Index(i, j, k)], 2 * expected[i]);
      }
}

TEST(InterfaceDistance, AnisotropicSlicesScaleMillimetresOnly) {
  Volume lab = Labels({2, 2, 4}, Eigen::Vector3d(1, 1, 2.5));
  for (int64_t x = 0; x < lab.voxel_count(); ++x)
    lab.mutable_data<uint8_t>()[x] = x >= 2 * 2 * 2 ? 3 : 0;
  std::vector<float> vox, mm;
  ASSERT_TRUE(ComputeInterfaceDistance(lab, &vox, &mm).ok());
  EXPECT_FLOAT_EQ(vox[lab.Index(0, 0, 0)], 1.5f);
  EXPECT_FLOAT_EQ(vox[lab.Index(1, 1, 2)], 0.5f);
  EXPECT_FLOAT_EQ(mm[lab.Index(0, 0, 0)], 3.75f);
  EXPECT_FLOAT_EQ(mm[lab.Index(1, 1, 2)], 1.25f);
}

TEST(InterfaceDistance, SingleLabelIsInfinitelyFar) {
  Volume lab = Labels({3, 3, 3});
  std::vector<float> vox, mm;
  ASSERT_TRUE(ComputeInterfaceDistance(lab, &vox, &mm).ok());
  for (float d : vox) EXPECT_TRUE(std::isinf(d));
}

TEST(InterfaceDistance, RejectsNonUint8Labels) {
  auto v = MakeVolume({2, 2, 2}, VoxelType::kInt16);
  ASSERT_TRUE(v.ok());
  std::vector<float> vox, mm;
  EXPECT_EQ(ComputeInterfaceDistance(*v, &vox, &mm).code(), absl::StatusCode::kInvalidArgument);
}

// Brute force over all faces on random labels, anisotropic spacing.
TEST(InterfaceDistance, MatchesBruteForceOnRandomLabels) {
  const Eigen::Vector3d spacing(0.7, 1.3, 2.0);
  // 37 along x: the strided passes work on tiles of 16 lines, so several tiles and a partial
  // one are exercised.
  Volume lab = Labels({37, 6, 5}, spacing);
  std::mt19937 rng(7);
  for (int64_t x = 0; x < lab.voxel_count(); ++x)
    lab.mutable_data<uint8_t>()[x] = (rng() % 10) < 8 ? 0 : static_cast<uint8_t>(1 + rng() % 2);
  std::vector<float> vox, mm;
  ASSERT_TRUE(ComputeInterfaceDistance(lab, &vox, &mm).ok());
  std::vector<Eigen::Vector3d> faces;
  const uint8_t* l = lab.data<uint8_t>();
  for (int64_t k = 0; k < 5; ++k)
    for (int64_t j = 0; j < 6; ++j)
      for (int64_t i = 0; i < 37; ++i) {
        const int64_t c[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          int64_t d[3] = {i, j, k};
          if (++d[a] >= lab.dims[a]) continue;
          if (l[lab.Index(i, j, k)] != l[lab.Index(d[0], d[1], d[2])]) {
            Eigen::Vector3d f(c[0], c[1], c[2]);
            f[a] += 0.5;
            faces.push_back(f);
          }
        }
      }
  ASSERT_FALSE(faces.empty());
  for (int64_t k = 0; k < 5; ++k)
    for (int64_t j = 0; j < 6; ++j)
      for (int64_t i = 0; i < 37; ++i) {
        double best_v = 1e30, best_mm = 1e30;
        for (const auto& f : faces) {
          const Eigen::Vector3d d = f - Eigen::Vector3d(i, j, k);
          best_v = std::min(best_v, d.norm());
          best_mm = std::min(best_mm, d.cwiseProduct(spacing).norm());
        }
        EXPECT_NEAR(vox[lab.Index(i, j, k)], best_v, 1e-4);
        EXPECT_NEAR(mm[lab.Index(i, j, k)], best_mm, 1e-4);
      }
}

// The start of the level set: the signed distance to one region's boundary, bounded by the
// band width. Within the bound it must be the exact Euclidean distance to the nearest face
// between the region and the rest (brute force), beyond it exactly +-clamp.
TEST(RegionSignedDistance, MatchesBruteForceWithinTheClampOnRandomLabels) {
  const std::array<int64_t, 3> dims = {13, 9, 11};
  const double h[3] = {1.0, 1.5, 2.0};
  const float clamp = 2.5f;
  const int64_t n = dims[0] * dims[1] * dims[2];
  std::vector<uint8_t> labels(n);
  std::mt19937 rng(11);
  // Blobs rather than independent voxels, so distances up to the clamp occur.
  for (int64_t z = 0; z < dims[2]; ++z)
    for (int64_t y = 0; y < dims[1]; ++y)
      for (int64_t x = 0; x < dims[0]; ++x)
        labels[x + dims[0] * (y + dims[1] * z)] =
            static_cast<uint8_t>((x / 6 + y / 4 + z / 3 + (rng() % 9 == 0)) % 3);
  auto at = [&](int64_t x, int64_t y, int64_t z) { return x + dims[0] * (y + dims[1] * z); };
  for (int region = 0; region < 3; ++region) {
    std::vector<float> phi(n);
    segment_internal::RegionSignedDistance(labels.data(), dims, h, region, clamp, phi.data(), 2);
    std::vector<Eigen::Vector3d> faces;
    for (int64_t z = 0; z < dims[2]; ++z)
      for (int64_t y = 0; y < dims[1]; ++y)
        for (int64_t x = 0; x < dims[0]; ++x)
          for (int a = 0; a < 3; ++a) {
            int64_t q[3] = {x, y, z};
            if (++q[a] >= dims[a]) continue;
            if ((labels[at(x, y, z)] == region) != (labels[at(q[0], q[1], q[2])] == region)) {
              Eigen::Vector3d f(x * h[0], y * h[1], z * h[2]);
              f[a] += 0.5 * h[a];
              faces.push_back(f);
            }
          }
    ASSERT_FALSE(faces.empty());
    int near = 0, far = 0;
    for (int64_t z = 0; z < dims[2]; ++z)
      for (int64_t y = 0; y < dims[1]; ++y)
        for (int64_t x = 0; x < dims[0]; ++x) {
          double best = 1e30;
          for (const auto& f : faces)
            best = std::min(best, (f - Eigen::Vector3d(x * h[0], y * h[1], z * h[2])).norm());
          const bool inside = labels[at(x, y, z)] == region;
          const float got = phi[at(x, y, z)];
          EXPECT_EQ(got > 0, inside) << x << " " << y << " " << z;
          if (best < clamp) {
            ++near;
            EXPECT_NEAR(std::abs(got), best, 1e-5) << x << " " << y << " " << z;
          } else {
            ++far;
            EXPECT_EQ(std::abs(got), clamp) << x << " " << y << " " << z;
          }
        }
    EXPECT_GT(near, 100);
    EXPECT_GT(far, 10) << "the test must also reach beyond the clamp";
  }
}

}  // namespace
}  // namespace decima
