// K-means on intensities: exact on separated levels, deterministic, honest about too few levels.
#include <gtest/gtest.h>

#include "core/segment/segment.h"
#include "core/volume/phantom.h"

namespace decima {
namespace {

TEST(KMeans, FindsThreeSeparatedLevelsExactly) {
  auto v = MakeVolume({10, 1, 1}, VoxelType::kUInt16);
  ASSERT_TRUE(v.ok());
  const uint16_t vals[10] = {10, 10, 10, 10, 50, 52, 48, 90, 90, 90};
  for (int i = 0; i < 10; ++i) v->mutable_data<uint16_t>()[i] = vals[i];
  auto km = KMeansIntensities(*v, 3);
  ASSERT_TRUE(km.ok()) << km.status();
  EXPECT_DOUBLE_EQ(km->means[0], 10);
  EXPECT_DOUBLE_EQ(km->means[1], 50);
  EXPECT_DOUBLE_EQ(km->means[2], 90);
  const uint8_t want[10] = {0, 0, 0, 0, 1, 1, 1, 2, 2, 2};
  for (int i = 0; i < 10; ++i) EXPECT_EQ(km->labels.data<uint8_t>()[i], want[i]) << i;
}

TEST(KMeans, HeavyTiesStillGiveDistinctMeans) {
  // 90 % of the voxels at 0 (CT air): the quantile seeds coincide and must be separated.
  auto v = MakeVolume({100, 1, 1}, VoxelType::kInt16);
  ASSERT_TRUE(v.ok());
  for (int i = 90; i < 95; ++i) v->mutable_data<int16_t>()[i] = 1000;
  for (int i = 95; i < 100; ++i) v->mutable_data<int16_t>()[i] = 2000;
  auto km = KMeansIntensities(*v, 3);
  ASSERT_TRUE(km.ok()) << km.status();
  EXPECT_DOUBLE_EQ(km->means[0], 0);
  EXPECT_DOUBLE_EQ(km->means[1], 1000);
  EXPECT_DOUBLE_EQ(km->means[2], 2000);
}

TEST(KMeans, FloatImagesAreBinnedButClose) {
  HeadPhantomOptions o;
  o.dims = {24, 24, 24};
  o.region_means = {0, 1000, 400};
  o.noise_sigma = 10;
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok());
  auto km = KMeansIntensities(p->image, 3);
  ASSERT_TRUE(km.ok());
  EXPECT_NEAR(km->means[0], 0, 5);
  EXPECT_NEAR(km->means[1], 400, 5);
  EXPECT_NEAR(km->means[2], 1000, 5);
  EXPECT_NEAR(km->within_class_sigma, 10, 1);
}

TEST(KMeans, RejectsFewerLevelsThanClassesAndBadK) {
  auto v = MakeVolume({4, 1, 1}, VoxelType::kUInt8);
  ASSERT_TRUE(v.ok());
  v->mutable_data<uint8_t>()[3] = 7;
  auto km = KMeansIntensities(*v, 3);
  EXPECT_EQ(km.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(km.status().message().find("2 distinct"), std::string::npos) << km.status();
  EXPECT_EQ(KMeansIntensities(*v, 1).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(KMeansIntensities(*v, 9).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace decima
