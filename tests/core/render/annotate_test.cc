#include "core/render/annotate.h"

#include "gtest/gtest.h"

namespace decima {
namespace {

TEST(AnnotateTest, OrientationLettersFollowLps) {
  EXPECT_EQ(OrientationLetters({1, 0, 0}), "L");
  EXPECT_EQ(OrientationLetters({-1, 0, 0}), "R");
  EXPECT_EQ(OrientationLetters({0, 1, 0}), "P");
  EXPECT_EQ(OrientationLetters({0, -1, 0}), "A");
  EXPECT_EQ(OrientationLetters({0, 0, 1}), "S");
  EXPECT_EQ(OrientationLetters({0, 0, -1}), "I");
  EXPECT_EQ(OrientationLetters({0.8, -0.6, 0}), "LA");  // oblique: both letters
  EXPECT_EQ(OrientationLetters({0.95, 0.1, 0}), "L");   // a small tilt keeps one letter
  EXPECT_EQ(OrientationLetters({0, 0, 0}), "");
}

TEST(AnnotateTest, AnteriorViewPutsThePatientsLeftOnTheRight) {
  auto view = ParseView("anterior");
  ASSERT_TRUE(view.ok());
  Bounds b;
  b.max = {100, 100, 100};
  auto cam = MakeViewCamera(*view, b, ViewOptions{});
  ASSERT_TRUE(cam.ok());
  EXPECT_EQ(OrientationLetters(cam->right), "L");
  EXPECT_EQ(OrientationLetters(-cam->right), "R");
  EXPECT_EQ(OrientationLetters(cam->up), "S");
  auto custom = ParseView("30:20");  // the colon form of "AZ,EL"
  ASSERT_TRUE(custom.ok());
  EXPECT_DOUBLE_EQ(custom->azimuth_deg, 30);
  EXPECT_DOUBLE_EQ(custom->elevation_deg, 20);
}

TEST(AnnotateTest, ScaleBarIsARoundLengthThatFitsAQuarter) {
  EXPECT_EQ(ScaleBarMm(2.0, 512), 50);   // 100 px of 128 allowed
  EXPECT_EQ(ScaleBarMm(0.5, 512), 200);  // 100 px
  EXPECT_EQ(ScaleBarMm(100, 64), 1);     // nothing fits: the smallest
}

TEST(AnnotateTest, AnnotatedRenderKeepsThePictureAndAddsAFooterBelow) {
  Image render{64, 48, 3, std::vector<uint8_t>(64 * 48 * 3, 0)};
  Camera cam;
  cam.width = 64;
  cam.height = 48;
  cam.ortho_width_mm = 64;
  const Image out = AnnotateRender(render, cam, {"INPUT X.NII  K 3", "VIEW ANTERIOR"});
  EXPECT_EQ(out.width, 64);
  EXPECT_GT(out.height, 48 + 2 * 7);  // two text lines at least
  // Letters and the scale bar drew light pixels on the black picture.
  int light = 0;
  for (int y = 0; y < 48; ++y) {
    for (int x = 0; x < 64; ++x) light += out.pixels[3 * (y * 64 + x)] > 200;
  }
  EXPECT_GT(light, 20);
  // A long footer wraps instead of being clipped: more lines, taller strip.
  const Image wrapped = AddFooter(render, {std::string(40, 'A') + " " + std::string(40, 'B')});
  const Image one = AddFooter(render, {"A"});
  EXPECT_GT(wrapped.height, one.height);
}

}  // namespace
}  // namespace decima
