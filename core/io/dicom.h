// DICOM series reader: a folder of single-frame DICOM images (one slice per file, as CT and MR
// scanners export them) assembled into one Volume.
//
// Geometry follows DICOM Part 3 C.7.6.2 (Image Plane module), which is already LPS millimetres:
//  - column 0 of the direction is the row direction cosine ImageOrientationPatient[0..2] (the
//    way i, the column index, grows), column 1 the column cosine [3..5] (the way j grows),
//    column 2 their cross product, the slice normal;
//  - slices are sorted so that ImagePositionPatient projected on the normal increases with k,
//    hence the direction is always right-handed (determinant +1) and origin is the position of
//    the slice lowest along the normal, whatever the file names or InstanceNumbers say;
//  - spacing = (PixelSpacing[1], PixelSpacing[0], mean distance between consecutive slices):
//    PixelSpacing is (between rows, between columns), i.e. (j, i). SliceThickness and
//    SpacingBetweenSlices are ignored, positions are the truth.
// Only DICOM Part 10 files (128-byte preamble + "DICM") are considered; other files are skipped.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/volume/volume.h"

namespace decima {

// One series found in a folder, as listed by ListDicomSeries and in the error of an ambiguous
// ReadDicomSeries.
struct DicomSeriesInfo {
  std::string series_instance_uid;  // (0020,000E)
  std::string series_description;   // (0008,103E), "" if absent
  std::string modality;             // (0008,0060), "" if absent
  int64_t file_count = 0;           // image files of this series in the folder
};

// Lists the image series in `dir` (its regular files plus those of its immediate
// subdirectories), sorted by SeriesInstanceUID. Reads headers only (no pixel data).
// Errors: NotFound if `dir` does not exist; InvalidArgument if it is not a directory, holds no
// DICOM image file (the message lists what was skipped and why), or holds a file with the
// DICOM marker that is structurally corrupt (truncated, lengths past the end, unclosed
// sequences) or whose header GDCM cannot parse (named).
// Thread-safe (the first call silences GDCM's global warning and error trace once).
absl::StatusOr<std::vector<DicomSeriesInfo>> ListDicomSeries(const std::filesystem::path& dir);

// What a series is, for people reading a job's report: from its first slice's header, each ""
// if absent. Text as in the file (UTF-8 with invalid bytes replaced); PatientName is a DICOM PN
// ("FAMILY^GIVEN^MIDDLE", see FormatPersonName).
struct DicomDescription {
  std::string patient_name;        // (0010,0010)
  std::string patient_id;          // (0010,0020)
  std::string study_date;          // (0008,0020), YYYYMMDD
  std::string study_description;   // (0008,1030)
  std::string series_description;  // (0008,103E)
  std::string modality;            // (0008,0060)
};

// A PN value as people write it: "DOE^JOHN^Q" -> "DOE, JOHN Q"; only the first (alphabetic)
// component group of "alphabetic=ideographic=phonetic"; "" for an empty name.
std::string FormatPersonName(const std::string& pn);

// True if `path` is a DICOM Part 10 file by its first 132 bytes (128-byte preamble, "DICM");
// else false with `*reason` saying why. Checking this before GDCM sees a file keeps arbitrary
// files (checksums, NIfTI, archives) away from its parser. The one DICM check of the project.
bool HasDicomMarker(const std::filesystem::path& path, std::string* reason);

// Reads the series `series_instance_uid` of `dir` into a Volume (dims = Columns x Rows x
// slices; type uint8/int8/uint16/int16/uint32/int32 as stored, or after Modality LUT rescale
// (0028,1052/1053) int16 if every rescaled value is an integer in int16 range, else float32;
// modality from (0008,0060)). With an empty uid the folder must hold exactly one series.
// Errors (every message names the folder and, where one is at fault, the file and field):
//  - NotFound: `dir` missing, or no series with that uid (lists the available ones);
//  - InvalidArgument: several series and no uid (lists uid, description, modality, file count
//    of each); fewer than 2 slices; slices differing in Rows, Columns, PixelSpacing,
//    ImageOrientationPatient, BitsAllocated, PixelRepresentation, or SamplesPerPixel != 1;
//    duplicate slice positions; a missing slice ("missing slice between <a> and <b>: gap X mm,
//    expected Y mm"); uneven spacing (a gap deviating from the mean by more than 1% + 0.01 mm);
//    slices not stacked along their normal (gantry tilt); corrupt files (as ListDicomSeries);
//    pixel data that cannot be decoded or whose length is not Rows * Columns * BitsAllocated / 8;
//    more than kMaxVoxels voxels (checked before any pixel buffer is allocated).
// Files without the "DICM" marker, and DICOM objects without SeriesInstanceUID or Rows
// (DICOMDIR, reports), are skipped. Bits outside BitsStored/HighBit are masked and signed
// samples sign-extended. Cost: one read of every file's header, one full read of each slice.
// The result passed Validate(). Thread-safe as ListDicomSeries.
// With `description`, it also receives the series' description (DicomDescription).
absl::StatusOr<Volume> ReadDicomSeries(const std::filesystem::path& dir,
                                       const std::string& series_instance_uid = "",
                                       DicomDescription* description = nullptr);

}  // namespace decima
