#include "core/render/diff.h"

#include <gtest/gtest.h>

#include <cmath>

#include "core/render/canvas.h"
#include "core/render/plot.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

Image Solid(int w, int h, Rgb8 c, int channels = 3) {
  Image im{w, h, channels, std::vector<uint8_t>(size_t(w) * h * channels, 255)};
  for (int64_t p = 0; p < int64_t{w} * h; ++p) std::copy_n(c.begin(), 3, &im.pixels[channels * p]);
  return im;
}

RenderedImage Rendered(const Image& im) {
  RenderedImage r;
  r.width = im.width;
  r.height = im.height;
  r.rgb.resize(size_t(im.width) * im.height * 3);
  for (size_t i = 0; i < r.rgb.size(); ++i) r.rgb[i] = im.pixels[i] / 255.0f;
  r.alpha.assign(size_t(im.width) * im.height, 1);
  r.empty = false;
  return r;
}

TEST(Diff, IdenticalImagesGiveZero) {
  const Image a = Solid(7, 5, {10, 20, 30});
  auto d = Diff(a, a);
  ASSERT_TRUE(d.ok());
  EXPECT_EQ(d->diff1, 0);
  EXPECT_EQ(d->max_diff2, 0);
  EXPECT_EQ(d->changed_pixels, 0);
  EXPECT_EQ(d->diff2.size(), 35u);
}

TEST(Diff, FollowsEquations9And10) {
  const Image a = Solid(4, 2, {100, 100, 100});
  Image b = a;
  // Pixel 3 differs by (3, 4, 0) -> diff2 = 5; pixel 6 by (0, 0, 12) -> 12; RGBA alpha ignored.
  b.pixels[3 * 3 + 0] = 103;
  b.pixels[3 * 3 + 1] = 96;
  b.pixels[3 * 6 + 2] = 112;
  auto d = Diff(a, b);
  ASSERT_TRUE(d.ok());
  EXPECT_FLOAT_EQ(d->diff2[3], 5);
  EXPECT_FLOAT_EQ(d->diff2[6], 12);
  EXPECT_EQ(d->diff2[0], 0);
  EXPECT_DOUBLE_EQ(d->diff1, 17.0 / 8);
  EXPECT_DOUBLE_EQ(d->max_diff2, 12);
  EXPECT_EQ(d->changed_pixels, 2);
  // The same through RenderedImage (rounded to 8 bits first) and with an RGBA operand.
  auto r = Diff(Rendered(a), Rendered(b));
  ASSERT_TRUE(r.ok());
  EXPECT_DOUBLE_EQ(r->diff1, d->diff1);
  Image rgba = Solid(4, 2, {100, 100, 100}, 4);
  rgba.pixels[4 * 3 + 3] = 0;
  auto m = Diff(rgba, b);
  ASSERT_TRUE(m.ok());
  EXPECT_DOUBLE_EQ(m->diff1, 17.0 / 8);
}

TEST(Diff, MismatchedOrMalformedImagesAreErrors) {
  EXPECT_EQ(Diff(Solid(4, 4, {}), Solid(4, 5, {})).status().code(),
            absl::StatusCode::kInvalidArgument);
  Image bad = Solid(4, 4, {});
  bad.pixels.pop_back();
  EXPECT_EQ(Diff(bad, Solid(4, 4, {})).status().code(), absl::StatusCode::kInvalidArgument);
  RenderedImage r = Rendered(Solid(4, 4, {}));
  r.rgb.resize(3);
  EXPECT_EQ(Diff(r, r).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(RenderedImage, ToImageRoundsAndClamps) {
  RenderedImage r;
  r.width = 2;
  r.height = 1;
  r.rgb = {0.0f, 1.0f, 0.5f, -0.2f, 1.7f, 0.999f};
  r.alpha = {1, 1};
  const Image im = r.ToImage();
  EXPECT_EQ(im.pixels, (std::vector<uint8_t>{0, 255, 128, 0, 255, 255}));
}

DiffResult SomeDiff(int w, int h) {
  Image a = Solid(w, h, {0, 0, 0}), b = a;
  for (int x = 0; x < w; ++x) b.pixels[3 * (int64_t{h / 2} * w + x)] = static_cast<uint8_t>(x);
  return *Diff(a, b);
}

TEST(DiffHeatMap, ShowsTheHeatMapAColourBarAndTheRange) {
  const DiffResult d = SomeDiff(64, 48);
  const Image im = DiffHeatMap(d);
  ASSERT_EQ(im.channels, 3);
  EXPECT_GT(im.width, 64 + 20);  // the colour-bar panel on the right
  EXPECT_GT(im.height, 48 + 7);  // the diff1 line under the map
  // The map itself is the heat colour of diff2 / max_diff2, pixel for pixel.
  for (int y = 0; y < 48; ++y) {
    for (int x = 0; x < 64; ++x) {
      const Rgb8 c = HeatColor(d.diff2[int64_t{y} * 64 + x] / d.max_diff2);
      const uint8_t* p = &im.pixels[3 * (int64_t{y} * im.width + x)];
      ASSERT_EQ(Rgb8({p[0], p[1], p[2]}), c) << x << "," << y;
    }
  }
  // The bar contains both ends of the scale.
  bool top = false, bottom = false;
  for (int y = 0; y < im.height; ++y) {
    for (int x = 64; x < im.width; ++x) {
      const uint8_t* p = &im.pixels[3 * (int64_t{y} * im.width + x)];
      top |= Rgb8({p[0], p[1], p[2]}) == HeatColor(1);
      bottom |= Rgb8({p[0], p[1], p[2]}) == HeatColor(0);
    }
  }
  EXPECT_TRUE(top);
  EXPECT_TRUE(bottom);
}

TEST(DiffHeatMap, WritesADecodablePngOfTheHeatMapSize) {
  const auto dir = testing::MakeScratchDir("diff");
  const DiffResult d = SomeDiff(100, 80);
  ASSERT_TRUE(WriteDiffImage(d, dir / "diff2.png").ok());
  auto png = ReadPng(dir / "diff2.png");
  ASSERT_TRUE(png.ok()) << png.status();
  const Image expected = DiffHeatMap(d);
  EXPECT_EQ(png->width, expected.width);
  EXPECT_EQ(png->height, expected.height);
  EXPECT_EQ(png->pixels, expected.pixels);
  DiffResult broken;
  EXPECT_EQ(WriteDiffImage(broken, dir / "x.png").code(), absl::StatusCode::kInvalidArgument);
}

TEST(Comparison, PutsOriginalSimplifiedAndDiffSideBySide) {
  const auto dir = testing::MakeScratchDir("cmp");
  Image a = Solid(40, 30, {200, 10, 10}), b = Solid(40, 30, {10, 200, 10});
  b.pixels[0] = 50;
  const RenderedImage ra = Rendered(a), rb = Rendered(b);
  auto d = Diff(ra, rb);
  ASSERT_TRUE(d.ok());
  auto im = ComparisonImage(ra, rb, *d);
  ASSERT_TRUE(im.ok()) << im.status();
  EXPECT_GT(im->width, 3 * 40);
  EXPECT_GT(im->height, 30);
  // The three panels share their bottom row; left panel = original, then simplified.
  const int y = im->height - 1;
  auto at = [&](int x) {
    const uint8_t* p = &im->pixels[3 * (int64_t{y} * im->width + x)];
    return Rgb8{p[0], p[1], p[2]};
  };
  EXPECT_EQ(at(0), Rgb8({200, 10, 10}));
  EXPECT_EQ(at(39), Rgb8({200, 10, 10}));
  int first_green = -1;
  for (int x = 40; x < im->width && first_green < 0; ++x)
    if (at(x) == Rgb8({10, 200, 10})) first_green = x;
  ASSERT_GT(first_green, 39);
  EXPECT_EQ(at(first_green + 39), Rgb8({10, 200, 10}));
  ASSERT_TRUE(WriteComparison(ra, rb, *d, dir / "cmp.png").ok());
  auto png = ReadPng(dir / "cmp.png");
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_EQ(png->width, im->width);
  EXPECT_EQ(png->height, im->height);
  // Size mismatch.
  const RenderedImage small = Rendered(Solid(20, 30, {}));
  EXPECT_EQ(ComparisonImage(ra, small, *d).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(DiffPlot, WritesADecodablePngOfTheRequestedSize) {
  const auto dir = testing::MakeScratchDir("plot");
  const std::vector<PlotSeries> series = {
      {"paper", {{0, 0}, {1e6, 1.5}, {2e6, 3.2}}},
      {"TetFusion", {{0, 0}, {1e6, 4.0}, {2e6, 9.1}}},
  };
  PlotOptions o;
  o.width = 640;
  o.height = 400;
  ASSERT_TRUE(WriteDiffPlot(series, dir / "fig5.png", o).ok());
  auto png = ReadPng(dir / "fig5.png");
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_EQ(png->width, 640);
  EXPECT_EQ(png->height, 400);
  // Both series colours appear (lines and markers are drawn).
  auto count = [&](Rgb8 c) {
    int64_t n = 0;
    for (size_t i = 0; i < png->pixels.size(); i += 3)
      n += png->pixels[i] == c[0] && png->pixels[i + 1] == c[1] && png->pixels[i + 2] == c[2];
    return n;
  };
  EXPECT_GT(count({31, 119, 180}), 100);
  EXPECT_GT(count({214, 39, 40}), 100);
}

TEST(DiffPlot, RejectsBadSeriesAndSizes) {
  EXPECT_FALSE(DiffPlotImage({}).ok());
  EXPECT_FALSE(DiffPlotImage({{"a", {}}}).ok());
  EXPECT_FALSE(DiffPlotImage({{"a", {{0, std::nan("")}}}}).ok());
  EXPECT_FALSE(DiffPlotImage({{"a", {{-1, 0}}}}).ok());
  PlotOptions tiny;
  tiny.width = 10;
  EXPECT_FALSE(DiffPlotImage({{"a", {{1, 1}}}}, tiny).ok());
  // A single point at the origin still plots (axes default to 0..1).
  EXPECT_TRUE(DiffPlotImage({{"a", {{0, 0}}}}).ok());
}

TEST(Canvas, FormatsNumbersCompactly) {
  EXPECT_EQ(FormatNumber(0), "0");
  EXPECT_EQ(FormatNumber(2.5), "2.5");
  EXPECT_EQ(FormatNumber(37.214), "37.21");
  EXPECT_EQ(FormatNumber(120000), "120K");
  EXPECT_EQ(FormatNumber(2.1e6), "2.1M");
  EXPECT_EQ(FormatNumber(std::nan("")), "?");
}

}  // namespace
}  // namespace decima
