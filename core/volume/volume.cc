#include "core/volume/volume.h"

#include <cassert>
#include <cmath>
#include <cstring>
#include <limits>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace decima {
namespace {

// Calls fn(const T* values) with the voxel buffer cast to its source type.
template <typename Fn>
auto VisitTyped(const Volume& v, Fn&& fn) {
  switch (v.type) {
    case VoxelType::kUInt8:
      return fn(v.data<uint8_t>());
    case VoxelType::kInt8:
      return fn(v.data<int8_t>());
    case VoxelType::kUInt16:
      return fn(v.data<uint16_t>());
    case VoxelType::kInt16:
      return fn(v.data<int16_t>());
    case VoxelType::kUInt32:
      return fn(v.data<uint32_t>());
    case VoxelType::kInt32:
      return fn(v.data<int32_t>());
    case VoxelType::kFloat32:
      return fn(v.data<float>());
    case VoxelType::kFloat64:
      return fn(v.data<double>());
  }
  return fn(v.data<uint8_t>());
}

bool IsFloating(VoxelType t) { return t == VoxelType::kFloat32 || t == VoxelType::kFloat64; }

}  // namespace

size_t VoxelTypeSize(VoxelType type) {
  switch (type) {
    case VoxelType::kUInt8:
    case VoxelType::kInt8:
      return 1;
    case VoxelType::kUInt16:
    case VoxelType::kInt16:
      return 2;
    case VoxelType::kUInt32:
    case VoxelType::kInt32:
    case VoxelType::kFloat32:
      return 4;
    case VoxelType::kFloat64:
      return 8;
  }
  return 1;
}

absl::string_view VoxelTypeName(VoxelType type) {
  switch (type) {
    case VoxelType::kUInt8:
      return "uint8";
    case VoxelType::kInt8:
      return "int8";
    case VoxelType::kUInt16:
      return "uint16";
    case VoxelType::kInt16:
      return "int16";
    case VoxelType::kUInt32:
      return "uint32";
    case VoxelType::kInt32:
      return "int32";
    case VoxelType::kFloat32:
      return "float32";
    case VoxelType::kFloat64:
      return "float64";
  }
  return "unknown";
}

Eigen::Affine3d Volume::IndexToPhysical() const {
  Eigen::Affine3d t = Eigen::Affine3d::Identity();
  t.linear() = direction * spacing.asDiagonal();
  t.translation() = origin;
  return t;
}

Eigen::Vector3d Volume::PhysicalPoint(double i, double j, double k) const {
  return origin + direction * (spacing.cwiseProduct(Eigen::Vector3d(i, j, k)));
}

double Volume::ValueAt(int64_t linear_index) const {
  assert(linear_index >= 0 && linear_index < voxel_count());
  return VisitTyped(*this, [&](const auto* p) { return static_cast<double>(p[linear_index]); });
}

std::vector<float> Volume::ToFloat() const {
  const int64_t n = voxel_count();
  std::vector<float> out(static_cast<size_t>(n));
  VisitTyped(*this, [&](const auto* p) {
    for (int64_t i = 0; i < n; ++i) out[i] = static_cast<float>(p[i]);
  });
  return out;
}

std::pair<double, double> Volume::ValueRange() const {
  const int64_t n = voxel_count();
  if (n == 0) return {0.0, 0.0};
  return VisitTyped(*this, [&](const auto* p) {
    auto lo = p[0], hi = p[0];
    for (int64_t i = 1; i < n; ++i) {
      lo = p[i] < lo ? p[i] : lo;
      hi = p[i] > hi ? p[i] : hi;
    }
    return std::pair<double, double>(static_cast<double>(lo), static_cast<double>(hi));
  });
}

absl::StatusOr<Volume> MakeVolume(std::array<int64_t, 3> dims, VoxelType type,
                                  Eigen::Vector3d spacing) {
  for (int c = 0; c < 3; ++c) {
    if (dims[c] < 1) {
      return absl::InvalidArgumentError(
          absl::StrCat("volume: dims[", c, "] = ", dims[c], " must be >= 1"));
    }
  }
  if (dims[0] > kMaxVoxels / dims[1] || dims[0] * dims[1] > kMaxVoxels / dims[2]) {
    return absl::InvalidArgumentError(absl::StrCat("volume: ", dims[0], "x", dims[1], "x", dims[2],
                                                   " exceeds the limit of ", kMaxVoxels,
                                                   " voxels"));
  }
  Volume v;
  v.dims = dims;
  v.type = type;
  v.spacing = spacing;
  v.bytes.assign(static_cast<size_t>(v.voxel_count()) * VoxelTypeSize(type), 0);
  return v;
}

absl::StatusOr<Volume> MakeFloatVolume(std::array<int64_t, 3> dims, std::vector<float> values,
                                       Eigen::Vector3d spacing) {
  auto v = MakeVolume(dims, VoxelType::kFloat32, spacing);
  if (!v.ok()) return v.status();
  if (static_cast<int64_t>(values.size()) != v->voxel_count()) {
    return absl::InvalidArgumentError(
        absl::StrCat("volume: ", values.size(), " values for ", v->voxel_count(), " voxels"));
  }
  std::memcpy(v->bytes.data(), values.data(), values.size() * sizeof(float));
  return v;
}

absl::Status Validate(const Volume& v, absl::string_view what) {
  for (int c = 0; c < 3; ++c) {
    if (v.dims[c] < 1) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": dimension ", c, " is ", v.dims[c], ", expected >= 1"));
    }
  }
  if (v.dims[0] > kMaxVoxels / v.dims[1] || v.dims[0] * v.dims[1] > kMaxVoxels / v.dims[2]) {
    return absl::InvalidArgumentError(absl::StrCat(what, ": ", v.dims[0], "x", v.dims[1], "x",
                                                   v.dims[2], " voxels exceeds the limit of ",
                                                   kMaxVoxels));
  }
  const size_t expected = static_cast<size_t>(v.voxel_count()) * VoxelTypeSize(v.type);
  if (v.bytes.size() != expected) {
    return absl::InvalidArgumentError(absl::StrCat(what, ": voxel data has ", v.bytes.size(),
                                                   " bytes, header implies ", expected));
  }
  for (int c = 0; c < 3; ++c) {
    if (!std::isfinite(v.spacing[c]) || v.spacing[c] <= 0) {
      return absl::InvalidArgumentError(absl::StrCat(what, ": spacing[", c, "] = ", v.spacing[c],
                                                     " mm, expected a finite value > 0"));
    }
    if (!std::isfinite(v.origin[c])) {
      return absl::InvalidArgumentError(absl::StrCat(what, ": origin[", c, "] is not finite"));
    }
  }
  const Eigen::Matrix3d gram = v.direction.transpose() * v.direction;
  if (!gram.allFinite() || !gram.isIdentity(1e-3)) {
    return absl::InvalidArgumentError(absl::StrCat(
        what, ": direction matrix is not orthonormal (columns must be unit and orthogonal)"));
  }
  if (IsFloating(v.type)) {
    const int64_t n = v.voxel_count();
    bool finite = VisitTyped(v, [&](const auto* p) {
      for (int64_t i = 0; i < n; ++i) {
        if (!std::isfinite(static_cast<double>(p[i]))) return false;
      }
      return true;
    });
    if (!finite) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": voxel values contain NaN or infinity"));
    }
  }
  return absl::OkStatus();
}

bool SameGrid(const Volume& a, const Volume& b, double tolerance_mm) {
  if (a.dims != b.dims) return false;
  if ((a.origin - b.origin).cwiseAbs().maxCoeff() > tolerance_mm) return false;
  if ((a.spacing - b.spacing).cwiseAbs().maxCoeff() > tolerance_mm) return false;
  return (a.direction - b.direction).cwiseAbs().maxCoeff() <= 1e-3;
}

std::string Describe(const Volume& v) {
  return absl::StrFormat("%dx%dx%d %s %gx%gx%g mm", v.dims[0], v.dims[1], v.dims[2],
                         VoxelTypeName(v.type), v.spacing[0], v.spacing[1], v.spacing[2]);
}

}  // namespace decima
