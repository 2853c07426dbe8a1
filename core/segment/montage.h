// Figure drawing for segmentations, in its own library (decima_segment_figures) that only tools
// and tests link: the service and the pipeline never draw figures.
#pragma once

#include <filesystem>

#include "absl/status/status.h"
#include "core/volume/volume.h"

namespace decima {

// Writes a PNG montage of three orthogonal slices through the volume centre (axial | coronal |
// sagittal, each at its physical aspect ratio) with the labels as a coloured overlay and the
// interfaces drawn solid, like the paper's Fig. 2. Grey levels window the image between its
// 1st and 99th percentile. `labels` must be uint8 on the image's grid. Overwrites `png`.
absl::Status WriteSegmentationMontage(const Volume& image, const Volume& labels,
                                      const std::filesystem::path& png);

}  // namespace decima
