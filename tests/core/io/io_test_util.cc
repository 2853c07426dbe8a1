#include "tests/core/io/io_test_util.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <zlib.h>

#include <cmath>
#include <fstream>
#include <iterator>
#include <stdexcept>

#include <Eigen/Geometry>

namespace decima::io::testing {

void ExpectError(const absl::Status& s, const std::filesystem::path& p, const std::string& what) {
  ASSERT_FALSE(s.ok()) << "expected an error about " << what;
  EXPECT_THAT(std::string(s.message()), ::testing::HasSubstr(p.string()));
  EXPECT_THAT(std::string(s.message()), ::testing::HasSubstr(what));
}

namespace {
template <typename T>
void Fill(Volume& v, double scale, double offset) {
  T* p = v.mutable_data<T>();
  for (int64_t i = 0; i < v.voxel_count(); ++i) {
    p[i] = static_cast<T>(std::fmod(static_cast<double>(i) * scale, 120.0) + offset);
  }
}
}  // namespace

Volume PatternVolume(std::array<int64_t, 3> dims, VoxelType type, bool left_handed) {
  Volume v = MakeVolume(dims, type).value();
  v.spacing = Eigen::Vector3d(0.5, 1.25, 3.0);
  v.origin = Eigen::Vector3d(-12.5, 40.25, 7.0);
  v.direction = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  if (left_handed) v.direction.col(2) *= -1;
  switch (type) {
    case VoxelType::kUInt8:
      Fill<uint8_t>(v, 7, 0);
      break;
    case VoxelType::kInt8:
      Fill<int8_t>(v, 7, -60);
      break;
    case VoxelType::kUInt16:
      Fill<uint16_t>(v, 7, 1000);
      break;
    case VoxelType::kInt16:
      Fill<int16_t>(v, 7, -1000);
      break;
    case VoxelType::kUInt32:
      Fill<uint32_t>(v, 7, 100000);
      break;
    case VoxelType::kInt32:
      Fill<int32_t>(v, 7, -100000);
      break;
    case VoxelType::kFloat32:
      Fill<float>(v, 0.37, -3.25);
      break;
    case VoxelType::kFloat64:
      Fill<double>(v, 0.37, -3.25);
      break;
  }
  return v;
}

std::vector<uint8_t> ReadAll(const std::filesystem::path& path) {
  std::ifstream f(path, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(f), {});
}

void WriteAll(const std::filesystem::path& path, const std::vector<uint8_t>& bytes) {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
}

void WriteText(const std::filesystem::path& path, const std::string& text) {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f << text;
}

std::vector<uint8_t> Compress(const std::vector<uint8_t>& bytes, bool gzip) {
  z_stream zs{};
  deflateInit2(&zs, 6, Z_DEFLATED, gzip ? 31 : 15, 8, Z_DEFAULT_STRATEGY);
  std::vector<uint8_t> out(deflateBound(&zs, bytes.size()) + 32);
  zs.next_in = const_cast<Bytef*>(bytes.data());
  zs.avail_in = static_cast<uInt>(bytes.size());
  zs.next_out = out.data();
  zs.avail_out = static_cast<uInt>(out.size());
  if (deflate(&zs, Z_FINISH) != Z_STREAM_END) throw std::runtime_error("deflate");
  out.resize(zs.total_out);
  deflateEnd(&zs);
  return out;
}

void CorruptMiddle(std::vector<uint8_t>& bytes, size_t begin, size_t count) {
  const size_t mid = begin + (bytes.size() - begin) / 2;
  for (size_t i = mid; i < mid + count && i < bytes.size(); ++i) bytes[i] ^= 0xff;
}

}  // namespace decima::io::testing
