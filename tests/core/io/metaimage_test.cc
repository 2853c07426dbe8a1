#include <cmath>
#include <limits>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "core/io/volume_io.h"
#include "tests/core/io/io_test_util.h"
#include "tests/testing/test_data.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;
using testing::AddressSpaceCap;
using testing::Compress;
using testing::CorruptMiddle;
using testing::ExpectError;
using ::testing::HasSubstr;
using testing::PatternVolume;
using testing::ReadAll;
using testing::WriteAll;
using testing::WriteText;

std::vector<uint8_t> Bytes(const std::string& s) { return {s.begin(), s.end()}; }

// A 3x2x2 int16 MetaImage header (little-endian) for hand-made files.
std::string Header(const std::string& data_file, const std::string& extra = "",
                   const std::string& dims = "3 2 2", const std::string& type = "MET_SHORT") {
  return "ObjectType = Image\nNDims = 3\nBinaryData = True\n" + extra + "DimSize = " + dims +
         "\nElementType = " + type + "\nElementDataFile = " + data_file + "\n";
}

std::vector<uint8_t> ShortData(int n = 12) {
  std::vector<uint8_t> b;
  for (int i = 0; i < n; ++i) {
    const int16_t v = static_cast<int16_t>(i * 100 - 300);
    b.push_back(static_cast<uint8_t>(v & 0xff));
    b.push_back(static_cast<uint8_t>((v >> 8) & 0xff));
  }
  return b;
}

class MetaImageRoundTrip
    : public ::testing::TestWithParam<std::tuple<VoxelType, const char*, bool>> {};

TEST_P(MetaImageRoundTrip, KeepsVoxelsAndGeometryExactly) {
  const auto [type, ext, compress] = GetParam();
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  const fs::path p = dir / (std::string("v") + ext);
  Volume v = PatternVolume({5, 4, 3}, type, /*left_handed=*/compress);
  v.modality = "CT";
  ASSERT_TRUE(WriteMetaImage(v, p, {.compress = compress}).ok());
  auto r = ReadMetaImage(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->type, type);
  EXPECT_EQ(r->bytes, v.bytes);
  EXPECT_EQ(r->dims, v.dims);
  // Shortest round-trip decimal form: geometry comes back bit-identical.
  EXPECT_EQ(r->spacing, v.spacing);
  EXPECT_EQ(r->origin, v.origin);
  EXPECT_LT((r->direction - v.direction).norm(), 1e-15);
  EXPECT_EQ(r->modality, "CT");
  if (std::string(ext) == ".mhd") {
    EXPECT_TRUE(fs::exists(dir / (compress ? "v.zraw" : "v.raw")));
  }
  int files = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++files;
  EXPECT_EQ(files, std::string(ext) == ".mhd" ? 2 : 1) << "temporary files left behind";
}

INSTANTIATE_TEST_SUITE_P(
    AllTypes, MetaImageRoundTrip,
    ::testing::Combine(::testing::Values(VoxelType::kUInt8, VoxelType::kInt8, VoxelType::kUInt16,
                                         VoxelType::kInt16, VoxelType::kUInt32, VoxelType::kInt32,
                                         VoxelType::kFloat32, VoxelType::kFloat64),
                       ::testing::Values(".mha", ".mhd"), ::testing::Bool()));

TEST(MetaImage, TransformMatrixIsWrittenAxisByAxisAsItkDoes) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  // Axis i along +y, axis j along -x, axis k along +z (LPS).
  const std::string text = Header("LOCAL",
                                  "TransformMatrix = 0 1 0 -1 0 0 0 0 1\n"
                                  "Offset = 1 2 3\nElementSpacing = 0.5 2 4\n");
  auto bytes = Bytes(text);
  const auto data = ShortData();
  bytes.insert(bytes.end(), data.begin(), data.end());
  WriteAll(dir / "t.mha", bytes);
  auto r = ReadMetaImage(dir / "t.mha");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->direction.col(0).isApprox(Eigen::Vector3d(0, 1, 0)));
  EXPECT_TRUE(r->direction.col(1).isApprox(Eigen::Vector3d(-1, 0, 0)));
  EXPECT_TRUE(r->PhysicalPoint(1, 1, 1).isApprox(Eigen::Vector3d(1 - 2, 2 + 0.5, 3 + 4)));
  EXPECT_EQ(r->data<int16_t>()[11], 800);
  // Writing it back produces the same TransformMatrix line.
  ASSERT_TRUE(WriteMetaImage(*r, dir / "w.mha", {.compress = false}).ok());
  const auto w = ReadAll(dir / "w.mha");
  EXPECT_THAT(std::string(w.begin(), w.end()), HasSubstr("TransformMatrix = 0 1 0 -1 0 0 0 0 1\n"));
}

TEST(MetaImage, ReadsBigEndianHeaderSizeAndDataAtEnd) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  auto be = ShortData();
  for (size_t i = 0; i < be.size(); i += 2) std::swap(be[i], be[i + 1]);
  std::vector<uint8_t> raw(7, 0xAB);  // 7 bytes of junk before the data
  raw.insert(raw.end(), be.begin(), be.end());
  WriteAll(dir / "d.raw", raw);
  WriteText(dir / "a.mhd", Header("d.raw", "ElementByteOrderMSB = True\nHeaderSize = 7\n"));
  WriteText(dir / "b.mhd", Header("d.raw", "ElementByteOrderMSB = True\nHeaderSize = -1\n"));
  for (const char* name : {"a.mhd", "b.mhd"}) {
    auto r = ReadMetaImage(dir / name);
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_EQ(r->data<int16_t>()[0], -300);
    EXPECT_EQ(r->data<int16_t>()[11], 800);
  }
}

TEST(MetaImageBroken, TruncatedData) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  auto b = Bytes(Header("LOCAL"));
  auto d = ShortData();
  b.insert(b.end(), d.begin(), d.end() - 3);
  const fs::path p = dir / "t.mha";
  WriteAll(p, b);
  ExpectError(ReadMetaImage(p).status(), p, "truncated");
  // A header without its ElementDataFile line.
  WriteText(p, "ObjectType = Image\nNDims = 3\n");
  ExpectError(ReadMetaImage(p).status(), p, "ElementDataFile");
}

TEST(MetaImageBroken, ZrawCorruption) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  const fs::path p = dir / "c.mhd";
  ASSERT_TRUE(WriteMetaImage(PatternVolume({40, 30, 20}, VoxelType::kFloat32), p).ok());
  auto z = ReadAll(dir / "c.zraw");
  CorruptMiddle(z, 2);
  WriteAll(dir / "c.zraw", z);
  auto r = ReadMetaImage(p);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(r.status().message(), HasSubstr("c.zraw"));
  EXPECT_THAT(r.status().message(), ::testing::AnyOf(HasSubstr("corrupt"), HasSubstr("truncated"),
                                                     HasSubstr("more data")));
  // Cut short.
  z = ReadAll(dir / "c.zraw");
  z.resize(z.size() / 3);
  WriteAll(dir / "c.zraw", z);
  ExpectError(ReadMetaImage(p).status(), dir / "c.zraw", "truncated");
}

TEST(MetaImageBroken, DimensionsDoNotMatchDataSize) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  WriteAll(dir / "d.raw", ShortData(14));
  const fs::path p = dir / "m.mhd";
  WriteText(p, Header("d.raw"));
  ExpectError(ReadMetaImage(p).status(), dir / "d.raw", "do not match");
  WriteAll(dir / "d.zraw", Compress(ShortData(14), false));
  WriteText(p, Header("d.zraw", "CompressedData = True\n"));
  ExpectError(ReadMetaImage(p).status(), dir / "d.zraw", "more data than the header implies");
}

TEST(MetaImageBroken, TrillionVoxelHeaderFailsFast) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  const fs::path p = dir / "huge.mha";
  // Refused from the header: a reader that allocated the declared voxels (2 GB and more)
  // would run out of this headroom.
  const AddressSpaceCap cap(uint64_t{1} << 30);
  ASSERT_TRUE(cap.active());
  WriteText(p, Header("LOCAL", "", "10000 10000 10000") + "xx");
  ExpectError(ReadMetaImage(p).status(), p, "exceeds the limit");
  WriteText(p, Header("LOCAL", "CompressedData = True\n", "1000 1000 1000") + "xx");
  ExpectError(ReadMetaImage(p).status(), p, "truncated");
}

TEST(MetaImageBroken, ZeroOrNegativeSpacing) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  WriteAll(dir / "d.raw", ShortData());
  const fs::path p = dir / "s.mhd";
  WriteText(p, Header("d.raw", "ElementSpacing = 1 0 1\n"));
  ExpectError(ReadMetaImage(p).status(), p, "ElementSpacing[1] = 0");
  WriteText(p, Header("d.raw", "ElementSpacing = 1 1 -2\n"));
  ExpectError(ReadMetaImage(p).status(), p, "ElementSpacing[2] = -2");
  WriteText(p, Header("d.raw", "ElementSpacing = 1 nan 1\n"));
  ExpectError(ReadMetaImage(p).status(), p, "ElementSpacing[1]");
}

TEST(MetaImageBroken, NanVoxels) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  std::vector<float> f(12, 1.0f);
  f[5] = std::numeric_limits<float>::quiet_NaN();
  std::vector<uint8_t> d(reinterpret_cast<uint8_t*>(f.data()),
                         reinterpret_cast<uint8_t*>(f.data()) + 48);
  WriteAll(dir / "d.raw", d);
  const fs::path p = dir / "n.mhd";
  WriteText(p, Header("d.raw", "", "3 2 2", "MET_FLOAT"));
  ExpectError(ReadMetaImage(p).status(), p, "NaN");
}

TEST(MetaImageBroken, TwoDimensionalImagesAndUnsupportedLayouts) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  WriteAll(dir / "d.raw", ShortData());
  const fs::path p = dir / "x.mhd";
  WriteText(p, "NDims = 2\nDimSize = 6 2\nElementType = MET_SHORT\nElementDataFile = d.raw\n");
  ExpectError(ReadMetaImage(p).status(), p, "2D image: Decima needs a 3D volume");
  WriteText(p, Header("d.raw", "", "6 2 1"));
  ExpectError(ReadMetaImage(p).status(), p, "2D image: Decima needs a 3D volume (DimSize[2] = 1");
  WriteText(p, Header("d.raw", "ElementNumberOfChannels = 3\n"));
  EXPECT_EQ(ReadMetaImage(p).status().code(), absl::StatusCode::kUnimplemented);
  WriteText(p, Header("d.raw", "", "3 2 2", "MET_LONG_LONG"));
  ExpectError(ReadMetaImage(p).status(), p, "ElementType 'MET_LONG_LONG'");
  WriteText(p, Header("d.raw", "", "3 2 2", "MET_BOGUS"));
  ExpectError(ReadMetaImage(p).status(), p, "unknown or unsupported ElementType");
  WriteText(p, Header("d.raw", "TransformMatrix = 1 0 0 0 1 0\n"));
  ExpectError(ReadMetaImage(p).status(), p, "TransformMatrix has 6 values, expected 9");
  WriteText(p, Header("d.raw", "TransformMatrix = 1 0 0 0.7 0.7 0 0 0 1\n"));
  ExpectError(ReadMetaImage(p).status(), p, "direction matrix is not orthonormal");
}

TEST(MetaImageBroken, MissingOrEscapingDataFile) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  const fs::path p = dir / "x.mhd";
  WriteText(p, Header("gone.raw"));
  auto r = ReadMetaImage(p);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(r.status().message(), HasSubstr("gone.raw"));
  WriteText(p, Header("../secret.raw"));
  ExpectError(ReadMetaImage(p).status(), p, "leaves the header's folder");
  WriteText(p, Header("/etc/passwd"));
  ExpectError(ReadMetaImage(p).status(), p, "absolute path");
}

TEST(MetaImageBroken, EmptyMissingAndGarbageFiles) {
  const fs::path dir = decima::testing::MakeScratchDir("mha");
  const fs::path p = dir / "e.mha";
  WriteText(p, "");
  ExpectError(ReadMetaImage(p).status(), p, "empty");
  WriteText(p, "\x01\x02\x03 binary junk\n");
  ExpectError(ReadMetaImage(p).status(), p, "not a MetaImage header");
  EXPECT_EQ(ReadMetaImage(dir / "none.mha").status().code(), absl::StatusCode::kNotFound);
}

TEST(MetaImageRealData, HeadNeckZrawMatchesTheNiftiCopy) {
  DECIMA_REQUIRE_SHARED_DATA(mhd, "ct-headneck-64x64x93.mhd");
  DECIMA_REQUIRE_SHARED_DATA(nii, "ct-headneck-64x64x93.nii.gz");
  auto m = ReadMetaImage(mhd);
  ASSERT_TRUE(m.ok()) << m.status();
  auto n = ReadNifti(nii);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(m->dims, (std::array<int64_t, 3>{64, 64, 93}));
  EXPECT_EQ(m->type, VoxelType::kInt16);
  EXPECT_EQ(n->type, VoxelType::kInt16);
  EXPECT_TRUE(m->spacing.isApprox(Eigen::Vector3d(3.2, 3.2, 1.5)));
  EXPECT_TRUE(n->spacing.isApprox(Eigen::Vector3d(3.2, 3.2, 1.5), 1e-6));
  EXPECT_EQ(m->bytes, n->bytes);
  EXPECT_TRUE(SameGrid(*m, *n)) << Describe(*m) << " vs " << Describe(*n);
  const auto [lo, hi] = m->ValueRange();
  EXPECT_EQ(lo, 0);
  EXPECT_EQ(hi, 3926);
}

}  // namespace
}  // namespace decima::io
