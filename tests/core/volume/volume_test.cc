#include "core/volume/volume.h"

#include <cmath>
#include <limits>

#include <gtest/gtest.h>

namespace decima {
namespace {

TEST(Volume, MakeVolumeRejectsZeroDimension) {
  auto v = MakeVolume({4, 0, 4}, VoxelType::kUInt8);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(v.status().message().find("dims[1]"), std::string::npos) << v.status();
}

TEST(Volume, MakeVolumeRejectsTrillionVoxelsWithoutAllocating) {
  auto v = MakeVolume({10000, 10000, 10000}, VoxelType::kFloat32);
  ASSERT_FALSE(v.ok());
  EXPECT_NE(v.status().message().find("exceeds"), std::string::npos) << v.status();
}

TEST(Volume, PhysicalPointFollowsSpacingOriginAndDirection) {
  auto v = MakeVolume({3, 4, 5}, VoxelType::kInt16, Eigen::Vector3d(0.5, 2.0, 3.0));
  ASSERT_TRUE(v.ok());
  v->origin = Eigen::Vector3d(10, 20, 30);
  // Axis i points along -y, axis j along +x: a 90 degree rotation about z.
  v->direction << 0, 1, 0, -1, 0, 0, 0, 0, 1;
  const Eigen::Vector3d p = v->PhysicalPoint(2, 1, 1);
  EXPECT_NEAR(p.x(), 10 + 2.0, 1e-12);
  EXPECT_NEAR(p.y(), 20 - 1.0, 1e-12);
  EXPECT_NEAR(p.z(), 30 + 3.0, 1e-12);
  EXPECT_TRUE(v->IndexToPhysical().isApprox(v->IndexToPhysical()));
  EXPECT_TRUE((v->IndexToPhysical() * Eigen::Vector3d(2, 1, 1)).isApprox(p));
}

TEST(Volume, ValueAccessKeepsSourceType) {
  auto v = MakeVolume({2, 1, 1}, VoxelType::kInt16);
  ASSERT_TRUE(v.ok());
  v->mutable_data<int16_t>()[0] = -1024;
  v->mutable_data<int16_t>()[1] = 3071;
  EXPECT_EQ(v->bytes.size(), 4u);
  EXPECT_EQ(v->ValueAt(0), -1024.0);
  EXPECT_EQ(v->ToFloat()[1], 3071.0f);
  EXPECT_EQ(v->ValueRange(), std::make_pair(-1024.0, 3071.0));
}

TEST(Volume, ValidateNamesTheBadField) {
  auto v = MakeVolume({2, 2, 2}, VoxelType::kFloat32);
  ASSERT_TRUE(v.ok());
  EXPECT_TRUE(Validate(*v, "a.nii").ok());

  Volume bad_spacing = *v;
  bad_spacing.spacing[2] = 0;
  auto s = Validate(bad_spacing, "a.nii");
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("a.nii: spacing[2]"), std::string::npos) << s;

  Volume negative = *v;
  negative.spacing[0] = -1;
  EXPECT_FALSE(Validate(negative, "a.nii").ok());

  Volume nan = *v;
  nan.mutable_data<float>()[3] = std::numeric_limits<float>::quiet_NaN();
  s = Validate(nan, "b.mha");
  EXPECT_NE(s.message().find("NaN"), std::string::npos) << s;

  Volume short_data = *v;
  short_data.bytes.resize(5);
  s = Validate(short_data, "c.nrrd");
  EXPECT_NE(s.message().find("bytes"), std::string::npos) << s;

  Volume skewed = *v;
  skewed.direction(0, 1) = 0.5;
  s = Validate(skewed, "d.nii");
  EXPECT_NE(s.message().find("direction"), std::string::npos) << s;
}

TEST(Volume, SameGridComparesGeometry) {
  auto a = MakeVolume({4, 4, 4}, VoxelType::kFloat32);
  auto b = MakeVolume({4, 4, 4}, VoxelType::kUInt8);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_TRUE(SameGrid(*a, *b));
  b->origin.x() += 0.5;
  EXPECT_FALSE(SameGrid(*a, *b));
  auto c = MakeVolume({4, 4, 5}, VoxelType::kUInt8);
  EXPECT_FALSE(SameGrid(*a, *c));
}

}  // namespace
}  // namespace decima
