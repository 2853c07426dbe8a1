// Test-only NIfTI-1 (.nii.gz) loader for the real-data tests and the figures program of
// core/segment, until core/io lands. Not a product reader: it trusts well-formed files of the
// shared data folder (little endian, uint8/int16/uint16/float32) and checks sizes before
// allocating, nothing more.
#pragma once

#include <zlib.h>

#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "core/volume/volume.h"

namespace decima::testing {

inline absl::StatusOr<Volume> LoadNiftiForTest(const std::filesystem::path& path) {
  gzFile f = gzopen(path.c_str(), "rb");
  if (f == nullptr) return absl::NotFoundError(absl::StrCat("cannot open ", path.string()));
  std::vector<uint8_t> data;
  uint8_t buf[1 << 16];
  int got;
  while ((got = gzread(f, buf, sizeof(buf))) > 0) data.insert(data.end(), buf, buf + got);
  gzclose(f);
  if (data.size() < 352) return absl::InvalidArgumentError(path.string() + ": too short");
  auto i16 = [&](size_t off) {
    int16_t v;
    std::memcpy(&v, &data[off], 2);
    return v;
  };
  auto f32 = [&](size_t off) {
    float v;
    std::memcpy(&v, &data[off], 4);
    return v;
  };
  int32_t sizeof_hdr;
  std::memcpy(&sizeof_hdr, data.data(), 4);
  if (sizeof_hdr != 348) return absl::InvalidArgumentError(path.string() + ": not NIfTI-1 LE");
  std::array<int64_t, 3> dims{};
  for (int c = 0; c < 3; ++c) dims[c] = std::max<int16_t>(1, i16(42 + 2 * c));
  VoxelType type;
  switch (i16(70)) {
    case 2: type = VoxelType::kUInt8; break;
    case 4: type = VoxelType::kInt16; break;
    case 512: type = VoxelType::kUInt16; break;
    case 16: type = VoxelType::kFloat32; break;
    default: return absl::InvalidArgumentError(path.string() + ": unsupported datatype");
  }
  const Eigen::Vector3d spacing(std::abs(f32(80)), std::abs(f32(84)), std::abs(f32(88)));
  auto v = MakeVolume(dims, type, spacing);
  if (!v.ok()) return v.status();
  const size_t offset = static_cast<size_t>(f32(108));
  if (offset < 348 || offset + v->bytes.size() > data.size()) {
    return absl::InvalidArgumentError(path.string() + ": truncated voxel data");
  }
  std::memcpy(v->bytes.data(), data.data() + offset, v->bytes.size());
  if (i16(254) > 0) {  // sform: RAS rows -> LPS
    Eigen::Matrix3d m;
    Eigen::Vector3d t;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) m(r, c) = f32(280 + 16 * r + 4 * c);
      t[r] = f32(280 + 16 * r + 12);
    }
    for (int r = 0; r < 2; ++r) {
      m.row(r) *= -1;
      t[r] *= -1;
    }
    for (int c = 0; c < 3; ++c) m.col(c) /= m.col(c).norm();
    v->direction = m;
    v->origin = t;
  }
  v->modality = "OT";
  return v;
}

}  // namespace decima::testing
