// Writes synthetic DICOM slices and series with GDCM for tests: full control over each
// attribute, including broken ones (tests/core/io/dicom_test.cc, tests/server, tests/e2e).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <gdcmTransferSyntax.h>

namespace decima::testing {

// One slice file as the test wants it; defaults make a valid 3 x 4 uint16 CT slice.
struct SliceSpec {
  int rows = 4;
  int columns = 3;
  std::vector<double> pixel_spacing = {0.5, 0.8};  // DICOM order: between rows, between columns
  std::vector<double> orientation = {1, 0, 0, 0, 1, 0};
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
  int bits_allocated = 16;
  int bits_stored = 0;  // 0: BitsAllocated
  int pixel_representation = 0;
  int samples_per_pixel = 1;
  std::optional<double> slope, intercept, slice_thickness;
  std::string series_uid = "1.2.826.0.1.3680043.9.7777.1";
  std::string description = "synthetic";
  std::string modality = "CT";
  // Patient and study attributes, written only when not empty.
  std::string patient_name, patient_id, study_date, study_description;
  std::string sop_class_uid = "1.2.840.10008.5.1.4.1.1.2";  // CT Image Storage
  int instance = 1;
  bool with_sequence = false;    // adds a nested Referenced Image Sequence (undefined lengths)
  std::string number_of_frames;  // (0028,0008) written as is when not empty (broken values too)
  gdcm::TransferSyntax::TSType transfer_syntax = gdcm::TransferSyntax::ExplicitVRLittleEndian;
  // Pixel (i, j) = value(i, j); values are cast to the stored type.
  std::function<double(int, int)> value = [](int i, int j) { return 10 * j + i; };
};

// Writes one Part 10 file (fails the current test if GDCM cannot).
void WriteSlice(const std::filesystem::path& path, const SliceSpec& s);

// Writes `n` slices of `base` stacked along the orientation's normal at `gaps` (n - 1 values)
// from `base.position`; slice s (0-based, in stacking order) holds value(i, j) + 100 * s and is
// written as "<prefix><name_order[s]>.dcm".
std::vector<std::filesystem::path> WriteSeries(const std::filesystem::path& dir,
                                               const SliceSpec& base,
                                               const std::vector<double>& gaps,
                                               std::vector<int> name_order = {},
                                               const std::string& prefix = "s");

}  // namespace decima::testing
