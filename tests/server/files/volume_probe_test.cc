#include <cstring>
#include <fstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/files/volume_probe.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;

// A NIfTI-1 header of dims (nx, ny, nz), int16, 1.5 mm, followed by `data_bytes` bytes.
std::string Nifti(int16_t nx, int16_t ny, int16_t nz, size_t data_bytes) {
  std::string h(352, '\0');
  int32_t s = 348;
  std::memcpy(&h[0], &s, 4);
  int16_t dim[4] = {3, nx, ny, nz};
  std::memcpy(&h[40], dim, 8);
  int16_t type = 4;
  std::memcpy(&h[70], &type, 2);
  float px[4] = {1, 1.5f, 1.5f, 1.5f};
  std::memcpy(&h[76], px, 16);
  float vox_offset = 352;
  std::memcpy(&h[108], &vox_offset, 4);
  std::memcpy(&h[344], "n+1", 4);
  return h + std::string(data_bytes, '\0');
}

class VolumeProbeTest : public ::testing::Test {
 protected:
  void SetUp() override { dir_ = testing::MakeScratchDir("probe"); }
  void Write(const std::string& name, const std::string& bytes) {
    fs::create_directories((dir_ / name).parent_path());
    std::ofstream(dir_ / name, std::ios::binary) << bytes;
  }
  fs::path dir_;
};

TEST_F(VolumeProbeTest, NiftiHeaderGivesDimsSpacingAndType) {
  Write("a.nii", Nifti(4, 5, 6, 240));
  auto h = ProbeVolume(dir_, {"a.nii"}, v1::VOLUME_FORMAT_UNSPECIFIED);
  ASSERT_TRUE(h.ok()) << h.status();
  EXPECT_EQ(h->format, v1::VOLUME_FORMAT_NIFTI);
  EXPECT_EQ(h->dims, (std::array<int64_t, 3>{4, 5, 6}));
  EXPECT_DOUBLE_EQ(h->spacing[0], 1.5);
  EXPECT_EQ(h->scalar_type, "int16");
  EXPECT_EQ(h->input, dir_ / "a.nii");
}

TEST_F(VolumeProbeTest, GarbageTruncatedAndAbsurdHeadersAreInvalidArgument) {
  Write("garbage.nii", std::string(1000, 'x'));
  Write("short.nii", "abc");
  Write("huge.nii", Nifti(-5, 2, 2, 0));
  Write("notes.txt", "hello");
  for (const char* f : {"garbage.nii", "short.nii", "huge.nii", "notes.txt"}) {
    auto h = ProbeVolume(dir_, {f}, v1::VOLUME_FORMAT_UNSPECIFIED);
    EXPECT_EQ(h.status().code(), absl::StatusCode::kInvalidArgument) << f;
    EXPECT_THAT(std::string(h.status().message()), HasSubstr(f));
  }
}

TEST_F(VolumeProbeTest, MetaImageAndNrrdHeaders) {
  Write("a.mhd",
        "ObjectType = Image\nNDims = 3\nDimSize = 3 4 5\nElementSpacing = 0.5 0.5 2\n"
        "ElementType = MET_SHORT\nModality = MET_MOD_CT\nElementDataFile = a.raw\n");
  Write("a.raw", std::string(120, '\0'));
  auto m = ProbeVolume(dir_, {"a.mhd", "a.raw"}, v1::VOLUME_FORMAT_UNSPECIFIED);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->format, v1::VOLUME_FORMAT_METAIMAGE);
  EXPECT_EQ(m->dims, (std::array<int64_t, 3>{3, 4, 5}));
  EXPECT_EQ(m->modality, "CT");
  Write("b.nrrd",
        "NRRD0004\ntype: short\ndimension: 3\nsizes: 2 3 4\nspacings: 1 1 3\n"
        "encoding: raw\nendian: little\n\n" +
            std::string(48, '\0'));
  auto n = ProbeVolume(dir_, {"b.nrrd"}, v1::VOLUME_FORMAT_UNSPECIFIED);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->dims, (std::array<int64_t, 3>{2, 3, 4}));
  EXPECT_DOUBLE_EQ(n->spacing[2], 3);
  Write("c.nrrd", "NRRD0004\nsizes: 2 3\n\n");
  EXPECT_FALSE(ProbeVolume(dir_, {"c.nrrd"}, v1::VOLUME_FORMAT_UNSPECIFIED).ok());
}

TEST_F(VolumeProbeTest, DicomSeriesNeedsThePreambleInEveryFile) {
  testing::SliceSpec spec;
  fs::create_directories(dir_ / "s");
  const auto files = testing::WriteSeries(dir_ / "s", spec, {1.0, 1.0}, {}, "");
  ASSERT_EQ(files.size(), 3u);
  auto ok = ProbeVolume(dir_, {"s/00.dcm", "s/01.dcm", "s/02.dcm"}, v1::VOLUME_FORMAT_UNSPECIFIED);
  ASSERT_TRUE(ok.ok()) << ok.status();
  EXPECT_EQ(ok->format, v1::VOLUME_FORMAT_DICOM);
  EXPECT_EQ(ok->modality, "CT");
  EXPECT_FALSE(ok->parsed);
  Write("s/3", "not dicom");
  auto bad = ProbeVolume(dir_, {"s/00.dcm", "s/3"}, v1::VOLUME_FORMAT_UNSPECIFIED);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(bad.status().message()), HasSubstr("s/3"));
}

TEST_F(VolumeProbeTest, DicomFilesWithSeveralSeriesNeedTheChosenUidAndItMustExist) {
  testing::SliceSpec a, b;
  a.series_uid = "1.2.826.0.1.3680043.9.7777.10";
  b.series_uid = "1.2.826.0.1.3680043.9.7777.20";
  b.modality = "MR";
  testing::WriteSeries(dir_, a, {1.0, 1.0}, {}, "a");
  testing::WriteSeries(dir_, b, {2.0}, {}, "b");
  const std::vector<std::string> files = {"a00.dcm", "a01.dcm", "a02.dcm", "b00.dcm", "b01.dcm"};
  auto none = ProbeVolume(dir_, files, v1::VOLUME_FORMAT_UNSPECIFIED);
  ASSERT_EQ(none.status().code(), absl::StatusCode::kInvalidArgument) << none.status();
  EXPECT_THAT(std::string(none.status().message()),
              ::testing::AllOf(HasSubstr("2 series"), HasSubstr(a.series_uid),
                               HasSubstr(b.series_uid), HasSubstr("--series")));
  auto chosen = ProbeVolume(dir_, files, v1::VOLUME_FORMAT_UNSPECIFIED, b.series_uid);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  EXPECT_EQ(chosen->modality, "MR");
  auto unknown = ProbeVolume(dir_, files, v1::VOLUME_FORMAT_UNSPECIFIED, "1.2.3.999");
  ASSERT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(unknown.status().message()),
              ::testing::AllOf(HasSubstr("1.2.3.999"), HasSubstr(a.series_uid)));
  // The server's folder never appears in what the client reads.
  EXPECT_THAT(std::string(unknown.status().message()), ::testing::Not(HasSubstr(dir_.string())));
}

}  // namespace
}  // namespace decima::server
