// What the regions of a job are called and how they are coloured: one table per job, made once
// after segmentation, that every artifact reads (VTU field data, .msh physical names, STL file
// names, the glTF, segmentation.png's legend, report.html, metrics.json and the DICOM SEG), so a
// region has the same name, colour and number everywhere.
//
// Numbering: a region is its label value r (0..K-1, as in labels.nii.gz and the VTU's "region"
// cell array); where a format needs numbers from 1 (Gmsh physical tags, DICOM segment numbers)
// it is r + 1, and names shown to people count from 1 too ("region 1" is label 0).
//
// Names (README "Region names"), in this order:
//  - the user's (JobSpec::region_names, one per label);
//  - for CT (DICOM Modality "CT", or no modality and a value range that is plausibly
//    Hounsfield units, PlausiblyHu), from each region's mean: below kAirBelowHu "air", from
//    there to kBoneFromHu "soft tissue", above "bone"; two regions of one class are numbered by
//    mean ("soft tissue 1", "soft tissue 2");
//  - otherwise neutral names by rank of mean: "region 1 (darkest)" ... "region K (brightest)".
// The tissue class (air / soft tissue / bone) is kept even under user names: it picks the
// colour and the DICOM codes, which describe intensity and stay true whatever the name.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace decima {

// Okabe & Ito (2008), "Color universal design": distinct under the common colour-vision
// deficiencies. sRGB bytes; the one palette of every coloured output.
inline constexpr std::array<std::array<uint8_t, 3>, 8> kOkabeIto = {{{86, 180, 233},   // sky blue
                                                                     {230, 159, 0},    // orange
                                                                     {0, 158, 115},    // green
                                                                     {240, 228, 66},   // yellow
                                                                     {0, 114, 178},    // blue
                                                                     {213, 94, 0},     // vermillion
                                                                     {204, 121, 167},  // purple
                                                                     {0, 0, 0}}};      // black

// HU thresholds on a region's mean (see the top of this file). Air is -1000 HU and lung
// parenchyma -900..-500, fat -100, soft tissue and brain 20..80, blood with contrast up to ~300,
// cancellous bone 300..800, cortical bone > 1000: -400 puts partial-volume air/skin mixtures with
// air, and 250 sits above enhanced blood and below the bone class a three-class head CT finds
// (its bone class mean is ~ 600-900 HU; its soft class ~ 30).
inline constexpr double kAirBelowHu = -400;
inline constexpr double kBoneFromHu = 250;

enum class TissueClass { kUnknown, kAir, kSoftTissue, kBone };

// A DICOM code (Code Sequence Macro).
struct Code {
  std::string value, scheme, meaning;
};

struct RegionInfo {
  uint8_t label = 0;
  std::string name;
  std::array<uint8_t, 3> rgb{};  // sRGB
  TissueClass tissue = TissueClass::kUnknown;
  // DICOM SEG Segmented Property Category and Type (CID 7150 / CID 7166): Tissue / Soft tissue,
  // Tissue / Bone, else Tissue / Tissue. Air is not a tissue and is left out of the SEG
  // (in_seg false): it is the space around the patient, which viewers show as "no segment".
  Code category, type;
  bool in_seg = true;
  int64_t voxels = 0;
  double mean = 0;     // image units
  double mean_hu = 0;  // mean + the HU offset, when the table was made from HU (else 0)
};

struct RegionTable {
  std::string naming;               // "user", "ct-hu" or "intensity"
  std::vector<RegionInfo> regions;  // regions[r].label == r
};

// True if the data should be read as Hounsfield units: modality "CT", or no modality and a value
// range from below -500 (only CT has air at -1000; MR magnitudes are >= 0) up to at most 40000.
bool PlausiblyHu(const std::string& modality, double min_value, double max_value);

// What to add to a CT's values to get HU: -1024 when nothing is below -100, else 0. A CT always
// has air (around the patient, in the airways) at -1000 HU; values that never go below -100
// are stored with the usual unsigned offset of 1024 and no RescaleIntercept to undo it (the
// shared CT head: RescaleIntercept 0, air at ~0, WindowCenter 1040 for soft tissue).
double HuOffset(double min_value);

// The table of K = means.size() regions (voxels.size() == K). `user_names` is empty or has K
// entries (checked by ValidateRegionNames; InvalidArgument here otherwise). With `hounsfield`,
// mean + hu_offset is compared with the HU thresholds.
absl::Status MakeRegionTable(const std::vector<double>& means, const std::vector<int64_t>& voxels,
                             bool hounsfield, const std::vector<std::string>& user_names,
                             RegionTable* table, double hu_offset = 0);

// Longest region name, bytes: DICOM's SegmentLabel is LO (64 characters).
inline constexpr size_t kMaxRegionNameBytes = 64;

// The rule for user-given names: exactly `regions` names, each 1..kMaxRegionNameBytes bytes of
// valid UTF-8 with no control characters (C0, DEL, C1) and no backslash (DICOM's value
// separator), not only spaces, and unique ignoring ASCII case (their file names must differ).
// InvalidArgument; `*index` (when given) receives the offending name's index, or -1 for the count.
absl::Status ValidateRegionNames(const std::vector<std::string>& names, int regions,
                                 int* index = nullptr);

// File names of the regions' surfaces: "surface-<name>.stl" with the name lower-cased, every run
// of characters other than [a-z0-9] made one "_" ("soft tissue" -> "surface-soft_tissue.stl"),
// "region_<r+1>" when nothing is left, and "_<r+1>" appended to a name another region already
// has (unique, so no surface overwrites another).
std::vector<std::string> SurfaceFileNames(const RegionTable& table);

}  // namespace decima
