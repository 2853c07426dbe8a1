// Slice montage PNG.
#include <fstream>

#include <gtest/gtest.h>

#include "core/segment/montage.h"
#include "core/segment/segment.h"
#include "core/volume/phantom.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

TEST(Montage, WritesAPngOfThreePanels) {
  HeadPhantomOptions o;
  o.dims = {40, 32, 20};
  o.spacing = {1, 1, 2};
  o.noise_sigma = 60;
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok());
  const auto path = testing::MakeScratchDir("montage") / "montage.png";
  ASSERT_TRUE(WriteSegmentationMontage(p->image, p->labels, path).ok());
  std::ifstream in(path, std::ios::binary);
  char sig[8] = {};
  in.read(sig, 8);
  EXPECT_EQ(std::string(sig + 1, 3), "PNG");
  // IHDR: width and height, big endian, at bytes 16..23.
  unsigned char ihdr[8];
  in.seekg(16);
  in.read(reinterpret_cast<char*>(ihdr), 8);
  const int width = (ihdr[0] << 24) | (ihdr[1] << 16) | (ihdr[2] << 8) | ihdr[3];
  const int height = (ihdr[4] << 24) | (ihdr[5] << 16) | (ihdr[6] << 8) | ihdr[7];
  // Panels: axial 40x32 mm, coronal 40x40, sagittal 32x40, upscaled x7 to reach 256 px.
  EXPECT_EQ(width, 7 * (40 + 40 + 32) + 8);
  EXPECT_EQ(height, 7 * 40);
}

TEST(Montage, RejectsLabelsOffGridAndUnwritablePath) {
  HeadPhantomOptions o;
  o.dims = {8, 8, 8};
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok());
  auto other = MakeVolume({8, 8, 7}, VoxelType::kUInt8);
  EXPECT_EQ(WriteSegmentationMontage(p->image, *other, "/tmp/x.png").code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(WriteSegmentationMontage(p->image, p->labels, "/nonexistent/dir/x.png").ok());
}

}  // namespace
}  // namespace decima
