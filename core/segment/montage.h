// Figure drawing for segmentations, in its own library (decima_segment_figures) that only tools
// and tests link: the service and the pipeline never draw figures.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/io/png.h"
#include "core/volume/volume.h"

namespace decima {

// The montage of three orthogonal slices through the volume centre (axial | coronal |
// sagittal, each at its physical aspect ratio) with the labels as a coloured overlay and the
// interfaces drawn solid, like the paper's Fig. 2. Grey levels window the image between its
// 1st and 99th percentile. `labels` must be uint8 on the image's grid (InvalidArgument
// otherwise). An RGB image, so that a caller can add a caption before writing it.
// `colours` (sRGB per label, e.g. a region table's): every label is tinted with its colour, so a
// legend can show the same ones; without it the figures' own palette leaves label 0 untinted.
absl::StatusOr<Image> SegmentationMontage(
    const Volume& image, const Volume& labels,
    const std::vector<std::array<uint8_t, 3>>* colours = nullptr);

// SegmentationMontage written as a PNG file; overwrites `png`.
absl::Status WriteSegmentationMontage(const Volume& image, const Volume& labels,
                                      const std::filesystem::path& png);

}  // namespace decima
