// Segment on the real CT head of ../shared/data (issue 3: "converges before the cap on the real
// CT head"), read through the product reader io::ReadVolume. Skips when the file is absent.
// The larger CT and the MRI are measured by segment_figures, not here (suite speed).
#include <gtest/gtest.h>

#include "core/io/volume_io.h"
#include "core/segment/segment.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

TEST(SegmentRealData, CtHead128ConvergesWithDefaultsIntoAirSoftTissueAndBone) {
  DECIMA_REQUIRE_SHARED_DATA(path, "ct-head-128x128x53.nii.gz");
  auto image = io::ReadVolume(path);
  ASSERT_TRUE(image.ok()) << image.status();
  SegmentOptions o;  // defaults, K = 3
  int reports = 0, setup_reports = 0;
  auto r = Segment(
      *image, o,
      [&](const Progress& p) { ++(p.metrics.at(0).second > 0 ? reports : setup_reports); },
      nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->converged);
  EXPECT_LT(r->iterations, o.max_iterations);
  EXPECT_EQ(reports, r->iterations);
  EXPECT_EQ(setup_reports, 2);  // k-means, initial level sets
  ASSERT_EQ(r->class_means.size(), 3u);
  // Darkest to brightest: air, soft tissue, bone, each a real part of the head.
  EXPECT_LT(r->class_means[0], r->class_means[1]);
  EXPECT_LT(r->class_means[1], r->class_means[2]);
  const double n = static_cast<double>(image->voxel_count());
  for (int i = 0; i < 3; ++i) EXPECT_GT(r->region_voxels[i] / n, 0.01) << "region " << i;
  EXPECT_TRUE(SameGrid(r->labels, *image));
  ASSERT_EQ(r->interface_distance_mm.size(), static_cast<size_t>(image->voxel_count()));
}

}  // namespace
}  // namespace decima
