#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <cstring>

#include "core/io/volume_io.h"
#include "tests/core/io/io_test_util.h"
#include "tests/testing/test_data.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using testing::PatternVolume;
using testing::WriteText;

TEST(ReadVolume, DispatchesByExtensionCaseInsensitively) {
  const fs::path dir = decima::testing::MakeScratchDir("dispatch");
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kUInt16);
  ASSERT_TRUE(WriteNifti(v, dir / "a.NII.GZ").ok());
  ASSERT_TRUE(WriteMetaImage(v, dir / "b.mha").ok());
  ASSERT_TRUE(WriteMetaImage(v, dir / "c.MHD", {.compress = false}).ok());
  EXPECT_EQ(DetectVolumeFormat(dir / "a.NII.GZ"), VolumeFormat::kNifti);
  EXPECT_EQ(DetectVolumeFormat(dir / "b.mha"), VolumeFormat::kMetaImage);
  EXPECT_EQ(DetectVolumeFormat(dir / "x.nhdr"), VolumeFormat::kNrrd);
  for (const char* name : {"a.NII.GZ", "b.mha", "c.MHD"}) {
    auto r = ReadVolume(dir / name);
    ASSERT_TRUE(r.ok()) << name << ": " << r.status();
    EXPECT_EQ(r->bytes, v.bytes) << name;
  }
}

TEST(ReadVolume, SniffsMagicBytesWhenTheExtensionIsUnknown) {
  const fs::path dir = decima::testing::MakeScratchDir("dispatch");
  const Volume v = PatternVolume({4, 3, 2}, VoxelType::kInt16);
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii.gz").ok());
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
  ASSERT_TRUE(WriteMetaImage(v, dir / "a.mha").ok());
  fs::rename(dir / "a.nii.gz", dir / "blob1");
  fs::rename(dir / "a.nii", dir / "blob2");
  fs::rename(dir / "a.mha", dir / "blob3");
  WriteText(dir / "blob4",
            "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n"
            "abcdefgh");
  EXPECT_EQ(DetectVolumeFormat(dir / "blob1"), VolumeFormat::kNifti);
  EXPECT_EQ(DetectVolumeFormat(dir / "blob2"), VolumeFormat::kNifti);
  EXPECT_EQ(DetectVolumeFormat(dir / "blob3"), VolumeFormat::kMetaImage);
  EXPECT_EQ(DetectVolumeFormat(dir / "blob4"), VolumeFormat::kNrrd);
  for (const char* name : {"blob1", "blob2", "blob3"}) {
    auto r = ReadVolume(dir / name);
    ASSERT_TRUE(r.ok()) << name << ": " << r.status();
    EXPECT_EQ(r->bytes, v.bytes) << name;
  }
  auto n = ReadVolume(dir / "blob4");
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->data<uint8_t>()[7], 'h');
}

TEST(ReadVolume, EmptyDirectoryIsRejectedByTheDicomReader) {
  const fs::path dir = decima::testing::MakeScratchDir("dispatch");
  auto r = ReadVolume(dir);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), HasSubstr(dir.string()));
}

// The DICOM series and the NIfTI file of the same CT hold the same voxels at the same patient
// positions; the DICOM k axis runs upwards (increasing position), the NIfTI one downwards.
TEST(ReadVolume, DicomSeriesMatchesTheNiftiCopyVoxelByVoxel) {
  DECIMA_REQUIRE_SHARED_DATA(dicom_dir, "ct-head-256x256x113-dicom");
  DECIMA_REQUIRE_SHARED_DATA(nifti, "ct-head-256x256x113.nii.gz");
  auto d = ReadVolume(dicom_dir);
  auto n = ReadVolume(nifti);
  ASSERT_TRUE(d.ok()) << d.status();
  ASSERT_TRUE(n.ok()) << n.status();
  ASSERT_EQ(d->dims, n->dims);
  ASSERT_EQ(d->type, n->type);
  const int64_t nz = d->dims[2];
  int64_t mismatches = 0;
  for (int64_t k = 0; k < nz; ++k) {
    for (int64_t j = 0; j < d->dims[1]; ++j) {
      for (int64_t i = 0; i < d->dims[0]; ++i) {
        mismatches += d->ValueAt(d->Index(i, j, nz - 1 - k)) != n->ValueAt(n->Index(i, j, k));
      }
    }
  }
  EXPECT_EQ(mismatches, 0);
  for (const auto& [i, j, k] : {std::array<int64_t, 3>{0, 0, 0}, {100, 37, 50}, {255, 255, 112}}) {
    EXPECT_TRUE(d->PhysicalPoint(i, j, nz - 1 - k).isApprox(n->PhysicalPoint(i, j, k), 1e-4));
  }
}

TEST(ReadVolume, UnknownEmptyAndMissingFiles) {
  const fs::path dir = decima::testing::MakeScratchDir("dispatch");
  WriteText(dir / "notes.txt", "hello, not a volume");
  auto r = ReadVolume(dir / "notes.txt");
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), HasSubstr("unknown volume format"));
  WriteText(dir / "empty", "");
  EXPECT_THAT(ReadVolume(dir / "empty").status().message(), HasSubstr("unknown volume format"));
  WriteText(dir / "empty.nii.gz", "");
  EXPECT_THAT(ReadVolume(dir / "empty.nii.gz").status().message(), HasSubstr("empty"));
  auto m = ReadVolume(dir / "missing.nrrd");
  EXPECT_EQ(m.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(m.status().message(), HasSubstr("missing.nrrd"));
}

TEST(ReadVolumeRealData, AllSharedFilesLoad) {
  DECIMA_REQUIRE_SHARED_DATA(p, "ct-head-128x128x113.nii.gz");
  auto r = ReadVolume(p);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->dims, (std::array<int64_t, 3>{128, 128, 113}));
  DECIMA_REQUIRE_SHARED_DATA(m, "ct-headneck-64x64x93.mhd");
  auto h = ReadVolume(m);
  ASSERT_TRUE(h.ok()) << h.status();
  EXPECT_EQ(h->voxel_count(), 64 * 64 * 93);
}

}  // namespace
}  // namespace decima::io

namespace decima::io {
namespace {

TEST(VolumeFormatFromName, KnowsEveryExtensionOnceIncludingHdrImgPairs) {
  for (const char* n : {"a.nii", "a.NII.GZ", "a.hdr", "a.img", "a.hdr.gz", "a.img.gz"}) {
    EXPECT_EQ(VolumeFormatFromName(n), VolumeFormat::kNifti) << n;
  }
  EXPECT_EQ(VolumeFormatFromName("a.mha"), VolumeFormat::kMetaImage);
  EXPECT_EQ(VolumeFormatFromName("a.MHD"), VolumeFormat::kMetaImage);
  EXPECT_EQ(VolumeFormatFromName("a.nrrd"), VolumeFormat::kNrrd);
  EXPECT_EQ(VolumeFormatFromName("a.nhdr"), VolumeFormat::kNrrd);
  EXPECT_EQ(VolumeFormatFromName("a.dcm"), VolumeFormat::kUnknown);
  EXPECT_EQ(VolumeFormatFromName("a.zraw"), VolumeFormat::kUnknown);
}

TEST(ProbeVolume, ReportsWhatReadVolumeReturnsForEveryFormat) {
  const fs::path dir = decima::testing::MakeScratchDir("probe");
  Volume v = PatternVolume({5, 4, 3}, VoxelType::kInt16);
  v.spacing = {0.5, 0.75, 2.0};
  v.modality = "CT";
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii.gz").ok());
  ASSERT_TRUE(WriteMetaImage(v, dir / "b.mha").ok());
  ASSERT_TRUE(WriteMetaImage(v, dir / "c.mhd", {.compress = false}).ok());
  for (const char* name : {"a.nii.gz", "b.mha", "c.mhd"}) {
    auto full = ReadVolume(dir / name);
    auto probe = ProbeVolume(dir / name);
    ASSERT_TRUE(full.ok() && probe.ok()) << name << ": " << probe.status();
    EXPECT_TRUE(probe->parsed);
    EXPECT_EQ(probe->input, dir / name);
    EXPECT_EQ(probe->dims, full->dims) << name;
    for (int c = 0; c < 3; ++c) EXPECT_DOUBLE_EQ(probe->spacing[c], full->spacing[c]) << name;
    EXPECT_EQ(probe->type, full->type) << name;
    EXPECT_EQ(probe->modality, full->modality) << name;
  }
}

TEST(ProbeVolume, DecodesNoVoxelACorruptDataStreamPassesTheProbeAndFailsTheRead) {
  const fs::path dir = decima::testing::MakeScratchDir("probe");
  const Volume v = PatternVolume({64, 64, 64}, VoxelType::kUInt16);
  ASSERT_TRUE(WriteMetaImage(v, dir / "a.mhd").ok());  // zlib data in a.zraw
  auto bytes = testing::ReadAll(dir / "a.zraw");
  testing::CorruptMiddle(bytes, bytes.size() / 2, 64);
  testing::WriteAll(dir / "a.zraw", bytes);
  EXPECT_FALSE(ReadVolume(dir / "a.mhd").ok());
  auto probe = ProbeVolume(dir / "a.mhd");
  ASSERT_TRUE(probe.ok()) << probe.status();
  EXPECT_EQ(probe->dims, (std::array<int64_t, 3>{64, 64, 64}));
}

TEST(ProbeVolume, RefusesRawDataShorterThanTheHeaderPromisesAndUnknownFiles) {
  const fs::path dir = decima::testing::MakeScratchDir("probe");
  const Volume v = PatternVolume({8, 8, 8}, VoxelType::kUInt8);
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
  auto bytes = testing::ReadAll(dir / "a.nii");
  bytes.resize(bytes.size() - 10);
  testing::WriteAll(dir / "a.nii", bytes);
  auto probe = ProbeVolume(dir / "a.nii");
  ASSERT_FALSE(probe.ok());
  EXPECT_EQ(probe.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(probe.status().message()), HasSubstr("truncated"));
  WriteText(dir / "notes.txt", "hello");
  EXPECT_EQ(ProbeVolume(dir / "notes.txt").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ProbeVolume(dir / "missing.nii").status().code(), absl::StatusCode::kNotFound);
}

// Issue 30: `decima submit` reads the dims with ProbeVolume before uploading (client/cli/
// volume_upload.h), so a broken header there is a Status naming the file, never a crash or a
// wrong dims. NIfTI-1 plain and gzipped, NRRD written by hand (the project writes none), and
// headers broken each way a file arrives broken.
TEST(ProbeVolume, GivesTheClientsDimsOrAnErrorNamingTheFileForBrokenHeaders) {
  const fs::path dir = decima::testing::MakeScratchDir("probe-client");
  const Volume v = PatternVolume({6, 5, 4}, VoxelType::kUInt8);
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii").ok());
  ASSERT_TRUE(WriteNifti(v, dir / "a.nii.gz").ok());
  ASSERT_TRUE(WriteMetaImage(v, dir / "a.mha").ok());
  WriteText(dir / "a.nrrd", std::string("NRRD0004\ntype: uchar\ndimension: 3\nsizes: 6 5 4\n"
                                        "encoding: raw\n\n") +
                                std::string(6 * 5 * 4, '\0'));
  for (const char* name : {"a.nii", "a.nii.gz", "a.mha", "a.nrrd"}) {
    auto probe = ProbeVolume(dir / name);
    ASSERT_TRUE(probe.ok()) << name << ": " << probe.status();
    EXPECT_EQ(probe->dims, (std::array<int64_t, 3>{6, 5, 4})) << name;
  }
  const auto nii = testing::ReadAll(dir / "a.nii");
  auto with_dim = [&](int16_t d) {
    auto b = nii;
    std::memcpy(b.data() + 42, &d, 2);  // dim[1]
    return b;
  };
  auto bad_magic = nii;
  std::memcpy(bad_magic.data() + 344, "xx1\0", 4);
  std::vector<uint8_t> gz_garbage = {0x1f, 0x8b, 8, 0};
  for (int i = 0; i < 300; ++i) gz_garbage.push_back(static_cast<uint8_t>(i * 37));
  const std::vector<std::pair<std::string, std::vector<uint8_t>>> broken = {
      {"truncated.nii", std::vector<uint8_t>(nii.begin(), nii.begin() + 100)},
      {"empty.nii", {}},
      {"magic.nii", bad_magic},
      {"zero.nii", with_dim(0)},
      {"negative.nii", with_dim(-6)},
      {"garbage.nii.gz", gz_garbage},
  };
  for (const auto& [name, bytes] : broken) {
    testing::WriteAll(dir / name, bytes);
    auto probe = ProbeVolume(dir / name);
    EXPECT_FALSE(probe.ok()) << name;
    EXPECT_THAT(std::string(probe.status().message()), HasSubstr(name));
  }
  WriteText(dir / "neg.nrrd",
            "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 6 -5 4\n"
            "encoding: raw\n\n");
  WriteText(dir / "nodims.mha",
            "ObjectType = Image\nNDims = 3\nElementType = MET_UCHAR\n"
            "ElementDataFile = LOCAL\n");
  for (const char* name : {"neg.nrrd", "nodims.mha"}) {
    auto probe = ProbeVolume(dir / name);
    EXPECT_FALSE(probe.ok()) << name;
    EXPECT_THAT(std::string(probe.status().message()), HasSubstr(name));
  }
}

TEST(ProbeVolume, AFolderIsDicomOnlyIfEveryFileCarriesTheMarker) {
  const fs::path dir = decima::testing::MakeScratchDir("probe-dicom");
  std::vector<uint8_t> dicm(200, 0);
  std::memcpy(dicm.data() + 128, "DICM", 4);
  testing::WriteAll(dir / "1.dcm", dicm);
  auto ok = ProbeVolume(dir);
  ASSERT_TRUE(ok.ok()) << ok.status();
  EXPECT_EQ(ok->format, VolumeFormat::kDirectory);
  EXPECT_FALSE(ok->parsed);
  WriteText(dir / "2.dcm", "not dicom");
  auto bad = ProbeVolume(dir);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(std::string(bad.status().message()), HasSubstr("2.dcm"));
}

}  // namespace
}  // namespace decima::io
