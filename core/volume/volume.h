// A 3D scalar image on a regular grid, as scanners and segmentation tools produce it.
//
// Invariants of a valid Volume (checked by Validate()):
//  - dims[c] >= 1 for all c and the product fits kMaxVoxels;
//  - bytes.size() == voxel_count() * VoxelTypeSize(type);
//  - spacing is finite and > 0; origin finite; direction has unit, mutually orthogonal columns
//    (tolerance 1e-3) and determinant +-1.
// Voxel (i, j, k) is stored at i + dims[0] * (j + dims[1] * k), native byte order.
// Physical points are LPS millimetres: p = origin + direction * diag(spacing) * (i, j, k).
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>
#include "absl/strings/string_view.h"

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace decima {

enum class VoxelType : uint8_t {
  kUInt8,
  kInt8,
  kUInt16,
  kInt16,
  kUInt32,
  kInt32,
  kFloat32,
  kFloat64
};

// Bytes per voxel of `type`.
size_t VoxelTypeSize(VoxelType type);
// Lower-case name ("uint8", "int16", "float32", ...), used in errors, JSON and file headers.
absl::string_view VoxelTypeName(VoxelType type);

// Largest voxel count any reader will allocate (2^31, i.e. 2 GiB of uint8, 8 GiB of float32).
// A header claiming more is rejected before anything is allocated.
inline constexpr int64_t kMaxVoxels = int64_t{1} << 31;

struct Volume {
  std::array<int64_t, 3> dims{0, 0, 0};
  Eigen::Vector3d spacing{1, 1, 1};  // mm between voxel centres along i, j, k
  Eigen::Vector3d origin{0, 0, 0};   // LPS mm of voxel (0, 0, 0)
  Eigen::Matrix3d direction = Eigen::Matrix3d::Identity();  // column c: LPS unit vector of axis c
  VoxelType type = VoxelType::kFloat32;
  std::vector<uint8_t> bytes;  // voxel values in `type`, native order
  std::string modality;        // "CT", "MR", ... or "" if unknown

  int64_t voxel_count() const { return dims[0] * dims[1] * dims[2]; }
  int64_t Index(int64_t i, int64_t j, int64_t k) const { return i + dims[0] * (j + dims[1] * k); }

  // Index (i, j, k) -> LPS mm. Linear part is direction * diag(spacing).
  Eigen::Affine3d IndexToPhysical() const;
  Eigen::Vector3d PhysicalPoint(double i, double j, double k) const;

  // Value of voxel `linear_index` converted to double. No bounds check beyond assert.
  double ValueAt(int64_t linear_index) const;
  // All voxel values converted to float32 (the working type of segmentation and meshing).
  std::vector<float> ToFloat() const;
  // Smallest and largest value (NaN-free volumes only).
  std::pair<double, double> ValueRange() const;

  // Typed view; T must match `type` (asserted).
  template <typename T>
  const T* data() const {
    return reinterpret_cast<const T*>(bytes.data());
  }
  template <typename T>
  T* mutable_data() {
    return reinterpret_cast<T*>(bytes.data());
  }
};

// Allocates a zero-filled volume with identity geometry. Fails (InvalidArgument) on dims < 1 or
// more than kMaxVoxels voxels.
absl::StatusOr<Volume> MakeVolume(std::array<int64_t, 3> dims, VoxelType type,
                                  Eigen::Vector3d spacing = Eigen::Vector3d::Ones());

// Builds a float32 volume from values (size must equal the voxel count).
absl::StatusOr<Volume> MakeFloatVolume(std::array<int64_t, 3> dims, std::vector<float> values,
                                       Eigen::Vector3d spacing = Eigen::Vector3d::Ones());

// Checks the invariants above plus: floating-point volumes hold no NaN or infinity. `what`
// (e.g. the file name) starts every error message. Returns InvalidArgument naming the field.
absl::Status Validate(const Volume& volume, absl::string_view what);

// True if `a` and `b` share dims and, within `tolerance_mm`, origin, spacing and direction (a
// label map must lie on its image's grid).
bool SameGrid(const Volume& a, const Volume& b, double tolerance_mm = 1e-3);

// Returns "128x128x53 uint16 2x2x2 mm" style summary for logs and errors.
std::string Describe(const Volume& volume);

}  // namespace decima
