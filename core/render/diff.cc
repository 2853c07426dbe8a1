#include "core/render/diff.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/render/canvas.h"

namespace decima {
namespace {

constexpr Rgb8 kPanel{40, 40, 40};
constexpr Rgb8 kText{235, 235, 235};

absl::Status CheckImage(const Image& im, const char* which) {
  if (im.width <= 0 || im.height <= 0 || (im.channels != 3 && im.channels != 4) ||
      im.pixels.size() != size_t(im.width) * im.height * im.channels) {
    return absl::InvalidArgumentError(absl::StrCat("diff: ", which, " image is malformed (",
                                                   im.width, "x", im.height, "x", im.channels, ", ",
                                                   im.pixels.size(), " bytes)"));
  }
  return absl::OkStatus();
}

double ScaleMax(const DiffResult& d, const DiffImageOptions& o) {
  if (o.max_value > 0) return o.max_value;
  return d.max_diff2 > 0 ? d.max_diff2 : 1.0;
}

int TextScale(const DiffImageOptions& o, int height) {
  return o.text_scale > 0 ? o.text_scale : std::max(1, height / 256);
}

Image HeatPixels(const DiffResult& d, double top) {
  Image im;
  im.width = d.width;
  im.height = d.height;
  im.channels = 3;
  im.pixels.resize(size_t(d.width) * d.height * 3);
  for (size_t i = 0; i < d.diff2.size(); ++i) {
    const Rgb8 c = HeatColor(d.diff2[i] / top);
    std::copy_n(c.begin(), 3, &im.pixels[3 * i]);
  }
  return im;
}

// Width of the colour-bar panel for a given text scale and scale maximum.
int BarPanelWidth(int s, double top) {
  const int labels = std::max({Canvas::TextWidth(FormatNumber(top), s),
                               Canvas::TextWidth(FormatNumber(top / 2), s),
                               Canvas::TextWidth("RGB DIST", s) - 10 * s});
  return 4 * s + 10 * s + 3 * s + labels + 4 * s;
}

// Vertical colour bar from y0 (top, = `top`) to y1 (bottom, = 0), with its range printed.
void DrawBar(Canvas& c, int x, int y0, int y1, int s, double top) {
  const int bar_w = 10 * s;
  c.Text(x, y0 - 7 * s - 4 * s, "RGB DIST", kText, s);
  for (int y = y0; y <= y1; ++y) {
    const double t = y1 > y0 ? double(y1 - y) / (y1 - y0) : 0;
    c.FillRect(x, y, bar_w, 1, HeatColor(t));
  }
  c.StrokeRect(x - 1, y0 - 1, bar_w + 2, y1 - y0 + 3, kText);
  const int lx = x + bar_w + 3 * s;
  const struct {
    double v;
    int y;
  } ticks[] = {{top, y0}, {top / 2, (y0 + y1) / 2}, {0, y1}};
  for (const auto& t : ticks) {
    c.FillRect(x + bar_w, t.y, 2 * s, std::max(1, s / 2), kText);
    // Labels centred on their tick, kept inside the bar's span so they never touch the title.
    const int ty = std::clamp(t.y - 7 * s / 2, y0, std::max(y0, y1 - 7 * s + 1));
    c.Text(lx, ty, FormatNumber(t.v), kText, s);
  }
}

}  // namespace

absl::StatusOr<DiffResult> Diff(const Image& a, const Image& b) {
  if (auto s = CheckImage(a, "first"); !s.ok()) return s;
  if (auto s = CheckImage(b, "second"); !s.ok()) return s;
  if (a.width != b.width || a.height != b.height) {
    return absl::InvalidArgumentError(absl::StrCat("diff: image sizes differ (", a.width, "x",
                                                   a.height, " vs ", b.width, "x", b.height, ")"));
  }
  DiffResult d;
  d.width = a.width;
  d.height = a.height;
  const int64_t n = int64_t{a.width} * a.height;
  d.diff2.resize(n);
  double sum = 0;
  for (int64_t i = 0; i < n; ++i) {
    const uint8_t* p = &a.pixels[a.channels * i];
    const uint8_t* q = &b.pixels[b.channels * i];
    const double dr = double(p[0]) - q[0], dg = double(p[1]) - q[1], db = double(p[2]) - q[2];
    const double e = std::sqrt(dr * dr + dg * dg + db * db);  // Eq. 10
    d.diff2[i] = static_cast<float>(e);
    sum += e;
    d.max_diff2 = std::max(d.max_diff2, e);
    d.changed_pixels += e > 0;
  }
  d.diff1 = sum / double(n);  // Eq. 9
  return d;
}

absl::StatusOr<DiffResult> Diff(const RenderedImage& a, const RenderedImage& b) {
  if (a.rgb.size() != size_t(a.width) * a.height * 3 ||
      b.rgb.size() != size_t(b.width) * b.height * 3) {
    return absl::InvalidArgumentError("diff: a rendered image's pixel buffer has the wrong size");
  }
  return Diff(a.ToImage(), b.ToImage());
}

Image DiffHeatMap(const DiffResult& diff, const DiffImageOptions& options) {
  const double top = ScaleMax(diff, options);
  const int s = TextScale(options, diff.height);
  const int pad = 6 * s;
  const int footer = 7 * s + 2 * pad;
  Canvas c(diff.width + BarPanelWidth(s, top), diff.height + footer, kPanel);
  c.Blit(HeatPixels(diff, top), 0, 0);
  DrawBar(c, diff.width + 4 * s, pad + 7 * s + 3 * s, diff.height - pad, s, top);
  c.Text(
      pad, diff.height + pad,
      absl::StrCat("MEAN DIFF ", FormatNumber(diff.diff1), "  MAX ", FormatNumber(diff.max_diff2)),
      kText, s);
  return c.Take();
}

absl::Status WriteDiffImage(const DiffResult& diff, const std::filesystem::path& path,
                            const DiffImageOptions& options) {
  if (diff.width <= 0 || diff.height <= 0 ||
      diff.diff2.size() != size_t(diff.width) * diff.height) {
    return absl::InvalidArgumentError("WriteDiffImage: the diff result is empty or malformed");
  }
  return WritePng(path, DiffHeatMap(diff, options));
}

absl::StatusOr<Image> ComparisonImage(const RenderedImage& original,
                                      const RenderedImage& simplified, const DiffResult& diff,
                                      const DiffImageOptions& options) {
  if (original.rgb.size() != size_t(original.width) * original.height * 3 ||
      simplified.rgb.size() != size_t(simplified.width) * simplified.height * 3) {
    return absl::InvalidArgumentError(
        "comparison: original, simplified and diff must have the same size");
  }
  return ComparisonImage(original.ToImage(), simplified.ToImage(), diff, options);
}

absl::StatusOr<Image> ComparisonImage(const Image& original, const Image& simplified,
                                      const DiffResult& diff, const DiffImageOptions& options) {
  const int w = original.width, h = original.height;
  if (simplified.width != w || simplified.height != h || diff.width != w || diff.height != h ||
      diff.diff2.size() != size_t(w) * h || original.channels != 3 || simplified.channels != 3 ||
      original.pixels.size() != size_t(w) * h * 3 ||
      simplified.pixels.size() != size_t(w) * h * 3) {
    return absl::InvalidArgumentError(
        "comparison: original, simplified and diff must have the same size");
  }
  const double top = ScaleMax(diff, options);
  const int s = TextScale(options, h);
  const int pad = 6 * s, gap = 4 * s;
  const int header = 7 * s + 2 * pad;
  const int width = 3 * w + 2 * gap + BarPanelWidth(s, top);
  Canvas c(width, header + h, kPanel);
  const std::string titles[3] = {"ORIGINAL", "SIMPLIFIED",
                                 absl::StrCat("DIFFERENCE (MEAN ", FormatNumber(diff.diff1), ")")};
  const Image* panels[3] = {&original, &simplified, nullptr};
  const Image heat = HeatPixels(diff, top);
  panels[2] = &heat;
  for (int k = 0; k < 3; ++k) {
    const int x = k * (w + gap);
    c.Text(x + pad, pad, titles[k], kText, s);
    c.Blit(*panels[k], x, header);
  }
  DrawBar(c, 3 * w + 2 * gap + 4 * s, header + 7 * s + 6 * s, header + h - pad, s, top);
  return c.Take();
}

absl::Status WriteComparison(const RenderedImage& original, const RenderedImage& simplified,
                             const DiffResult& diff, const std::filesystem::path& path,
                             const DiffImageOptions& options) {
  absl::StatusOr<Image> im = ComparisonImage(original, simplified, diff, options);
  if (!im.ok()) return im.status();
  return WritePng(path, *im);
}

}  // namespace decima
