#include "core/volume/phantom.h"

#include <cmath>
#include <set>

#include <gtest/gtest.h>

namespace decima {
namespace {

TEST(Phantom, HeadPhantomHasNestedRegionsWithGivenMeans) {
  HeadPhantomOptions o;
  o.dims = {40, 40, 40};
  o.region_means = {0, 100, 200, 300};
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok()) << p.status();
  const auto* lab = p->labels.data<uint8_t>();
  const auto* img = p->image.data<float>();
  std::set<int> seen;
  for (int64_t i = 0; i < p->labels.voxel_count(); ++i) {
    seen.insert(lab[i]);
    EXPECT_EQ(img[i], o.region_means[lab[i]]);  // no noise asked for
  }
  EXPECT_EQ(seen, (std::set<int>{0, 1, 2, 3}));
  // Corner is outside, centre is the innermost region.
  EXPECT_EQ(lab[0], 0);
  EXPECT_EQ(lab[p->labels.Index(20, 20, 20)], 3);
  // Nesting: walking from the centre outwards the label never increases.
  int prev = 3;
  for (int i = 20; i < 40; ++i) {
    const int l = lab[p->labels.Index(i, 20, 20)];
    EXPECT_LE(l, prev);
    prev = l;
  }
}

TEST(Phantom, NoiseHasRequestedSigmaAndIsSeeded) {
  HeadPhantomOptions o;
  o.dims = {32, 32, 32};
  o.region_means = {50, 50};
  o.noise_sigma = 10;
  auto a = MakeHeadPhantom(o);
  auto b = MakeHeadPhantom(o);
  o.seed = 2;
  auto c = MakeHeadPhantom(o);
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  EXPECT_EQ(a->image.bytes, b->image.bytes);
  EXPECT_NE(a->image.bytes, c->image.bytes);
  double sum = 0, sum2 = 0;
  const auto* img = a->image.data<float>();
  const int64_t n = a->image.voxel_count();
  for (int64_t i = 0; i < n; ++i) {
    sum += img[i];
    sum2 += img[i] * img[i];
  }
  const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_NEAR(mean, 50.0, 0.2);
  EXPECT_NEAR(sd, 10.0, 0.2);
}

TEST(Phantom, RejectsBadRegionCounts) {
  HeadPhantomOptions o;
  o.region_means = {1};
  EXPECT_FALSE(MakeHeadPhantom(o).ok());
  o.region_means.assign(9, 1.0);
  EXPECT_FALSE(MakeHeadPhantom(o).ok());
}

TEST(Phantom, GaussianBlobsHaveTwoRegionsWithOverlappingDistributions) {
  GaussianBlobsOptions o;
  auto p = MakeGaussianBlobsPhantom(o);
  ASSERT_TRUE(p.ok()) << p.status();
  double sum[2] = {0, 0};
  int64_t count[2] = {0, 0};
  const auto* lab = p->labels.data<uint8_t>();
  const auto* img = p->image.data<float>();
  for (int64_t i = 0; i < p->image.voxel_count(); ++i) {
    sum[lab[i]] += img[i];
    ++count[lab[i]];
  }
  ASSERT_GT(count[0], 1000);
  ASSERT_GT(count[1], 1000);
  EXPECT_NEAR(sum[0] / count[0], o.mean0, 1.5);
  EXPECT_NEAR(sum[1] / count[1], o.mean1, 1.5);
  EXPECT_LT(o.mean1 - o.mean0, 2 * o.sigma);  // the weak-boundary premise of Fig. 1
}

}  // namespace
}  // namespace decima
