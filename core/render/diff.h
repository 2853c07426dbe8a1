// Image differences of the paper's §3: diff1 (Eq. 9), the mean per-pixel RGB distance between
// the rendering of the original and of the simplified mesh, and diff2 (Eq. 10), that distance
// per pixel, shown as a heat map with a colour bar.
//
// Both are computed on the 8-bit colours (0..255 per channel) the renders are stored with
// (RenderedImage::ToImage), so they are the numbers one gets from the PNG files; diff2 is in
// 0..441.7 (= 255 * sqrt(3)). diff1 averages over ALL pixels of the image (n in Eq. 9),
// background included, so it depends on how much of the image the mesh covers: compare values
// only between renders of the same size and view.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/io/png.h"
#include "core/render/renderer.h"

namespace decima {

struct DiffResult {
  int width = 0;
  int height = 0;
  std::vector<float> diff2;    // Eq. 10 per pixel, rows top to bottom
  double diff1 = 0;            // Eq. 9: mean of diff2 over all pixels
  double max_diff2 = 0;        // largest diff2
  int64_t changed_pixels = 0;  // pixels with diff2 > 0
};

// Eq. 9 and 10 between two renders of the same size. Errors: InvalidArgument if the sizes
// differ or an image is malformed.
absl::StatusOr<DiffResult> Diff(const RenderedImage& a, const RenderedImage& b);
// The same for 8-bit images (e.g. read back from PNG files); channels 3 or 4 (alpha ignored).
absl::StatusOr<DiffResult> Diff(const Image& a, const Image& b);

struct DiffImageOptions {
  // Top of the colour scale; 0 = the image's own max_diff2 (1 if the images are identical).
  // Set it to compare several heat maps on one scale.
  double max_value = 0;
  // Glyph scale of the labels (1 = 5x7 pixels); 0 = chosen from the image height.
  int text_scale = 0;
};

// The diff2 heat map with a vertical colour bar on its right, labelled with the scale's range
// (0 at the bottom, the maximum at the top) and "diff1 = ..." under the map.
Image DiffHeatMap(const DiffResult& diff, const DiffImageOptions& options = {});
absl::Status WriteDiffImage(const DiffResult& diff, const std::filesystem::path& path,
                            const DiffImageOptions& options = {});

// Side by side: original | simplified | diff2 heat map (+ colour bar), each panel titled.
// Errors: InvalidArgument if the three sizes differ.
absl::StatusOr<Image> ComparisonImage(const RenderedImage& original,
                                      const RenderedImage& simplified, const DiffResult& diff,
                                      const DiffImageOptions& options = {});
// The same from 8-bit RGB pictures of the renders (e.g. annotated with AnnotateRender, which
// keeps their size); channels 3.
absl::StatusOr<Image> ComparisonImage(const Image& original, const Image& simplified,
                                      const DiffResult& diff, const DiffImageOptions& options = {});
absl::Status WriteComparison(const RenderedImage& original, const RenderedImage& simplified,
                             const DiffResult& diff, const std::filesystem::path& path,
                             const DiffImageOptions& options = {});

}  // namespace decima
