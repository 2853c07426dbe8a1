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
using testing::WriteAll;
using testing::WriteText;

// 12 int16 values -300, -200, ..., 800 in the given byte order.
std::vector<uint8_t> ShortData(bool big_endian = false, int n = 12) {
  std::vector<uint8_t> b;
  for (int i = 0; i < n; ++i) {
    const auto v = static_cast<uint16_t>(static_cast<int16_t>(i * 100 - 300));
    const uint8_t lo = v & 0xff, hi = v >> 8;
    b.push_back(big_endian ? hi : lo);
    b.push_back(big_endian ? lo : hi);
  }
  return b;
}

std::string Header(const std::string& extra, const std::string& sizes = "3 2 2",
                   const std::string& encoding = "raw", const std::string& dimension = "3") {
  return "NRRD0004\n# a comment\ntype: short\ndimension: " + dimension + "\nsizes: " + sizes +
         "\nendian: little\nencoding: " + encoding + "\n" + extra;
}

// Attached .nrrd: header, blank line, data.
void WriteAttached(const fs::path& p, const std::string& header, const std::vector<uint8_t>& d) {
  std::vector<uint8_t> b(header.begin(), header.end());
  b.push_back('\n');
  b.insert(b.end(), d.begin(), d.end());
  WriteAll(p, b);
}

TEST(Nrrd, ReadsAttachedRawWithSpaceDirectionsInRas) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "a.nrrd";
  WriteAttached(p,
                Header("space: right-anterior-superior\n"
                       "space directions: (0,2,0) (-0.5, 0, 0) (0,0,3)\n"
                       "space origin: (10,20,30)\nkinds: domain domain domain\n"
                       "Units:=mm\n"),
                ShortData());
  auto r = ReadNrrd(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->dims, (std::array<int64_t, 3>{3, 2, 2}));
  EXPECT_EQ(r->type, VoxelType::kInt16);
  EXPECT_TRUE(r->spacing.isApprox(Eigen::Vector3d(2, 0.5, 3)));
  EXPECT_TRUE(r->origin.isApprox(Eigen::Vector3d(-10, -20, 30)));
  // RAS (0,2,0) per i is LPS (0,-2,0); RAS (-0.5,0,0) per j is LPS (+0.5,0,0).
  EXPECT_TRUE(r->PhysicalPoint(1, 1, 1).isApprox(Eigen::Vector3d(-10 + 0.5, -20 - 2, 33)));
  EXPECT_EQ(r->data<int16_t>()[11], 800);
}

TEST(Nrrd, ReadsDetachedGzipBigEndianWithSkips) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  // line skip applies to the file, byte skip to the inflated data.
  std::vector<uint8_t> inflated(5, 0xEE);
  const auto d = ShortData(/*big_endian=*/true);
  inflated.insert(inflated.end(), d.begin(), d.end());
  const auto z = Compress(inflated, true);
  std::string prefix = "skip me\nand me\n";
  std::vector<uint8_t> file(prefix.begin(), prefix.end());
  file.insert(file.end(), z.begin(), z.end());
  WriteAll(dir / "d.raw.gz", file);
  std::string h = Header("data file: d.raw.gz\nline skip: 2\nbyte skip: 5\nspacings: 1.5 2 2.5\n",
                         "3 2 2", "gzip");
  h.replace(h.find("endian: little"), 14, "endian: big");
  WriteText(dir / "a.nhdr", h);
  auto r = ReadNrrd(dir / "a.nhdr");
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->data<int16_t>()[0], -300);
  EXPECT_EQ(r->data<int16_t>()[11], 800);
  EXPECT_TRUE(r->spacing.isApprox(Eigen::Vector3d(1.5, 2, 2.5)));
  EXPECT_TRUE(r->direction.isIdentity());
}

TEST(Nrrd, ReadsAsciiAndByteSkipMinusOne) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "a.nrrd";
  WriteText(
      p, Header("", "3 2 2", "ascii") + "\n-300 -200 -100\n0 100 200\n300 400 500\n600 700 800\n");
  auto r = ReadNrrd(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->data<int16_t>()[11], 800);
  WriteText(p, Header("", "3 2 2", "ascii") + "\n1 2 3 70000 5 6 7 8 9 10 11 12\n");
  ExpectError(ReadNrrd(p).status(), p, "does not fit");

  std::vector<uint8_t> junk(9, 0x55);
  const auto d = ShortData();
  junk.insert(junk.end(), d.begin(), d.end());
  WriteAll(dir / "d.raw", junk);
  WriteText(dir / "b.nhdr", Header("data file: d.raw\nbyte skip: -1\n"));
  auto b = ReadNrrd(dir / "b.nhdr");
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(b->data<int16_t>()[0], -300);
}

TEST(Nrrd, AcceptsASizeOneLeadingAxisButNotVectors) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "a.nrrd";
  WriteAttached(p,
                Header("space: left-posterior-superior\n"
                       "space directions: none (1,0,0) (0,1,0) (0,0,1)\n"
                       "kinds: scalar domain domain domain\n",
                       "1 3 2 2", "raw", "4"),
                ShortData());
  auto r = ReadNrrd(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->dims, (std::array<int64_t, 3>{3, 2, 2}));
  WriteAttached(p, Header("kinds: vector domain domain domain\n", "3 2 2 2", "raw", "4"),
                ShortData(false, 24));
  EXPECT_EQ(ReadNrrd(p).status().code(), absl::StatusCode::kUnimplemented);
  WriteAttached(p, Header("kinds: RGB-color domain domain\n"), ShortData());
  EXPECT_EQ(ReadNrrd(p).status().code(), absl::StatusCode::kUnimplemented);
}

TEST(NrrdBroken, TruncatedData) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "t.nrrd";
  auto d = ShortData();
  d.resize(d.size() - 1);
  WriteAttached(p, Header(""), d);
  ExpectError(ReadNrrd(p).status(), p, "truncated");
  WriteText(p, Header(""));  // header without the blank line and data
  ExpectError(ReadNrrd(p).status(), p, "truncated");
}

TEST(NrrdBroken, GzipCorruption) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "c.nrrd";
  std::vector<uint8_t> big;
  for (int i = 0; i < 40 * 30 * 20; ++i) {
    big.push_back(static_cast<uint8_t>(i * 37 % 251));
    big.push_back(static_cast<uint8_t>(i % 3));
  }
  const std::string h = Header("", "40 30 20", "gzip");
  auto z = Compress(big, true);
  CorruptMiddle(z, 0);
  WriteAttached(p, h, z);
  auto r = ReadNrrd(p);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(r.status().message(), HasSubstr(p.string()));
  EXPECT_THAT(r.status().message(), ::testing::AnyOf(HasSubstr("corrupt"), HasSubstr("truncated"),
                                                     HasSubstr("more data")));
}

TEST(NrrdBroken, DimensionsDoNotMatchDataSize) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "m.nrrd";
  WriteAttached(p, Header(""), ShortData(false, 13));
  ExpectError(ReadNrrd(p).status(), p, "do not match");
  WriteAttached(p, Header("", "3 2 2", "gzip"), Compress(ShortData(false, 13), true));
  ExpectError(ReadNrrd(p).status(), p, "more data than the header implies");
  WriteAttached(p, Header("", "3 2"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "sizes has 2 values");
}

TEST(NrrdBroken, TrillionVoxelHeaderFailsFast) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "h.nrrd";
  // Refused from the header: a reader that allocated the declared voxels (2 GB and more)
  // would run out of this headroom.
  const AddressSpaceCap cap(uint64_t{1} << 30);
  ASSERT_TRUE(cap.active());
  WriteAttached(p, Header("", "10000 10000 10000"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "exceeds the limit");
  WriteAttached(p, Header("", "1000 1000 1000", "gzip"), Compress(ShortData(), true));
  ExpectError(ReadNrrd(p).status(), p, "truncated");
  WriteAttached(p, Header("", "1000 1000 1000", "ascii"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "truncated");
}

TEST(NrrdBroken, ZeroOrNegativeSpacing) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "s.nrrd";
  WriteAttached(p, Header("spacings: 1 0 1\n"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "spacings[1] = '0'");
  WriteAttached(p, Header("spacings: 1 1 -1\n"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "spacings[2] = '-1'");
  WriteAttached(p, Header("space: LPS\nspace directions: (1,0,0) (0,0,0) (0,0,1)\n"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "zero vector");
}

TEST(NrrdBroken, NanVoxels) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "n.nrrd";
  std::vector<float> f(12, 2.0f);
  f[3] = std::numeric_limits<float>::quiet_NaN();
  std::vector<uint8_t> d(reinterpret_cast<uint8_t*>(f.data()),
                         reinterpret_cast<uint8_t*>(f.data()) + 48);
  std::string h = Header("");
  h.replace(h.find("type: short"), 11, "type: float");
  WriteAttached(p, h, d);
  ExpectError(ReadNrrd(p).status(), p, "NaN");
}

TEST(NrrdBroken, TwoDimensionalAndUnknownTypes) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "x.nrrd";
  WriteAttached(p, Header("", "6 2", "raw", "2"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "2D image: Decima needs a 3D volume");
  WriteAttached(p, Header("", "12 1 1"), ShortData());
  ExpectError(ReadNrrd(p).status(), p, "2D image: Decima needs a 3D volume (sizes[1] = 1");
  std::string h = Header("");
  h.replace(h.find("type: short"), 11, "type: quaternion");
  WriteAttached(p, h, ShortData());
  ExpectError(ReadNrrd(p).status(), p, "unknown type 'quaternion'");
  WriteAttached(p, Header("space: left-handed-nonsense\n"), ShortData());
  EXPECT_EQ(ReadNrrd(p).status().code(), absl::StatusCode::kUnimplemented);
  WriteAttached(p, Header("", "3 2 2", "bzip2"), ShortData());
  EXPECT_EQ(ReadNrrd(p).status().code(), absl::StatusCode::kUnimplemented);
}

TEST(NrrdBroken, MissingDetachedDataAndBadFiles) {
  const fs::path dir = decima::testing::MakeScratchDir("nrrd");
  const fs::path p = dir / "x.nhdr";
  WriteText(p, Header("data file: nothere.raw\n"));
  auto r = ReadNrrd(p);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(r.status().message(), HasSubstr("nothere.raw"));
  WriteText(p, Header("data file: ../../etc/passwd\n"));
  ExpectError(ReadNrrd(p).status(), p, "leaves the header's folder");
  WriteText(p, "");
  ExpectError(ReadNrrd(p).status(), p, "empty");
  WriteText(p, "NRRX0004\n");
  ExpectError(ReadNrrd(p).status(), p, "magic");
  EXPECT_EQ(ReadNrrd(dir / "none.nrrd").status().code(), absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace decima::io
