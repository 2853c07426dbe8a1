// A user-supplied label map instead of the level set: validated against the image's grid,
// remapped to 0..K-1, and given the same interface distance as a level-set result.
#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/segment/internal.h"
#include "core/segment/segment.h"

namespace decima {

absl::StatusOr<SegmentResult> SegmentationFromLabelMap(const Volume& image,
                                                       const Volume& label_map) {
  DECIMA_RETURN_IF_ERROR(Validate(image, "label map: image"));
  DECIMA_RETURN_IF_ERROR(Validate(label_map, "label map"));
  if (!SameGrid(image, label_map)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "label map: grid ", Describe(label_map), " (origin ", label_map.origin.x(), ",",
        label_map.origin.y(), ",", label_map.origin.z(), ") does not match the image grid ",
        Describe(image), " (origin ", image.origin.x(), ",", image.origin.y(), ",",
        image.origin.z(), "); dims, spacing, origin and direction must agree within 0.001 mm"));
  }
  const int64_t n = label_map.voxel_count();
  // Distinct values, at most 8 (kept sorted; linear search is fine for 8 entries).
  std::vector<double> distinct;
  for (int64_t x = 0; x < n; ++x) {
    const double v = label_map.ValueAt(x);
    if (v != std::floor(v)) {
      const int64_t i = x % label_map.dims[0], j = (x / label_map.dims[0]) % label_map.dims[1],
                    k = x / (label_map.dims[0] * label_map.dims[1]);
      return absl::InvalidArgumentError(absl::StrCat("label map: voxel (", i, ",", j, ",", k,
                                                     ") holds ", v,
                                                     ", expected integer region labels"));
    }
    if (std::find(distinct.begin(), distinct.end(), v) == distinct.end()) {
      if (distinct.size() == 8) {
        std::sort(distinct.begin(), distinct.end());
        return absl::InvalidArgumentError(
            absl::StrCat("label map: more than 8 distinct labels (", distinct.front(), "..",
                         distinct.back(), " and ", v, "); Decima supports 2 to 8 regions"));
      }
      distinct.push_back(v);
    }
  }
  std::sort(distinct.begin(), distinct.end());
  const int k = static_cast<int>(distinct.size());

  SegmentResult result;
  DECIMA_ASSIGN_OR_RETURN(result.labels, MakeVolume(image.dims, VoxelType::kUInt8, image.spacing));
  result.labels.origin = image.origin;
  result.labels.direction = image.direction;
  result.labels.modality = "SEG";
  uint8_t* lab = result.labels.mutable_data<uint8_t>();
  std::vector<double> sum(k, 0.0);
  for (int64_t x = 0; x < n; ++x) {
    const double v = label_map.ValueAt(x);
    const int r =
        static_cast<int>(std::lower_bound(distinct.begin(), distinct.end(), v) - distinct.begin());
    lab[x] = static_cast<uint8_t>(r);
    sum[r] += image.ValueAt(x);
  }
  segment_internal::CountRegions(k, &result);
  result.class_means.resize(k);
  double within = 0.0;
  for (int r = 0; r < k; ++r)
    result.class_means[r] = sum[r] / std::max<int64_t>(1, result.region_voxels[r]);
  for (int64_t x = 0; x < n; ++x) {
    const double d = image.ValueAt(x) - result.class_means[lab[x]];
    within += d * d;
  }
  result.within_class_sigma = std::sqrt(within / static_cast<double>(n));
  result.iterations = 0;
  result.converged = true;
  result.energy = 0.0;
  DECIMA_RETURN_IF_ERROR(ComputeInterfaceDistance(result.labels, &result.interface_distance_voxels,
                                                  &result.interface_distance_mm));
  return result;
}

}  // namespace decima
