#include "core/render/renderer.h"

#include <gtest/gtest.h>

#include "core/mesh/tetrahedralize.h"

namespace decima {
namespace {

TEST(Render, Smoke) {
  auto vol = MakeFloatVolume({8, 8, 8}, std::vector<float>(512, 1.0f));
  ASSERT_TRUE(vol.ok());
  auto mesh = Tetrahedralize(*vol);
  ASSERT_TRUE(mesh.ok());
  auto cam = MakeViewCamera({0, 0}, MeshBounds(*mesh), {.width = 32, .height = 32});
  ASSERT_TRUE(cam.ok());
  TransferFunction tf{"const", {{0, {1, 0.5f, 0.25f}, 0.1f}}};
  auto img = Render(*mesh, *cam, tf);
  ASSERT_TRUE(img.ok()) << img.status();
  EXPECT_FALSE(img->empty);
  EXPECT_EQ(img->stats.lost_rays, 0);
  EXPECT_EQ(img->stats.fallback_steps, 0);
  // Centre pixel: 7 mm of constant extinction 0.1/mm.
  const int64_t c = 16 * 32 + 16;
  EXPECT_NEAR(img->alpha[c], 1 - std::exp(-0.7), 1e-5);
  EXPECT_NEAR(img->rgb[3 * c], 1 - std::exp(-0.7), 1e-5);
}

}  // namespace
}  // namespace decima
