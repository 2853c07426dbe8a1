// The paper's Fig. 5(c): diff1 (Eq. 9) against the number of cells removed, one line per
// simplification policy (the paper's and TetFusion), drawn as a PNG with axes, ticks, labels
// and a legend. Library decima_render_figures: linked by tools and tests only, not decima_core.
#pragma once

#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "core/io/png.h"

namespace decima {

struct PlotSeries {
  std::string name;                               // legend entry, e.g. "paper policy"
  std::vector<std::pair<double, double>> points;  // (cells removed, diff1), any order
};

struct PlotOptions {
  int width = 800;   // pixels
  int height = 560;  // pixels
  std::string title = "diff1 vs cells removed";
  std::string x_label = "cells removed";
  std::string y_label = "diff1";
  int text_scale = 2;  // glyph scale of the 5x7 font
};

// Draws the series (sorted by x, lines with square markers, distinct colours, up to 6 series)
// on axes that start at 0 and end at a "nice" value above the largest point.
// Errors: InvalidArgument for no series, a series without points, a non-finite or negative
// coordinate, more than 6 series, or a size outside 200..4096.
absl::StatusOr<Image> DiffPlotImage(const std::vector<PlotSeries>& series,
                                    const PlotOptions& options = {});
absl::Status WriteDiffPlot(const std::vector<PlotSeries>& series, const std::filesystem::path& path,
                           const PlotOptions& options = {});

}  // namespace decima
