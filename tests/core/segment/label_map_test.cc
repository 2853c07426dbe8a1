// User-supplied label maps: grid check, remapping, interface distance.
#include <gtest/gtest.h>

#include "core/segment/segment.h"

namespace decima {
namespace {

Volume Image(std::array<int64_t, 3> dims) {
  auto v = MakeVolume(dims, VoxelType::kFloat32, Eigen::Vector3d(1, 1, 2));
  EXPECT_TRUE(v.ok());
  for (int64_t x = 0; x < v->voxel_count(); ++x)
    v->mutable_data<float>()[x] = static_cast<float>(x % 7);
  return *std::move(v);
}

TEST(LabelMap, RemapsArbitraryValuesInSortedOrderAndMeasuresDistance) {
  Volume img = Image({4, 2, 2});
  auto lm = MakeVolume(img.dims, VoxelType::kInt16, img.spacing);
  ASSERT_TRUE(lm.ok());
  for (int64_t k = 0; k < 2; ++k)
    for (int64_t j = 0; j < 2; ++j)
      for (int64_t i = 0; i < 4; ++i)
        lm->mutable_data<int16_t>()[lm->Index(i, j, k)] = i < 2 ? 42 : -5;
  auto r = SegmentationFromLabelMap(img, *lm);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->region_voxels, (std::vector<int64_t>{8, 8}));  // -5 -> 0, 42 -> 1
  EXPECT_EQ(r->labels.data<uint8_t>()[r->labels.Index(0, 0, 0)], 1);
  EXPECT_EQ(r->labels.data<uint8_t>()[r->labels.Index(3, 1, 1)], 0);
  EXPECT_DOUBLE_EQ(r->region_volumes_mm3[0], 16.0);
  EXPECT_FLOAT_EQ(r->interface_distance_voxels[r->labels.Index(0, 0, 0)], 1.5f);
  EXPECT_FLOAT_EQ(r->interface_distance_voxels[r->labels.Index(1, 1, 1)], 0.5f);
  EXPECT_FLOAT_EQ(r->interface_distance_mm[r->labels.Index(2, 0, 0)], 0.5f);
  EXPECT_TRUE(r->converged);
  EXPECT_EQ(r->iterations, 0);
  ASSERT_EQ(r->class_means.size(), 2u);
  EXPECT_TRUE(SameGrid(r->labels, img));
}

TEST(LabelMap, RejectsWrongGridNamingBoth) {
  Volume img = Image({4, 2, 2});
  auto lm = MakeVolume({4, 2, 3}, VoxelType::kUInt8, img.spacing);
  ASSERT_TRUE(lm.ok());
  auto r = SegmentationFromLabelMap(img, *lm);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("4x2x3"), std::string::npos) << r.status();
  EXPECT_NE(r.status().message().find("4x2x2"), std::string::npos) << r.status();
  auto shifted = MakeVolume(img.dims, VoxelType::kUInt8, img.spacing);
  shifted->origin.x() = 0.5;
  EXPECT_EQ(SegmentationFromLabelMap(img, *shifted).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(LabelMap, RejectsNonIntegerAndTooManyLabels) {
  Volume img = Image({9, 1, 1});
  auto lm = MakeVolume(img.dims, VoxelType::kFloat32, img.spacing);
  ASSERT_TRUE(lm.ok());
  lm->mutable_data<float>()[3] = 1.5f;
  auto r = SegmentationFromLabelMap(img, *lm);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("(3,0,0)"), std::string::npos) << r.status();
  for (int i = 0; i < 9; ++i) lm->mutable_data<float>()[i] = static_cast<float>(10 * i);
  r = SegmentationFromLabelMap(img, *lm);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("more than 8"), std::string::npos) << r.status();
  lm->mutable_data<float>()[8] = 0;  // now 8 labels: accepted
  EXPECT_TRUE(SegmentationFromLabelMap(img, *lm).ok());
}

}  // namespace
}  // namespace decima
