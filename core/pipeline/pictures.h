// The pictures of a job (internal to core/pipeline): each view's original, simplified, diff and
// comparison, segmentation.png and curve.png, with the footers and PNG tEXt chunks that carry
// the job's parameters with the picture (README "Outputs").
#pragma once

#include <cstddef>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "core/render/camera.h"
#include "core/render/diff.h"
#include "core/render/plot.h"
#include "core/render/renderer.h"
#include "core/volume/regions.h"
#include "core/volume/volume.h"

namespace decima::pipeline {

// What every picture of a job says about the job.
struct PictureCaption {
  std::string input_name;
  std::string job_name;
  size_t regions = 0;  // K, the segmentation's class count
  bool from_label_map = false;
  double target_reduction = 0;
  double achieved_reduction = 0;
  std::string policy;  // SimplifyPolicyName
  std::string preset;  // the transfer function's preset, "custom" for a JSON document
};

// One view rendered twice with the same camera, and the difference.
struct ViewRender {
  std::string name;  // as the spec gives it: "anterior", "30:20", ...
  Camera camera;
  RenderedImage original, simplified;
  DiffResult diff;
};

// The top of the difference heat maps of every job: colour distances (diff2, RGB distance
// 0..441.7) from 0 (black) to this value (pale yellow); larger ones show as the top colour. A
// fixed scale, so that an identical pixel is black and pictures of different jobs compare:
// scaled to a job's own largest difference, a one-grey-level change filled the map with orange.
// 100 is the distance between mid grey and a clearly different shade (e.g. (128,128,128) to
// (186,186,186)), where a reader starts to see a change at a glance.
inline constexpr double kHeatScaleMax = 100;

// "50.0%" for 0.5.
std::string FormatPercent(double fraction);

// The file name of a view's picture `base` ("original", "simplified", "diff", "comparison"):
// the first view's plain, a further view's suffixed "-<view>", "AZ:EL" written "azAZ_elEL".
std::string ViewPictureName(const char* base, const std::string& view, size_t view_index);

// The four pictures of view `view_index` in `dir`, under ViewPictureName. `heat` is the one
// heat-map scale of every view of the job.
absl::Status WriteViewPictures(const ViewRender& view, size_t view_index,
                               const PictureCaption& caption, const DiffImageOptions& heat,
                               const std::filesystem::path& dir);
// Only the comparison picture (original, simplified and difference side by side), at `path`;
// the original and simplified panels carry orientation letters and a mm scale (AnnotateRender).
absl::Status WriteComparisonPicture(const ViewRender& view, const PictureCaption& caption,
                                    const DiffImageOptions& heat,
                                    const std::filesystem::path& path);

// segmentation.png: the label overlay on the axial, coronal and sagittal slices through the
// centre (SegmentationMontage) in the region table's colours, the legend (AddRegionLegend) and
// its footer. The PNG's "decima:region_names" text chunk lists the names, one per line.
absl::Status WriteSegmentationPicture(const Volume& image, const Volume& labels,
                                      const RegionTable& regions, const PictureCaption& caption,
                                      const std::filesystem::path& path);

// `image` with a legend strip below it: per region a kLegendSwatch-pixel square of its colour
// (solid, with no border inside it) and its name (upper case: the figures' bitmap font has no
// lower case; characters it lacks are drawn as "?"), left to right, wrapped to the width.
inline constexpr int kLegendSwatch = 16;
Image AddRegionLegend(const Image& image, const RegionTable& regions);

// curve.png: diff1 of view `view` against the cells removed (the paper's Fig. 5).
absl::Status WriteCurvePicture(const PlotSeries& series, const std::string& view,
                               const PictureCaption& caption, const std::filesystem::path& path);

}  // namespace decima::pipeline
