#include "core/pipeline/pictures.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <cstdio>

#include "absl/strings/str_cat.h"
#include "core/common/status.h"
#include "core/io/png.h"
#include "core/render/annotate.h"
#include "core/render/canvas.h"
#include "core/segment/montage.h"

namespace decima::pipeline {
namespace {

using TextChunks = std::vector<std::pair<std::string, std::string>>;

// File-name part of a view: named views as they are, "30:20" / "30,20" as "az30_el20".
std::string ViewFileSuffix(const std::string& view) {
  const size_t sep = view.find_first_of(",:");
  std::string out = sep == std::string::npos
                        ? view
                        : absl::StrCat("az", view.substr(0, sep), "_el", view.substr(sep + 1));
  for (char& c : out) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_' && c != '-' && c != '.') c = '_';
  }
  return out;
}

// The two footer lines every view picture ends with.
std::vector<std::string> ViewFooter(const ViewRender& view, const PictureCaption& c) {
  return {absl::StrCat("INPUT ", c.input_name, c.job_name.empty() ? "" : "  JOB ", c.job_name),
          absl::StrCat("K ", c.regions, "  REDUCTION ", FormatPercent(c.achieved_reduction), " OF ",
                       FormatPercent(c.target_reduction), "  POLICY ", c.policy, "  PRESET ",
                       c.preset, "  VIEW ", view.name)};
}

TextChunks ViewText(const ViewRender& view, const PictureCaption& c, const DiffImageOptions& heat) {
  return {{"Software", "decima"},
          {"Source", c.input_name},
          {"decima:job", c.job_name},
          {"decima:view", view.name},
          {"decima:regions", absl::StrCat(c.regions)},
          {"decima:target_reduction", absl::StrCat(c.target_reduction)},
          {"decima:achieved_reduction", absl::StrCat(c.achieved_reduction)},
          {"decima:policy", c.policy},
          {"decima:transfer_function", c.preset},
          {"decima:diff1", absl::StrCat(view.diff.diff1)},
          {"decima:heat_scale_max", absl::StrCat(heat.max_value)}};
}

std::vector<std::string> WithTitle(std::string title, std::vector<std::string> footer) {
  footer.insert(footer.begin(), std::move(title));
  return footer;
}

}  // namespace

std::string FormatPercent(double fraction) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f%%", 100 * fraction);
  return buf;
}

std::string ViewPictureName(const char* base, const std::string& view, size_t view_index) {
  return absl::StrCat(base, view_index == 0 ? "" : absl::StrCat("-", ViewFileSuffix(view)), ".png");
}

absl::Status WriteViewPictures(const ViewRender& view, size_t view_index,
                               const PictureCaption& caption, const DiffImageOptions& heat,
                               const std::filesystem::path& dir) {
  const std::vector<std::string> footer = ViewFooter(view, caption);
  const TextChunks text = ViewText(view, caption, heat);
  auto path = [&](const char* base) { return dir / ViewPictureName(base, view.name, view_index); };
  DECIMA_RETURN_IF_ERROR(WritePng(
      path("original"),
      AnnotateRender(view.original.ToImage(), view.camera, WithTitle("ORIGINAL MESH", footer)),
      text));
  DECIMA_RETURN_IF_ERROR(WritePng(
      path("simplified"),
      AnnotateRender(view.simplified.ToImage(), view.camera, WithTitle("SIMPLIFIED MESH", footer)),
      text));
  DECIMA_RETURN_IF_ERROR(WritePng(
      path("diff"),
      AddFooter(
          DiffHeatMap(view.diff, heat),
          WithTitle(absl::StrCat("COLOUR DIFFERENCE PER PIXEL (RGB DISTANCE 0-442), FIXED SCALE 0-",
                                 FormatNumber(heat.max_value), ", LARGER AS THE TOP"),
                    footer)),
      text));
  return WriteComparisonPicture(view, caption, heat, path("comparison"));
}

absl::Status WriteComparisonPicture(const ViewRender& view, const PictureCaption& caption,
                                    const DiffImageOptions& heat,
                                    const std::filesystem::path& path) {
  DECIMA_ASSIGN_OR_RETURN(
      const Image comparison,
      ComparisonImage(AnnotateRender(view.original.ToImage(), view.camera, {}),
                      AnnotateRender(view.simplified.ToImage(), view.camera, {}), view.diff, heat));
  return WritePng(path, AddFooter(comparison, ViewFooter(view, caption)),
                  ViewText(view, caption, heat));
}

Image AddRegionLegend(const Image& image, const RegionTable& regions) {
  constexpr int kPad = 8, kScale = 2, kGapAfter = 24;
  const Rgb8 fill{24, 24, 28}, ink{235, 235, 235};  // as the footer (core/render/annotate.cc)
  const int row_height = std::max(kLegendSwatch, Canvas::TextHeight(kScale)) + kPad;
  const int width = std::max(image.width, 2 * kPad + kLegendSwatch);
  // Lay out first (entries wrap to the width), then draw.
  struct Entry {
    int x, y;
  };
  std::vector<Entry> at;
  int x = kPad, y = kPad;
  for (const RegionInfo& r : regions.regions) {
    const int w = kLegendSwatch + 6 + Canvas::TextWidth(r.name, kScale);
    if (x > kPad && x + w > width - kPad) {
      x = kPad;
      y += row_height;
    }
    at.push_back({x, y});
    x += w + kGapAfter;
  }
  const int strip = regions.regions.empty() ? 0 : y + row_height;
  Canvas canvas(width, image.height + strip, fill);
  canvas.Blit(image, 0, 0);
  for (size_t i = 0; i < regions.regions.size(); ++i) {
    const RegionInfo& r = regions.regions[i];
    const int top = image.height + at[i].y;
    canvas.FillRect(at[i].x, top, kLegendSwatch, kLegendSwatch, {r.rgb[0], r.rgb[1], r.rgb[2]});
    canvas.Text(at[i].x + kLegendSwatch + 6, top + (kLegendSwatch - Canvas::TextHeight(kScale)) / 2,
                r.name, ink, kScale);
  }
  return canvas.Take();
}

absl::Status WriteSegmentationPicture(const Volume& image, const Volume& labels,
                                      const RegionTable& regions, const PictureCaption& caption,
                                      const std::filesystem::path& path) {
  std::vector<std::array<uint8_t, 3>> colours;
  std::string names;
  for (const RegionInfo& r : regions.regions) {
    colours.push_back(r.rgb);
    absl::StrAppend(&names, names.empty() ? "" : "\n", r.name);
  }
  DECIMA_ASSIGN_OR_RETURN(const Image montage, SegmentationMontage(image, labels, &colours));
  return WritePng(
      path,
      AddFooter(AddRegionLegend(montage, regions),
                {"SEGMENTATION: AXIAL | CORONAL | SAGITTAL THROUGH THE CENTRE",
                 absl::StrCat("INPUT ", caption.input_name, "  K ", caption.regions,
                              caption.from_label_map ? "  FROM LABEL MAP" : "  LEVEL SET")}),
      {{"Software", "decima"},
       {"Source", caption.input_name},
       {"decima:job", caption.job_name},
       {"decima:regions", absl::StrCat(caption.regions)},
       {"decima:region_names", names}});
}

absl::Status WriteCurvePicture(const PlotSeries& series, const std::string& view,
                               const PictureCaption& caption, const std::filesystem::path& path) {
  PlotOptions po;
  po.title = absl::StrCat("diff1 vs cells removed, view ", view);
  po.y_label = "diff1 (RGB distance 0-442)";
  DECIMA_ASSIGN_OR_RETURN(const Image plot, DiffPlotImage({series}, po));
  return WritePng(
      path,
      AddFooter(plot, {absl::StrCat("INPUT ", caption.input_name, "  POLICY ", caption.policy,
                                    "  VIEW ", view)}),
      {{"Software", "decima"}, {"Source", caption.input_name}, {"decima:job", caption.job_name}});
}

}  // namespace decima::pipeline
