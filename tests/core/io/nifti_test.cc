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
using testing::Peek;
using testing::Poke;
using testing::ReadAll;
using testing::WriteAll;

// NIfTI-1 field offsets (nifti1.h) the tests patch.
constexpr size_t kDim = 40, kDatatype = 70, kPixdim = 76, kVoxOffset = 108, kSclSlope = 112,
                 kSclInter = 116, kQformCode = 252, kSformCode = 254, kMagic = 344;

void ExpectSameGeometry(const Volume& a, const Volume& b, double tol) {
  EXPECT_EQ(a.dims, b.dims);
  EXPECT_TRUE(a.spacing.isApprox(b.spacing, tol)) << a.spacing.transpose();
  EXPECT_LT((a.origin - b.origin).norm(), tol * 100) << a.origin.transpose();
  EXPECT_LT((a.direction - b.direction).norm(), tol) << a.direction;
}

// A valid little-endian .nii with a 4x3x2 int16 volume, to be patched by tests.
std::vector<uint8_t> SmallNii(const fs::path& dir, VoxelType type = VoxelType::kInt16) {
  const fs::path p = dir / "small.nii";
  EXPECT_TRUE(WriteNifti(PatternVolume({4, 3, 2}, type), p).ok());
  return ReadAll(p);
}

absl::Status ReadBytesAs(const fs::path& p, const std::vector<uint8_t>& bytes) {
  WriteAll(p, bytes);
  return ReadNifti(p).status();
}

class NiftiRoundTrip : public ::testing::TestWithParam<std::tuple<VoxelType, const char*, bool>> {};

TEST_P(NiftiRoundTrip, KeepsVoxelsExactlyAndGeometryToFloatPrecision) {
  const auto [type, ext, left_handed] = GetParam();
  const fs::path p = decima::testing::MakeScratchDir("nifti") / (std::string("v") + ext);
  const Volume v = PatternVolume({5, 4, 3}, type, left_handed);
  ASSERT_TRUE(WriteNifti(v, p).ok());
  auto r = ReadNifti(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->type, type);
  EXPECT_EQ(r->bytes, v.bytes);
  EXPECT_EQ(r->modality, "");
  ExpectSameGeometry(*r, v, 1e-6);
  EXPECT_LT((r->PhysicalPoint(4, 3, 2) - v.PhysicalPoint(4, 3, 2)).norm(), 1e-4);
}

INSTANTIATE_TEST_SUITE_P(
    AllTypes, NiftiRoundTrip,
    ::testing::Combine(::testing::Values(VoxelType::kUInt8, VoxelType::kInt8, VoxelType::kUInt16,
                                         VoxelType::kInt16, VoxelType::kUInt32, VoxelType::kInt32,
                                         VoxelType::kFloat32, VoxelType::kFloat64),
                       ::testing::Values(".nii", ".nii.gz"), ::testing::Bool()));

TEST(Nifti, WrittenHeaderIsRasWithQformAndSform) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  Volume v = PatternVolume({4, 3, 2}, VoxelType::kUInt8);
  v.direction.setIdentity();
  v.origin = Eigen::Vector3d(10, 20, 30);
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
  const auto b = ReadAll(dir / "a.nii");
  ASSERT_EQ(b.size(), 352u + 24u);
  EXPECT_EQ(Peek<int32_t>(b, 0), 348);
  EXPECT_EQ(Peek<int16_t>(b, kQformCode), 1);
  EXPECT_EQ(Peek<int16_t>(b, kSformCode), 1);
  EXPECT_EQ(Peek<float>(b, kVoxOffset), 352.0f);
  // LPS identity is RAS diag(-1, -1, 1): srow_x = (-0.5, 0, 0, -10).
  EXPECT_FLOAT_EQ(Peek<float>(b, 280), -0.5f);
  EXPECT_FLOAT_EQ(Peek<float>(b, 292), -10.0f);
  EXPECT_FLOAT_EQ(Peek<float>(b, 296 + 4), -1.25f);
  EXPECT_FLOAT_EQ(Peek<float>(b, 296 + 12), -20.0f);
  EXPECT_FLOAT_EQ(Peek<float>(b, 312 + 8), 3.0f);
  EXPECT_FLOAT_EQ(Peek<float>(b, 312 + 12), 30.0f);
  EXPECT_EQ(std::string(reinterpret_cast<const char*>(b.data() + kMagic)), "n+1");
}

TEST(Nifti, QformAloneGivesTheSameGeometryAsSform) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  for (bool left : {false, true}) {
    const Volume v = PatternVolume({4, 3, 2}, VoxelType::kInt16, left);
    ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
    auto b = ReadAll(dir / "a.nii");
    Poke<int16_t>(b, kSformCode, 0);
    WriteAll(dir / "q.nii", b);
    auto r = ReadNifti(dir / "q.nii");
    ASSERT_TRUE(r.ok()) << r.status();
    ExpectSameGeometry(*r, v, 1e-5);
  }
}

TEST(Nifti, NoTransformMeansPixdimOnlyInRas) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  Poke<int16_t>(b, kSformCode, 0);
  Poke<int16_t>(b, kQformCode, 0);
  WriteAll(dir / "n.nii", b);
  auto r = ReadNifti(dir / "n.nii");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->origin.isZero());
  EXPECT_TRUE(r->direction.isApprox(Eigen::Vector3d(-1, -1, 1).asDiagonal().toDenseMatrix()));
  EXPECT_TRUE(r->spacing.isApprox(Eigen::Vector3d(0.5, 1.25, 3.0)));
}

TEST(Nifti, SformWinsOverQform) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  // Replace the sform by a pure translation; the qform still holds the oblique rotation.
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) Poke<float>(b, 280 + 16 * r + 4 * c, r == c ? 2.0f : 0.0f);
    Poke<float>(b, 280 + 16 * r + 12, 5.0f * (r + 1));
  }
  WriteAll(dir / "s.nii", b);
  auto r = ReadNifti(dir / "s.nii");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->direction.isApprox(Eigen::Vector3d(-1, -1, 1).asDiagonal().toDenseMatrix()));
  EXPECT_TRUE(r->origin.isApprox(Eigen::Vector3d(-5, -10, 15)));
  // Spacing stays pixdim's, as specified.
  EXPECT_TRUE(r->spacing.isApprox(Eigen::Vector3d(0.5, 1.25, 3.0)));
}

TEST(Nifti, ShearedSformFallsBackToQform) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kInt16);
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
  auto b = ReadAll(dir / "a.nii");
  Poke<float>(b, 280 + 4, 0.4f);  // shear srow_x[1]
  Poke<float>(b, 280, 0.5f);
  Poke<float>(b, 296 + 4, 1.25f);
  Poke<float>(b, 312 + 8, 3.0f);
  Poke<float>(b, 296, 0.0f);
  WriteAll(dir / "s.nii", b);
  auto r = ReadNifti(dir / "s.nii");
  ASSERT_TRUE(r.ok()) << r.status();
  ExpectSameGeometry(*r, v, 1e-5);
  Poke<int16_t>(b, kQformCode, 0);
  auto s = ReadBytesAs(dir / "s2.nii", b);
  EXPECT_THAT(s.message(), HasSubstr("sform"));
}

TEST(Nifti, SlopeAndInterceptConvertToFloat) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kInt16);
  Poke<float>(b, kSclSlope, 2.0f);
  Poke<float>(b, kSclInter, -1.5f);
  WriteAll(dir / "s.nii", b);
  auto r = ReadNifti(dir / "s.nii");
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->type, VoxelType::kFloat32);
  for (int64_t i = 0; i < v.voxel_count(); ++i) {
    EXPECT_FLOAT_EQ(r->data<float>()[i], v.data<int16_t>()[i] * 2.0f - 1.5f);
  }
  // Slope 0 means "no scaling": the stored type is kept.
  Poke<float>(b, kSclSlope, 0.0f);
  WriteAll(dir / "z.nii", b);
  auto z = ReadNifti(dir / "z.nii");
  ASSERT_TRUE(z.ok()) << z.status();
  EXPECT_EQ(z->type, VoxelType::kInt16);
  EXPECT_EQ(z->bytes, v.bytes);
}

// Byte-swaps the NIfTI-1 header fields that the writer fills, and the int16 data.
TEST(Nifti, ReadsBigEndianFiles) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kInt16);
  auto swap = [&](size_t off, size_t n) { std::reverse(b.begin() + off, b.begin() + off + n); };
  swap(0, 4);
  for (int i = 0; i < 8; ++i) swap(kDim + 2 * i, 2);
  swap(kDatatype, 2);
  swap(72, 2);
  for (int i = 0; i < 8; ++i) swap(kPixdim + 4 * i, 4);
  swap(kVoxOffset, 4);
  swap(kSclSlope, 4);
  swap(kSclInter, 4);
  swap(kQformCode, 2);
  swap(kSformCode, 2);
  for (int i = 0; i < 18; ++i) swap(256 + 4 * i, 4);
  for (size_t i = 352; i < b.size(); i += 2) swap(i, 2);
  WriteAll(dir / "be.nii", b);
  auto r = ReadNifti(dir / "be.nii");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->bytes, v.bytes);
  ExpectSameGeometry(*r, v, 1e-5);
}

// Builds a NIfTI-2 file by hand (nifti2.h layout) and reads it.
TEST(Nifti, ReadsNifti2) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  std::vector<uint8_t> b(544, 0);
  Poke<int32_t>(b, 0, 540);
  std::memcpy(b.data() + 4, "n+2\0\r\n\032\n", 8);
  Poke<int16_t>(b, 12, 16);  // float32
  Poke<int16_t>(b, 14, 32);
  const int64_t dim[8] = {3, 3, 2, 2, 1, 1, 1, 1};
  for (int i = 0; i < 8; ++i) Poke<int64_t>(b, 16 + 8 * i, dim[i]);
  const double pixdim[8] = {1, 0.75, 1.5, 2.5, 1, 1, 1, 1};
  for (int i = 0; i < 8; ++i) Poke<double>(b, 104 + 8 * i, pixdim[i]);
  Poke<int64_t>(b, 168, 544);
  Poke<int32_t>(b, 348, 2);  // sform_code
  // srow: RAS axes i -> +R, j -> +A, k -> +S, origin (1, 2, 3).
  Poke<double>(b, 400, 0.75);
  Poke<double>(b, 424, 1.0);
  Poke<double>(b, 432 + 8, 1.5);
  Poke<double>(b, 432 + 24, 2.0);
  Poke<double>(b, 464 + 16, 2.5);
  Poke<double>(b, 464 + 24, 3.0);
  std::vector<float> values(12);
  for (int i = 0; i < 12; ++i) values[i] = 0.5f * i;
  const auto* vb = reinterpret_cast<const uint8_t*>(values.data());
  b.insert(b.end(), vb, vb + 48);
  WriteAll(dir / "n2.nii", b);
  auto r = ReadNifti(dir / "n2.nii");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->dims, (std::array<int64_t, 3>{3, 2, 2}));
  EXPECT_EQ(r->type, VoxelType::kFloat32);
  EXPECT_FLOAT_EQ(r->data<float>()[11], 5.5f);
  EXPECT_TRUE(r->origin.isApprox(Eigen::Vector3d(-1, -2, 3)));
  EXPECT_TRUE(r->PhysicalPoint(1, 1, 1).isApprox(Eigen::Vector3d(-1.75, -3.5, 5.5)));
  // And gzipped.
  WriteAll(dir / "n2.nii.gz", Compress(b, true));
  auto g = ReadNifti(dir / "n2.nii.gz");
  ASSERT_TRUE(g.ok()) << g.status();
  EXPECT_EQ(g->bytes, r->bytes);
}

TEST(Nifti, ReadsHdrImgPairFromEitherName) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kInt16);
  std::vector<uint8_t> hdr(b.begin(), b.begin() + 348);
  std::memcpy(hdr.data() + kMagic, "ni1\0", 4);
  Poke<float>(hdr, kVoxOffset, 0.0f);
  WriteAll(dir / "pair.hdr", hdr);
  WriteAll(dir / "pair.img", std::vector<uint8_t>(b.begin() + 352, b.end()));
  for (const char* name : {"pair.hdr", "pair.img"}) {
    auto r = ReadNifti(dir / name);
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_EQ(r->bytes, v.bytes);
  }
  fs::remove(dir / "pair.img");
  auto missing = ReadNifti(dir / "pair.hdr");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound) << missing.status();
  EXPECT_THAT(missing.status().message(), HasSubstr("pair.img"));
}

TEST(Nifti, WriterReplacesFilesAtomicallyAndRejectsBadNames) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kUInt8);
  EXPECT_EQ(WriteNifti(v, dir / "a.nrrd").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(WriteNifti(v, dir / "no-such-dir" / "a.nii").ok());
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());  // overwrite
  Volume bad = v;
  bad.bytes.pop_back();
  EXPECT_FALSE(WriteNifti(bad, dir / "a.nii").ok());
  int files = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++files;
  EXPECT_EQ(files, 1) << "temporary files left behind";
  EXPECT_TRUE(ReadNifti(dir / "a.nii").ok());
}

// ---- Broken input: each must fail with a message naming the file and the problem. ----

TEST(NiftiBroken, TruncatedData) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  b.resize(b.size() - 5);
  const fs::path p = dir / "t.nii";
  ExpectError(ReadBytesAs(p, b), p, "truncated");
  // Truncated inside the header, and a truncated .nii.gz.
  b.resize(200);
  ExpectError(ReadBytesAs(p, b), p, "truncated");
  auto full = SmallNii(dir);
  auto gz = Compress(full, true);
  gz.resize(gz.size() / 2);
  const fs::path pg = dir / "t.nii.gz";
  ExpectError(ReadBytesAs(pg, gz), pg, "truncated");
}

TEST(NiftiBroken, GzipCorruption) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  const fs::path p = dir / "c.nii.gz";
  ASSERT_TRUE(WriteNifti(PatternVolume({40, 30, 20}, VoxelType::kFloat32), p).ok());
  auto b = ReadAll(p);
  CorruptMiddle(b, 10);
  WriteAll(p, b);
  auto r = ReadNifti(p);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(r.status().message(), HasSubstr(p.string()));
  EXPECT_THAT(r.status().message(), ::testing::AnyOf(HasSubstr("corrupt"), HasSubstr("truncated"),
                                                     HasSubstr("more data")));
}

TEST(NiftiBroken, DimensionsDoNotMatchDataSize) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  b.insert(b.end(), 24, 0);  // one extra slice
  const fs::path p = dir / "m.nii";
  ExpectError(ReadBytesAs(p, b), p, "do not match");
  const fs::path pg = dir / "m.nii.gz";
  WriteAll(pg, Compress(b, true));
  ExpectError(ReadNifti(pg).status(), pg, "more data than the header implies");
}

TEST(NiftiBroken, TrillionVoxelHeaderFailsFastWithoutAllocating) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  for (int i = 1; i <= 3; ++i) Poke<int16_t>(b, kDim + 2 * i, 10000);
  const fs::path p = dir / "huge.nii";
  // Refused from the header: a reader that allocated the declared voxels (2 GB and more)
  // would run out of this headroom.
  const AddressSpaceCap cap(uint64_t{1} << 30);
  ASSERT_TRUE(cap.active());
  ExpectError(ReadBytesAs(p, b), p, "exceeds the limit");
  // Within the limit but far more than a tiny gzip can hold: rejected before inflating.
  for (int i = 1; i <= 3; ++i) Poke<int16_t>(b, kDim + 2 * i, 1200);
  const fs::path pg = dir / "huge.nii.gz";
  WriteAll(pg, Compress(b, true));
  ExpectError(ReadNifti(pg).status(), pg, "truncated");
}

TEST(NiftiBroken, ZeroOrNonFiniteSpacing) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const fs::path p = dir / "s.nii";
  Poke<float>(b, kPixdim + 8, 0.0f);
  ExpectError(ReadBytesAs(p, b), p, "pixdim[2]");
  Poke<float>(b, kPixdim + 8, std::numeric_limits<float>::quiet_NaN());
  ExpectError(ReadBytesAs(p, b), p, "pixdim[2]");
  // A negative pixdim is a size with a sign: its absolute value is the spacing.
  Poke<float>(b, kPixdim + 8, -1.25f);
  WriteAll(p, b);
  auto r = ReadNifti(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_DOUBLE_EQ(r->spacing[1], 1.25);
}

TEST(NiftiBroken, NanVoxels) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir, VoxelType::kFloat32);
  Poke<float>(b, 352 + 4 * 7, std::numeric_limits<float>::quiet_NaN());
  const fs::path p = dir / "nan.nii";
  ExpectError(ReadBytesAs(p, b), p, "NaN");
}

TEST(NiftiBroken, TwoDimensionalImages) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const fs::path p = dir / "2d.nii";
  Poke<int16_t>(b, kDim, 2);
  ExpectError(ReadBytesAs(p, b), p, "2D image: Decima needs a 3D volume");
  Poke<int16_t>(b, kDim, 3);
  Poke<int16_t>(b, kDim + 6, 1);  // dim[3] = 1
  b.resize(352 + 4 * 3 * 2);
  ExpectError(ReadBytesAs(p, b), p, "2D image: Decima needs a 3D volume (dim[1..3][2] = 1");
}

TEST(NiftiBroken, FourDimensionalSeriesAndUnknownDatatype) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const fs::path p = dir / "x.nii";
  auto four = b;
  Poke<int16_t>(four, kDim, 4);
  Poke<int16_t>(four, kDim + 8, 2);
  EXPECT_EQ(ReadBytesAs(p, four).code(), absl::StatusCode::kUnimplemented);
  auto bad = b;
  Poke<int16_t>(bad, kDatatype, 9999);
  ExpectError(ReadBytesAs(p, bad), p, "unknown datatype code 9999");
  Poke<int16_t>(bad, kDatatype, 128);  // RGB24
  EXPECT_EQ(ReadBytesAs(p, bad).code(), absl::StatusCode::kUnimplemented);
}

TEST(NiftiBroken, BadHeaderFields) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  auto b = SmallNii(dir);
  const fs::path p = dir / "h.nii";
  auto size = b;
  Poke<int32_t>(size, 0, 1234);
  ExpectError(ReadBytesAs(p, size), p, "sizeof_hdr = 1234");
  auto magic = b;
  std::memcpy(magic.data() + kMagic, "xyz\0", 4);
  ExpectError(ReadBytesAs(p, magic), p, "magic");
  auto off = b;
  Poke<float>(off, kVoxOffset, 100.0f);
  ExpectError(ReadBytesAs(p, off), p, "vox_offset");
  Poke<float>(off, kVoxOffset, -4.0f);
  ExpectError(ReadBytesAs(p, off), p, "vox_offset");
  Poke<float>(off, kVoxOffset, 1e9f);
  ExpectError(ReadBytesAs(p, off), p, "truncated");
  auto dim0 = b;
  Poke<int16_t>(dim0, kDim, 9);
  ExpectError(ReadBytesAs(p, dim0), p, "dim[0] = 9");
  auto neg = b;
  Poke<int16_t>(neg, kDim + 4, -3);
  ExpectError(ReadBytesAs(p, neg), p, "dim[1..3][1] = -3");
}

TEST(NiftiBroken, EmptyAndMissingFiles) {
  const fs::path dir = decima::testing::MakeScratchDir("nifti");
  const fs::path p = dir / "empty.nii";
  ExpectError(ReadBytesAs(p, {}), p, "empty");
  const fs::path gz = dir / "empty.nii.gz";
  ExpectError(ReadBytesAs(gz, {}), gz, "empty");
  auto r = ReadNifti(dir / "missing.nii");
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(r.status().message(), HasSubstr("missing.nii"));
  EXPECT_FALSE(ReadNifti(dir).ok());
}

// ---- Real data (skipped when ../shared/data is absent). ----

TEST(NiftiRealData, CtHead128x128x53) {
  DECIMA_REQUIRE_SHARED_DATA(p, "ct-head-128x128x53.nii.gz");
  auto r = ReadNifti(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->dims, (std::array<int64_t, 3>{128, 128, 53}));
  EXPECT_EQ(r->type, VoxelType::kUInt16);
  EXPECT_TRUE(r->spacing.isApprox(Eigen::Vector3d(2, 2, 2)));
  const auto [lo, hi] = r->ValueRange();
  EXPECT_EQ(lo, 0);
  EXPECT_EQ(hi, 3272);
}

TEST(NiftiRealData, CtHead256AffineMatchesManifest) {
  DECIMA_REQUIRE_SHARED_DATA(p, "ct-head-256x256x113.nii.gz");
  auto r = ReadNifti(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->dims, (std::array<int64_t, 3>{256, 256, 113}));
  EXPECT_TRUE(r->spacing.isApprox(Eigen::Vector3d(1, 1, 2)));
  // MANIFEST: voxel (i, j, k) at LPS (-127.5 + i, -127.5 + j, 224 - 2k) mm.
  for (const auto& ijk :
       {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(255, 0, 112), Eigen::Vector3d(17, 200, 50)}) {
    const Eigen::Vector3d want(-127.5 + ijk.x(), -127.5 + ijk.y(), 224 - 2 * ijk.z());
    EXPECT_LT((r->PhysicalPoint(ijk.x(), ijk.y(), ijk.z()) - want).norm(), 1e-4) << ijk;
  }
}

}  // namespace
}  // namespace decima::io
