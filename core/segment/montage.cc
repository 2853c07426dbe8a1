// Slice montage of a segmentation (the paper's Fig. 2): axial | coronal | sagittal through the
// volume centre, grey image with the regions tinted and their interfaces drawn solid.
//
// Display orientation from the direction matrix (assumed close to axis-aligned): superior up in
// coronal and sagittal panels, anterior up in the axial panel, patient left on the right
// (radiological convention). Each panel is resampled (nearest neighbour) to square pixels of
// the smallest spacing, enlarged by an integer factor when the volume is small.

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/io/png.h"
#include "core/segment/internal.h"
#include "core/segment/montage.h"
#include "core/segment/segment.h"

namespace decima {
namespace {

// Region colours (label 0 is left untinted: usually air/background).
constexpr uint8_t kPalette[8][3] = {{255, 255, 255}, {230, 60, 50},  {60, 200, 80},
                                    {70, 120, 255},  {250, 210, 40}, {220, 80, 220},
                                    {60, 220, 230},  {250, 140, 30}};
constexpr double kTint = 0.35;
constexpr int kGap = 4;

struct Panel {
  int width = 0, height = 0;
  std::vector<float> grey;      // window-normalized 0..1
  std::vector<uint8_t> labels;  // per pixel
};

// Axis a displayed along screen axis; `flip`: reversed.
struct ScreenAxis {
  int axis;
  bool flip;
};

Panel MakePanel(const Volume& image, const std::vector<float>& values, const uint8_t* lab,
                int fixed_axis, int64_t fixed_index, ScreenAxis horiz, ScreenAxis vert,
                double mm_per_pixel, float lo, float hi) {
  Panel p;
  const double wmm = image.dims[horiz.axis] * image.spacing[horiz.axis];
  const double hmm = image.dims[vert.axis] * image.spacing[vert.axis];
  p.width = std::max(1, static_cast<int>(std::lround(wmm / mm_per_pixel)));
  p.height = std::max(1, static_cast<int>(std::lround(hmm / mm_per_pixel)));
  p.grey.resize(static_cast<size_t>(p.width) * p.height);
  p.labels.resize(p.grey.size());
  const float range = hi > lo ? hi - lo : 1.0f;
  for (int r = 0; r < p.height; ++r) {
    for (int c = 0; c < p.width; ++c) {
      int64_t idx[3];
      idx[fixed_axis] = fixed_index;
      int64_t u = std::min<int64_t>(
          image.dims[horiz.axis] - 1,
          static_cast<int64_t>((c + 0.5) * mm_per_pixel / image.spacing[horiz.axis]));
      int64_t v = std::min<int64_t>(
          image.dims[vert.axis] - 1,
          static_cast<int64_t>((r + 0.5) * mm_per_pixel / image.spacing[vert.axis]));
      if (horiz.flip) u = image.dims[horiz.axis] - 1 - u;
      if (vert.flip) v = image.dims[vert.axis] - 1 - v;
      idx[horiz.axis] = u;
      idx[vert.axis] = v;
      const int64_t x = image.Index(idx[0], idx[1], idx[2]);
      p.grey[static_cast<size_t>(r) * p.width + c] =
          std::clamp((values[x] - lo) / range, 0.0f, 1.0f);
      p.labels[static_cast<size_t>(r) * p.width + c] = lab[x];
    }
  }
  return p;
}

}  // namespace

absl::StatusOr<Image> SegmentationMontage(const Volume& image, const Volume& labels,
                                          const std::vector<std::array<uint8_t, 3>>* colours) {
  DECIMA_RETURN_IF_ERROR(Validate(image, "montage: image"));
  DECIMA_RETURN_IF_ERROR(Validate(labels, "montage: labels"));
  if (labels.type != VoxelType::kUInt8 || !SameGrid(image, labels)) {
    return absl::InvalidArgumentError(absl::StrCat("montage: labels ", Describe(labels),
                                                   " must be uint8 on the image grid ",
                                                   Describe(image)));
  }
  const std::vector<float> values = image.ToFloat();
  // Window: 1st..99th percentile (robust to CT streaks and MRI hot spots).
  float lo, hi;
  {
    std::vector<float> sample;
    const int64_t n = image.voxel_count();
    const int64_t step = std::max<int64_t>(1, n / 200000);
    for (int64_t x = 0; x < n; x += step) sample.push_back(values[x]);
    auto at = [&](double q) {
      auto it = sample.begin() + static_cast<int64_t>(q * (sample.size() - 1));
      std::nth_element(sample.begin(), it, sample.end());
      return *it;
    };
    lo = at(0.01);
    hi = at(0.99);
  }
  const Eigen::Matrix3d& d = image.direction;
  const bool flip_i = d(0, 0) < 0;  // patient left to the right
  const bool flip_j = d(1, 1) < 0;  // anterior up (axial), anterior left (sagittal)
  const bool flip_k = d(2, 2) > 0;  // superior up
  double mmpp = image.spacing.minCoeff();
  double extent_px = 0;
  for (int c = 0; c < 3; ++c)
    extent_px = std::max(extent_px, image.dims[c] * image.spacing[c] / mmpp);
  if (extent_px < 256) mmpp /= std::ceil(256.0 / extent_px);
  const uint8_t* lab = labels.data<uint8_t>();
  // A panel is drawn unless one of its two axes is flat (a 2D image gets only the axial panel).
  std::vector<Panel> panels;
  const auto& n = image.dims;
  if (n[0] > 1 && n[1] > 1)
    panels.push_back(
        MakePanel(image, values, lab, 2, n[2] / 2, {0, flip_i}, {1, flip_j}, mmpp, lo, hi));
  if (n[0] > 1 && n[2] > 1)
    panels.push_back(
        MakePanel(image, values, lab, 1, n[1] / 2, {0, flip_i}, {2, flip_k}, mmpp, lo, hi));
  if (n[1] > 1 && n[2] > 1)
    panels.push_back(
        MakePanel(image, values, lab, 0, n[0] / 2, {1, flip_j}, {2, flip_k}, mmpp, lo, hi));
  if (panels.empty())
    panels.push_back(
        MakePanel(image, values, lab, 2, n[2] / 2, {0, flip_i}, {1, flip_j}, mmpp, lo, hi));
  int width = 0, height = 0;
  for (const Panel& p : panels) {
    width += p.width;
    height = std::max(height, p.height);
  }
  width += kGap * (static_cast<int>(panels.size()) - 1);
  Image montage;
  montage.width = width;
  montage.height = height;
  montage.channels = 3;
  std::vector<uint8_t>& rgb = montage.pixels;
  rgb.assign(static_cast<size_t>(width) * height * 3, 0);
  int x0 = 0;
  for (const Panel& p : panels) {
    for (int r = 0; r < p.height; ++r) {
      for (int c = 0; c < p.width; ++c) {
        const size_t s = static_cast<size_t>(r) * p.width + c;
        const uint8_t l = p.labels[s];
        const bool edge = (c + 1 < p.width && p.labels[s + 1] != l) ||
                          (r + 1 < p.height && p.labels[s + p.width] != l);
        uint8_t* out = &rgb[(static_cast<size_t>(r) * width + x0 + c) * 3];
        const double g = 255.0 * p.grey[s];
        const bool own = colours != nullptr && l < colours->size();
        for (int ch = 0; ch < 3; ++ch) {
          const double c = own ? (*colours)[l][ch] : kPalette[l & 7][ch];
          const double tint = l == 0 && !own ? g : (1 - kTint) * g + kTint * c;
          const uint8_t edge_colour =
              own ? (*colours)[l][ch] : kPalette[std::max<uint8_t>(l, 1) & 7][ch];
          out[ch] = edge ? edge_colour : static_cast<uint8_t>(std::lround(tint));
        }
      }
    }
    x0 += p.width + kGap;
  }
  return montage;
}

absl::Status WriteSegmentationMontage(const Volume& image, const Volume& labels,
                                      const std::filesystem::path& png) {
  DECIMA_ASSIGN_OR_RETURN(const Image montage, SegmentationMontage(image, labels));
  return WritePng(png, montage);
}

}  // namespace decima
