#include "core/volume/regions.h"

#include <algorithm>
#include <numeric>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "core/common/utf8.h"

namespace decima {
namespace {

// Preferred palette entries per class, so a CT's classes look alike in every job: air sky blue,
// soft tissue vermillion (flesh-like), bone yellow (ivory-like). A second region of a class takes
// the first entry not yet used.
int PreferredColour(TissueClass t, uint8_t label) {
  switch (t) {
    case TissueClass::kAir:
      return 0;
    case TissueClass::kSoftTissue:
      return 5;
    case TissueClass::kBone:
      return 3;
    case TissueClass::kUnknown:
      break;
  }
  return label % 8;
}

const char* ClassName(TissueClass t) {
  switch (t) {
    case TissueClass::kAir:
      return "air";
    case TissueClass::kSoftTissue:
      return "soft tissue";
    case TissueClass::kBone:
      return "bone";
    case TissueClass::kUnknown:
      break;
  }
  return "";
}

}  // namespace

bool PlausiblyHu(const std::string& modality, double min_value, double max_value) {
  if (modality == "CT") return true;
  if (!modality.empty()) return false;
  return min_value < -500 && min_value >= -32768 && max_value <= 40000;
}

double HuOffset(double min_value) { return min_value >= -100 ? -1024 : 0; }

absl::Status MakeRegionTable(const std::vector<double>& means, const std::vector<int64_t>& voxels,
                             bool hounsfield, const std::vector<std::string>& user_names,
                             RegionTable* table, double hu_offset) {
  const size_t k = means.size();
  if (k == 0 || k > 255 || voxels.size() != k) {
    return absl::InvalidArgumentError(
        absl::StrCat("regions: ", k, " means and ", voxels.size(), " voxel counts"));
  }
  if (!user_names.empty() && user_names.size() != k) {
    return absl::InvalidArgumentError(
        absl::StrCat("region_names: ", user_names.size(), " names for ", k, " regions"));
  }
  table->regions.assign(k, {});
  table->naming = !user_names.empty() ? "user" : hounsfield ? "ct-hu" : "intensity";
  // Rank by mean (ties by label), for the neutral names and the numbering within a class.
  std::vector<size_t> order(k);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return means[a] < means[b]; });
  std::array<int, 4> class_count{}, class_seen{};
  for (size_t r = 0; r < k; ++r) {
    RegionInfo& ri = table->regions[r];
    ri.label = static_cast<uint8_t>(r);
    ri.voxels = voxels[r];
    ri.mean = means[r];
    if (hounsfield) {
      ri.mean_hu = means[r] + hu_offset;
      ri.tissue = ri.mean_hu < kAirBelowHu   ? TissueClass::kAir
                  : ri.mean_hu < kBoneFromHu ? TissueClass::kSoftTissue
                                             : TissueClass::kBone;
    }
    ++class_count[static_cast<int>(ri.tissue)];
  }
  std::set<int> used;
  for (size_t rank = 0; rank < k; ++rank) {
    RegionInfo& ri = table->regions[order[rank]];
    const int c = static_cast<int>(ri.tissue);
    ++class_seen[c];
    if (!user_names.empty()) {
      ri.name = user_names[ri.label];
    } else if (ri.tissue != TissueClass::kUnknown) {
      ri.name = class_count[c] > 1 ? absl::StrCat(ClassName(ri.tissue), " ", class_seen[c])
                                   : ClassName(ri.tissue);
    } else {
      ri.name = absl::StrCat("region ", rank + 1,
                             rank == 0       ? " (darkest)"
                             : rank + 1 == k ? " (brightest)"
                                             : "");
    }
    int colour = PreferredColour(ri.tissue, ri.label);
    for (int step = 0; step < 8 && used.count(colour) > 0; ++step) colour = (colour + 1) % 8;
    used.insert(colour);
    ri.rgb = kOkabeIto[colour];
    ri.category = {"85756007", "SCT", "Tissue"};
    switch (ri.tissue) {
      case TissueClass::kAir:
        ri.in_seg = false;
        ri.type = {"85756007", "SCT", "Tissue"};  // never written (in_seg false)
        break;
      case TissueClass::kSoftTissue:
        ri.type = {"87784001", "SCT", "Soft tissue"};
        break;
      case TissueClass::kBone:
        ri.type = {"3138006", "SCT", "Bone"};
        break;
      case TissueClass::kUnknown:
        ri.type = {"85756007", "SCT", "Tissue"};
        break;
    }
  }
  return absl::OkStatus();
}

absl::Status ValidateRegionNames(const std::vector<std::string>& names, int regions, int* index) {
  auto fail = [index](int i, std::string message) {
    if (index != nullptr) *index = i;
    return absl::InvalidArgumentError(std::move(message));
  };
  if (names.size() != static_cast<size_t>(std::max(regions, 0))) {
    return fail(-1, absl::StrCat(names.size(), " names for ", regions,
                                 " regions (one name per region, in label order)"));
  }
  std::set<std::string> seen;
  for (size_t i = 0; i < names.size(); ++i) {
    const std::string& n = names[i];
    const int at = static_cast<int>(i);
    if (n.empty() || absl::StripAsciiWhitespace(n).empty()) return fail(at, "empty name");
    if (n.size() > kMaxRegionNameBytes) {
      return fail(at, absl::StrCat(n.size(), " bytes, at most ", kMaxRegionNameBytes));
    }
    if (ValidUtf8(n) != n) return fail(at, "not valid UTF-8");
    for (size_t j = 0; j < n.size(); ++j) {
      const auto c = static_cast<unsigned char>(n[j]);
      // C1 controls are U+0080..U+009F: the two bytes C2 80..C2 9F in UTF-8.
      const bool c1 = c == 0xC2 && j + 1 < n.size() &&
                      static_cast<unsigned char>(n[j + 1]) >= 0x80 &&
                      static_cast<unsigned char>(n[j + 1]) <= 0x9F;
      if (c < 0x20 || c == 0x7F || c1) {
        return fail(at, absl::StrCat("control character at byte ", j));
      }
      if (c == '\\') return fail(at, "backslash (DICOM's value separator)");
    }
    if (!seen.insert(absl::AsciiStrToLower(n)).second) {
      return fail(at, absl::StrCat("'", n, "' appears twice"));
    }
  }
  return absl::OkStatus();
}

std::vector<std::string> SurfaceFileNames(const RegionTable& table) {
  std::vector<std::string> out;
  std::set<std::string> taken;
  for (const RegionInfo& ri : table.regions) {
    std::string part;
    for (char ch : absl::AsciiStrToLower(ri.name)) {
      if (absl::ascii_isalnum(static_cast<unsigned char>(ch))) {
        part += ch;
      } else if (!part.empty() && part.back() != '_') {
        part += '_';
      }
    }
    while (!part.empty() && part.back() == '_') part.pop_back();
    if (part.empty()) part = absl::StrCat("region_", ri.label + 1);
    if (taken.count(part) > 0) absl::StrAppend(&part, "_", ri.label + 1);
    while (taken.count(part) > 0) part += "_";
    taken.insert(part);
    out.push_back(absl::StrCat("surface-", part, ".stl"));
  }
  return out;
}

}  // namespace decima
