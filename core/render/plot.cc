#include "core/render/plot.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/render/canvas.h"

namespace decima {
namespace {

constexpr Rgb8 kWhite{255, 255, 255};
constexpr Rgb8 kInk{30, 30, 30};
constexpr Rgb8 kGrid{225, 225, 225};
constexpr Rgb8 kColors[] = {{31, 119, 180},  {214, 39, 40},  {44, 160, 44},
                            {148, 103, 189}, {255, 127, 14}, {23, 190, 207}};

// Tick step 1, 2 or 5 x 10^k giving about `target` intervals up to `max`.
double NiceStep(double max, int target) {
  const double raw = max / target;
  const double p = std::pow(10.0, std::floor(std::log10(raw)));
  for (double m : {1.0, 2.0, 5.0, 10.0}) {
    if (m * p >= raw) return m * p;
  }
  return 10 * p;
}

}  // namespace

absl::StatusOr<Image> DiffPlotImage(const std::vector<PlotSeries>& series, const PlotOptions& o) {
  if (series.empty() || series.size() > 6) {
    return absl::InvalidArgumentError(
        absl::StrCat("plot: ", series.size(), " series given, expected 1..6"));
  }
  if (o.width < 200 || o.width > 4096 || o.height < 200 || o.height > 4096 || o.text_scale < 1 ||
      o.text_scale > 8) {
    return absl::InvalidArgumentError("plot: size must be in 200..4096, text_scale in 1..8");
  }
  double xmax = 0, ymax = 0;
  for (const PlotSeries& s : series) {
    if (s.points.empty()) {
      return absl::InvalidArgumentError(absl::StrCat("plot: series '", s.name, "' has no points"));
    }
    for (const auto& [x, y] : s.points) {
      if (!std::isfinite(x) || !std::isfinite(y) || x < 0 || y < 0) {
        return absl::InvalidArgumentError(absl::StrCat("plot: series '", s.name, "' has a point (",
                                                       x, ", ", y, ") that is not finite >= 0"));
      }
      xmax = std::max(xmax, x);
      ymax = std::max(ymax, y);
    }
  }
  if (xmax <= 0) xmax = 1;
  if (ymax <= 0) ymax = 1;
  const double xstep = NiceStep(xmax, 5), ystep = NiceStep(ymax, 5);
  const double xtop = std::ceil(xmax / xstep - 1e-9) * xstep;
  const double ytop = std::ceil(ymax / ystep - 1e-9) * ystep;

  const int s = o.text_scale;
  const int th = Canvas::TextHeight(s);
  int ylabel_w = 0;
  for (double v = 0; v <= ytop + ystep * 0.5; v += ystep) {
    ylabel_w = std::max(ylabel_w, Canvas::TextWidth(FormatNumber(v), s));
  }
  // Plot area inside margins: title on top, y label above the y axis, x label below.
  const int left = 8 * s + ylabel_w + 4 * s;
  const int right = o.width - 10 * s - Canvas::TextWidth(FormatNumber(xtop), s) / 2;
  const int top = 3 * th + 8 * s;
  const int bottom = o.height - (2 * th + 10 * s);
  if (right - left < 50 || bottom - top < 50) {
    return absl::InvalidArgumentError("plot: the image is too small for its labels");
  }
  auto X = [&](double x) { return left + (right - left) * x / xtop; };
  auto Y = [&](double y) { return bottom - (bottom - top) * y / ytop; };

  Canvas c(o.width, o.height, kWhite);
  c.Text((o.width - Canvas::TextWidth(o.title, s)) / 2, 4 * s, o.title, kInk, s);
  // Grid, ticks and tick labels.
  for (int i = 0; i * xstep <= xtop + xstep * 0.5; ++i) {
    const double v = i * xstep;
    const int x = static_cast<int>(std::lround(X(v)));
    c.FillRect(x, top, 1, bottom - top, kGrid);
    c.FillRect(x, bottom, 1, 3 * s, kInk);
    const std::string label = FormatNumber(v);
    c.Text(x - Canvas::TextWidth(label, s) / 2, bottom + 5 * s, label, kInk, s);
  }
  for (int i = 0; i * ystep <= ytop + ystep * 0.5; ++i) {
    const double v = i * ystep;
    const int y = static_cast<int>(std::lround(Y(v)));
    c.FillRect(left, y, right - left, 1, kGrid);
    c.FillRect(left - 3 * s, y, 3 * s, 1, kInk);
    const std::string label = FormatNumber(v);
    c.Text(left - 5 * s - Canvas::TextWidth(label, s), y - th / 2, label, kInk, s);
  }
  // Axes and their labels.
  c.FillRect(left, top, 2, bottom - top + 1, kInk);
  c.FillRect(left, bottom, right - left + 1, 2, kInk);
  c.Text((left + right - Canvas::TextWidth(o.x_label, s)) / 2, bottom + 5 * s + th + 4 * s,
         o.x_label, kInk, s);
  c.Text(std::max(2, left - Canvas::TextWidth(o.y_label, s) / 2), top - th - 4 * s, o.y_label, kInk,
         s);

  // Series: lines through the points in x order, square markers.
  for (size_t k = 0; k < series.size(); ++k) {
    std::vector<std::pair<double, double>> pts = series[k].points;
    std::sort(pts.begin(), pts.end());
    const Rgb8 col = kColors[k];
    for (size_t i = 0; i + 1 < pts.size(); ++i) {
      c.Line(X(pts[i].first), Y(pts[i].second), X(pts[i + 1].first), Y(pts[i + 1].second), col,
             std::max(2, s));
    }
    for (const auto& [x, y] : pts) {
      const int m = 3 * s;
      c.FillRect(static_cast<int>(std::lround(X(x))) - m, static_cast<int>(std::lround(Y(y))) - m,
                 2 * m + 1, 2 * m + 1, col);
    }
  }
  // Legend, top left inside the plot area.
  int lw = 0;
  for (const PlotSeries& ser : series) lw = std::max(lw, Canvas::TextWidth(ser.name, s));
  const int lx = left + 10 * s, ly = top + 6 * s;
  const int row = th + 5 * s;
  const int box_w = 4 * s + 14 * s + 4 * s + lw + 4 * s;
  const int box_h = static_cast<int>(series.size()) * row + 4 * s;
  c.FillRect(lx, ly, box_w, box_h, kWhite);
  c.StrokeRect(lx, ly, box_w, box_h, kInk);
  for (size_t k = 0; k < series.size(); ++k) {
    const int y = ly + 4 * s + static_cast<int>(k) * row;
    c.Line(lx + 4 * s, y + th / 2, lx + 18 * s, y + th / 2, kColors[k], std::max(2, s));
    c.FillRect(lx + 11 * s - 2 * s, y + th / 2 - 2 * s, 4 * s + 1, 4 * s + 1, kColors[k]);
    c.Text(lx + 22 * s, y, series[k].name, kInk, s);
  }
  return c.Take();
}

absl::Status WriteDiffPlot(const std::vector<PlotSeries>& series, const std::filesystem::path& path,
                           const PlotOptions& options) {
  absl::StatusOr<Image> im = DiffPlotImage(series, options);
  if (!im.ok()) return im.status();
  return WritePng(path, *im);
}

}  // namespace decima
