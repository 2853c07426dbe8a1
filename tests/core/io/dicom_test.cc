// Tests of ReadDicomSeries / ListDicomSeries. Every series is written by the test itself with
// gdcm::Writer (full control over each attribute, including broken ones); the real CT series in
// the shared data folder is checked last.
#include "core/io/dicom.h"

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <numeric>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include <gdcmDataElement.h>
#include <gdcmFile.h>
#include <gdcmImageChangeTransferSyntax.h>
#include <gdcmImageReader.h>
#include <gdcmImageWriter.h>
#include <gdcmItem.h>
#include <gdcmSequenceOfItems.h>
#include <gdcmTag.h>
#include <gdcmTransferSyntax.h>
#include <gdcmWriter.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

namespace fs = std::filesystem;
using ::testing::AllOf;
using ::testing::AnyOf;
using ::testing::HasSubstr;

using testing::SliceSpec;
using testing::WriteSeries;
using testing::WriteSlice;

void WriteBytes(const fs::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out << bytes;
}

TEST(DicomTest, WriterProducesPart10Files) {
  const fs::path dir = testing::MakeScratchDir("dicom-part10");
  WriteSlice(dir / "a.dcm", SliceSpec{});
  std::ifstream in(dir / "a.dcm", std::ios::binary);
  std::string head(132, '\0');
  in.read(head.data(), 132);
  EXPECT_EQ(head.substr(128), "DICM");
}

TEST(DicomTest, ShuffledFileNamesAreSortedByPositionAlongNormal) {
  const fs::path dir = testing::MakeScratchDir("dicom-shuffled");
  SliceSpec base;
  base.position = {-10, 20, 5};
  WriteSeries(dir, base, {2, 2, 2, 2}, {3, 0, 4, 1, 2});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->dims, (std::array<int64_t, 3>{3, 4, 5}));
  EXPECT_EQ(v->type, VoxelType::kUInt16);
  EXPECT_EQ(v->modality, "CT");
  // PixelSpacing (0.5, 0.8) is (between rows = along j, between columns = along i).
  EXPECT_TRUE(v->spacing.isApprox(Eigen::Vector3d(0.8, 0.5, 2))) << v->spacing.transpose();
  EXPECT_TRUE(v->origin.isApprox(Eigen::Vector3d(-10, 20, 5)));
  EXPECT_TRUE(v->direction.isApprox(Eigen::Matrix3d::Identity()));
  for (int k = 0; k < 5; ++k) {
    for (int j = 0; j < 4; ++j) {
      for (int i = 0; i < 3; ++i) {
        ASSERT_EQ(v->ValueAt(v->Index(i, j, k)), 10 * j + i + 100 * k) << i << "," << j << "," << k;
      }
    }
  }
}

// What the report shows of a series: patient, study and series from its first slice, padding
// stripped; absent attributes are empty.
TEST(DicomTest, ReadsThePatientStudyAndSeriesDescription) {
  const fs::path dir = testing::MakeScratchDir("dicom-description");
  SliceSpec base;
  base.patient_name = "DOE^JANE^Q";
  base.patient_id = "P123";
  base.study_date = "20240131";
  base.study_description = "CT HEAD W/O";
  base.description = "Axial 2mm";
  WriteSeries(dir, base, {2, 2});
  DicomDescription d;
  absl::StatusOr<Volume> v = ReadDicomSeries(dir, "", &d);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(d.patient_name, "DOE^JANE^Q");
  EXPECT_EQ(FormatPersonName(d.patient_name), "DOE, JANE Q");
  EXPECT_EQ(d.patient_id, "P123");
  EXPECT_EQ(d.study_date, "20240131");
  EXPECT_EQ(d.study_description, "CT HEAD W/O");
  EXPECT_EQ(d.series_description, "Axial 2mm");
  EXPECT_EQ(d.modality, "CT");

  const fs::path bare = testing::MakeScratchDir("dicom-description-bare");
  WriteSeries(bare, SliceSpec{}, {2});
  ASSERT_TRUE(ReadDicomSeries(bare, "", &d).ok());
  EXPECT_EQ(d.patient_name, "");
  EXPECT_EQ(d.study_description, "");
  EXPECT_EQ(d.series_description, "synthetic");
}

TEST(DicomTest, FormatPersonNameWritesFamilyCommaGiven) {
  EXPECT_EQ(FormatPersonName("DOE^JOHN"), "DOE, JOHN");
  EXPECT_EQ(FormatPersonName("DOE"), "DOE");
  EXPECT_EQ(FormatPersonName("^JOHN"), "JOHN");
  EXPECT_EQ(FormatPersonName("DOE^JOHN^^DR^"), "DOE, JOHN DR");
  EXPECT_EQ(FormatPersonName("Yamada^Tarou=山田^太郎"), "Yamada, Tarou");
  EXPECT_EQ(FormatPersonName(""), "");
}

TEST(DicomTest, DescendingPositionsPutOriginAtLowestSliceWithRightHandedDirection) {
  // Like the real CT: instance 1 is at the top (largest z), file names follow instances.
  const fs::path dir = testing::MakeScratchDir("dicom-descending");
  SliceSpec base;
  base.position = {0, 0, 8};
  base.orientation = {1, 0, 0, 0, 1, 0};
  // Stack downwards: write slices with decreasing z by flipping the gap sign via positions.
  for (int s = 0; s < 5; ++s) {
    SliceSpec spec = base;
    spec.position.z() = 8 - 2.0 * s;
    spec.instance = s + 1;
    spec.value = [s](int i, int j) { return 10 * j + i + 100.0 * s; };
    WriteSlice(dir / absl::StrCat("IM", s + 1, ".dcm"), spec);
  }
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_TRUE(v->origin.isApprox(Eigen::Vector3d(0, 0, 0))) << v->origin.transpose();
  EXPECT_TRUE(v->direction.isApprox(Eigen::Matrix3d::Identity()));
  EXPECT_DOUBLE_EQ(v->spacing.z(), 2);
  // k = 0 is instance 5 (z = 0), k = 4 is instance 1 (z = 8).
  EXPECT_EQ(v->ValueAt(v->Index(0, 0, 0)), 400);
  EXPECT_EQ(v->ValueAt(v->Index(0, 0, 4)), 0);
  EXPECT_TRUE(v->PhysicalPoint(0, 0, 4).isApprox(Eigen::Vector3d(0, 0, 8)));
}

TEST(DicomTest, SliceSpacingComesFromPositionsNotSliceThickness) {
  const fs::path dir = testing::MakeScratchDir("dicom-thickness");
  SliceSpec base;
  base.slice_thickness = 3;
  WriteSeries(dir, base, {2.5, 2.5, 2.5});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_NEAR(v->spacing.z(), 2.5, 1e-9);
}

TEST(DicomTest, RescaleWithIntegerInterceptGivesInt16) {
  const fs::path dir = testing::MakeScratchDir("dicom-rescale-int");
  SliceSpec base;
  base.slope = 1;
  base.intercept = -1024;
  WriteSeries(dir, base, {1, 1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->type, VoxelType::kInt16);
  EXPECT_EQ(v->ValueAt(v->Index(2, 3, 2)), 10 * 3 + 2 + 200 - 1024);
  EXPECT_EQ(v->ValueAt(v->Index(0, 0, 0)), -1024);
}

TEST(DicomTest, FractionalRescaleGivesFloat32) {
  const fs::path dir = testing::MakeScratchDir("dicom-rescale-float");
  SliceSpec base;
  base.slope = 0.5;
  base.intercept = 0.25;
  WriteSeries(dir, base, {1, 1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->type, VoxelType::kFloat32);
  EXPECT_FLOAT_EQ(v->ValueAt(v->Index(1, 2, 1)), (21 + 100) * 0.5 + 0.25);
}

TEST(DicomTest, RescaleOutsideInt16RangeGivesFloat32) {
  const fs::path dir = testing::MakeScratchDir("dicom-rescale-range");
  SliceSpec base;
  base.slope = 1000;
  base.intercept = 0;
  WriteSeries(dir, base, {1, 1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->type, VoxelType::kFloat32);
  EXPECT_FLOAT_EQ(v->ValueAt(v->Index(2, 3, 2)), 232000);
}

TEST(DicomTest, IdentityRescaleKeepsStoredSignedAndByteTypes) {
  {
    const fs::path dir = testing::MakeScratchDir("dicom-int16");
    SliceSpec base;
    base.slope = 1;
    base.intercept = 0;
    base.pixel_representation = 1;
    base.value = [](int i, int j) { return -1000 + 10 * j + i; };
    WriteSeries(dir, base, {1, 1});
    absl::StatusOr<Volume> v = ReadDicomSeries(dir);
    ASSERT_TRUE(v.ok()) << v.status();
    EXPECT_EQ(v->type, VoxelType::kInt16);
    EXPECT_EQ(v->ValueAt(v->Index(1, 1, 0)), -989);
  }
  {
    const fs::path dir = testing::MakeScratchDir("dicom-uint8");
    SliceSpec base;
    base.bits_allocated = 8;
    base.modality = "MR";
    WriteSeries(dir, base, {1, 1});
    absl::StatusOr<Volume> v = ReadDicomSeries(dir);
    ASSERT_TRUE(v.ok()) << v.status();
    EXPECT_EQ(v->type, VoxelType::kUInt8);
    EXPECT_EQ(v->modality, "MR");
    EXPECT_EQ(v->ValueAt(v->Index(2, 3, 2)), 232);
  }
}

TEST(DicomTest, BitsAboveBitsStoredAreMaskedAndSignExtended) {
  const fs::path dir = testing::MakeScratchDir("dicom-12bit");
  SliceSpec base;
  base.bits_stored = 12;
  base.pixel_representation = 1;
  // Stored 12-bit two's complement of (10j + i - 20) with junk (an overlay) in bits 12..15.
  base.value = [](int i, int j) {
    const int v = 10 * j + i - 20;
    return static_cast<double>(static_cast<int16_t>((v & 0x0FFF) | 0xA000));
  };
  WriteSeries(dir, base, {1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->type, VoxelType::kInt16);
  EXPECT_EQ(v->ValueAt(v->Index(0, 0, 0)), -20);
  EXPECT_EQ(v->ValueAt(v->Index(2, 3, 0)), 12);
  // Slice 1 adds 100 to the double before the cast: (v + 100) in the low bits.
  EXPECT_EQ(v->ValueAt(v->Index(0, 0, 1)), 80);
}

TEST(DicomTest, ObliqueOrientationGivesDirectionAndPhysicalPoints) {
  const fs::path dir = testing::MakeScratchDir("dicom-oblique");
  const Eigen::Matrix3d r =
      Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, -2, 3).normalized()).toRotationMatrix();
  SliceSpec base;
  base.orientation = {r(0, 0), r(1, 0), r(2, 0), r(0, 1), r(1, 1), r(2, 1)};
  base.position = {12.5, -40, 7};
  std::vector<fs::path> files = WriteSeries(dir, base, {1.5, 1.5, 1.5}, {2, 3, 0, 1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_TRUE(v->direction.isApprox(r, 1e-8)) << v->direction;
  EXPECT_NEAR(v->direction.determinant(), 1, 1e-9);
  EXPECT_TRUE(v->spacing.isApprox(Eigen::Vector3d(0.8, 0.5, 1.5), 1e-8));
  // Voxel (i, j, k) lies at position_k + i * 0.8 * row + j * 0.5 * col.
  for (int k = 0; k < 4; ++k) {
    const Eigen::Vector3d position_k = base.position + 1.5 * k * r.col(2);
    EXPECT_TRUE(v->PhysicalPoint(0, 0, k).isApprox(position_k, 1e-8)) << k;
    const Eigen::Vector3d expected = position_k + 2 * 0.8 * r.col(0) + 3 * 0.5 * r.col(1);
    EXPECT_LT((v->PhysicalPoint(2, 3, k) - expected).norm(), 1e-6) << k;
    EXPECT_EQ(v->ValueAt(v->Index(2, 3, k)), 32 + 100 * k);
  }
}

TEST(DicomTest, MissingSliceIsReportedWithTheGap) {
  const fs::path dir = testing::MakeScratchDir("dicom-missing");
  WriteSeries(dir, SliceSpec{}, {2, 2, 4, 2});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()),
              HasSubstr("missing slice between s02.dcm and s03.dcm: gap 4 mm, expected 2 mm"));
}

TEST(DicomTest, UnevenSpacingIsRejected) {
  const fs::path dir = testing::MakeScratchDir("dicom-uneven");
  WriteSeries(dir, SliceSpec{}, {2, 2.3, 1.7, 2});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("uneven slice spacing"));
}

TEST(DicomTest, SpacingWithinToleranceIsAccepted) {
  // Rounded positions (2.004, 1.996 mm) stay within 1% + 0.01 mm of the 2 mm mean.
  const fs::path dir = testing::MakeScratchDir("dicom-tolerance");
  WriteSeries(dir, SliceSpec{}, {2.004, 1.996, 2.0});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_NEAR(v->spacing.z(), 2.0, 1e-9);
}

TEST(DicomTest, DuplicatePositionsAreRejected) {
  const fs::path dir = testing::MakeScratchDir("dicom-duplicate");
  WriteSeries(dir, SliceSpec{}, {2, 0, 2});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_THAT(std::string(v.status().message()),
              AllOf(HasSubstr("s01.dcm and s02.dcm"), HasSubstr("same position")));
}

TEST(DicomTest, ShearedStackIsRejected) {
  const fs::path dir = testing::MakeScratchDir("dicom-sheared");
  SliceSpec base;
  for (int s = 0; s < 3; ++s) {
    SliceSpec spec = base;
    spec.position = {0.5 * s, 0, 2.0 * s};  // gantry tilt: origin drifts along x
    spec.instance = s + 1;
    WriteSlice(dir / absl::StrCat("t", s, ".dcm"), spec);
  }
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("gantry tilt"));
}

TEST(DicomTest, TwoSeriesNeedAUidAndEachCanBePicked) {
  const fs::path dir = testing::MakeScratchDir("dicom-two-series");
  SliceSpec a;
  a.series_uid = "1.2.3.100";
  a.description = "axial";
  SliceSpec b;
  b.series_uid = "1.2.3.200";
  b.description = "scout";
  b.modality = "MR";
  WriteSeries(dir, a, {1, 1}, {}, "a");
  WriteSeries(dir, b, {3}, {}, "b");

  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()),
              AllOf(HasSubstr("1.2.3.100 (\"axial\", modality CT, 3 files)"),
                    HasSubstr("1.2.3.200 (\"scout\", modality MR, 2 files)")));

  absl::StatusOr<Volume> vb = ReadDicomSeries(dir, "1.2.3.200");
  ASSERT_TRUE(vb.ok()) << vb.status();
  EXPECT_EQ(vb->dims[2], 2);
  EXPECT_DOUBLE_EQ(vb->spacing.z(), 3);
  EXPECT_EQ(vb->modality, "MR");
  absl::StatusOr<Volume> va = ReadDicomSeries(dir, "1.2.3.100");
  ASSERT_TRUE(va.ok()) << va.status();
  EXPECT_EQ(va->dims[2], 3);

  absl::StatusOr<Volume> unknown = ReadDicomSeries(dir, "9.9.9");
  ASSERT_FALSE(unknown.ok());
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(unknown.status().message()),
              AllOf(HasSubstr("9.9.9"), HasSubstr("1.2.3.100"), HasSubstr("1.2.3.200")));

  absl::StatusOr<std::vector<DicomSeriesInfo>> list = ListDicomSeries(dir);
  ASSERT_TRUE(list.ok()) << list.status();
  ASSERT_EQ(list->size(), 2u);
  EXPECT_EQ((*list)[0].series_instance_uid, "1.2.3.100");
  EXPECT_EQ((*list)[0].file_count, 3);
  EXPECT_EQ((*list)[1].series_description, "scout");
}

TEST(DicomTest, NonDicomFilesAreSkipped) {
  const fs::path dir = testing::MakeScratchDir("dicom-extra-files");
  WriteSeries(dir, SliceSpec{}, {1, 1});
  WriteBytes(dir / "SHA256SUMS", "0123abcd  s00.dcm\n");
  WriteBytes(dir / "garbage.dcm", std::string(4000, '\x5a'));
  WriteBytes(dir / "empty.dcm", "");
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->dims[2], 3);
}

TEST(DicomTest, FilesOneFolderDownAreFound) {
  const fs::path dir = testing::MakeScratchDir("dicom-subdir");
  fs::create_directories(dir / "series1");
  WriteSeries(dir / "series1", SliceSpec{}, {1, 1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->dims[2], 3);
}

TEST(DicomTest, OnlyGarbageIsAnErrorListingTheSkippedFiles) {
  const fs::path dir = testing::MakeScratchDir("dicom-only-garbage");
  WriteBytes(dir / "garbage.dcm", std::string(4000, '\x5a'));
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()),
              AllOf(HasSubstr("no DICOM image file"), HasSubstr("garbage.dcm (no DICM marker")));
}

TEST(DicomTest, GarbageAfterTheDicomMarkerIsAnErrorNamingTheFile) {
  const fs::path dir = testing::MakeScratchDir("dicom-garbage-marker");
  WriteSeries(dir, SliceSpec{}, {1, 1});
  std::mt19937 rng(7);
  std::string bytes(128, '\0');
  bytes += "DICM";
  for (int b = 0; b < 5000; ++b) bytes.push_back(static_cast<char>(rng()));
  WriteBytes(dir / "zz_broken.dcm", bytes);
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  // Either GDCM refuses the header (error naming the file) or it parses nothing usable and the
  // file is skipped as "not an image"; it must never crash or be taken as a slice.
  if (!v.ok()) {
    EXPECT_THAT(std::string(v.status().message()), HasSubstr("zz_broken.dcm"));
  } else {
    EXPECT_EQ(v->dims[2], 3);
  }
}

TEST(DicomTest, HeaderTruncatedFileIsAnErrorNamingTheFile) {
  const fs::path dir = testing::MakeScratchDir("dicom-header-truncated");
  std::vector<fs::path> files = WriteSeries(dir, SliceSpec{}, {1, 1});
  fs::resize_file(files[1], 300);  // inside the data set, before Rows
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("s01.dcm"));
}

TEST(DicomTest, TruncatedPixelDataIsAnErrorNamingTheFile) {
  const fs::path dir = testing::MakeScratchDir("dicom-pixel-truncated");
  SliceSpec base;
  base.rows = 16;
  base.columns = 16;
  std::vector<fs::path> files = WriteSeries(dir, base, {1, 1});
  fs::resize_file(files[2], fs::file_size(files[2]) - 100);
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("s02.dcm"));
}

TEST(DicomTest, EmptyFolderIsAnError) {
  const fs::path dir = testing::MakeScratchDir("dicom-empty");
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()),
              HasSubstr("no DICOM image file found (the folder is empty)"));
}

TEST(DicomTest, MissingFolderIsNotFound) {
  const fs::path dir = testing::MakeScratchDir("dicom-missing-dir") / "nope";
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("nope"));
}

TEST(DicomTest, FileInsteadOfFolderIsAnError) {
  const fs::path dir = testing::MakeScratchDir("dicom-file-arg");
  WriteSlice(dir / "one.dcm", SliceSpec{});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir / "one.dcm");
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("not a folder"));
}

TEST(DicomTest, InconsistentRowsNameTheFileAndField) {
  const fs::path dir = testing::MakeScratchDir("dicom-rows");
  WriteSeries(dir, SliceSpec{}, {1, 1});
  SliceSpec odd;
  odd.rows = 5;
  odd.position = {0, 0, 3};
  odd.instance = 4;
  WriteSlice(dir / "s03.dcm", odd);
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()),
              AllOf(HasSubstr("s03.dcm"), HasSubstr("Rows is 5, expected 4")));
}

TEST(DicomTest, InconsistentPixelSpacingAndOrientationNameTheField) {
  {
    const fs::path dir = testing::MakeScratchDir("dicom-spacing-mismatch");
    WriteSeries(dir, SliceSpec{}, {1});
    SliceSpec odd;
    odd.pixel_spacing = {0.5, 0.9};
    odd.position = {0, 0, 2};
    WriteSlice(dir / "s02.dcm", odd);
    absl::StatusOr<Volume> v = ReadDicomSeries(dir);
    ASSERT_FALSE(v.ok());
    EXPECT_THAT(std::string(v.status().message()),
                AllOf(HasSubstr("s02.dcm"), HasSubstr("PixelSpacing")));
  }
  {
    const fs::path dir = testing::MakeScratchDir("dicom-orientation-mismatch");
    WriteSeries(dir, SliceSpec{}, {1});
    SliceSpec odd;
    odd.orientation = {0, 1, 0, 1, 0, 0};
    odd.position = {0, 0, 2};
    WriteSlice(dir / "s02.dcm", odd);
    absl::StatusOr<Volume> v = ReadDicomSeries(dir);
    ASSERT_FALSE(v.ok());
    EXPECT_THAT(std::string(v.status().message()),
                AllOf(HasSubstr("s02.dcm"), HasSubstr("ImageOrientationPatient")));
  }
}

TEST(DicomTest, MissingPositionNamesTheField) {
  const fs::path dir = testing::MakeScratchDir("dicom-no-position");
  WriteSeries(dir, SliceSpec{}, {1});
  // Rewrite one slice without ImagePositionPatient.
  gdcm::Reader reader;
  reader.SetFileName((dir / "s01.dcm").c_str());
  ASSERT_TRUE(reader.Read());
  reader.GetFile().GetDataSet().Remove(gdcm::Tag(0x0020, 0x0032));
  gdcm::Writer writer;
  writer.SetFile(reader.GetFile());
  writer.SetFileName((dir / "s01.dcm").c_str());
  ASSERT_TRUE(writer.Write());
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_THAT(
      v.status().message(),
      AllOf(HasSubstr("s01.dcm"), HasSubstr("ImagePositionPatient (0020,0032) is missing")));
}

TEST(DicomTest, ColourSlicesAreRejected) {
  const fs::path dir = testing::MakeScratchDir("dicom-rgb");
  SliceSpec base;
  base.samples_per_pixel = 3;
  base.bits_allocated = 8;
  WriteSeries(dir, base, {1});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_THAT(std::string(v.status().message()), HasSubstr("SamplesPerPixel is 3, expected 1"));
}

TEST(DicomTest, SingleSliceIsAnError) {
  const fs::path dir = testing::MakeScratchDir("dicom-single");
  WriteSlice(dir / "only.dcm", SliceSpec{});
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(v.status().message()),
              AllOf(HasSubstr("only.dcm"), HasSubstr("at least 2")));
}

TEST(DicomTest, RleCompressedSeriesReadsLikeUncompressed) {
  const fs::path dir = testing::MakeScratchDir("dicom-rle");
  std::vector<fs::path> files = WriteSeries(dir, SliceSpec{}, {2, 2});
  for (const fs::path& f : files) {
    gdcm::ImageReader reader;
    reader.SetFileName(f.c_str());
    ASSERT_TRUE(reader.Read());
    gdcm::ImageChangeTransferSyntax change;
    change.SetTransferSyntax(gdcm::TransferSyntax::RLELossless);
    change.SetInput(reader.GetImage());
    ASSERT_TRUE(change.Change());
    gdcm::ImageWriter writer;
    writer.SetFile(reader.GetFile());
    writer.SetImage(change.GetOutput());
    writer.SetFileName(f.c_str());
    ASSERT_TRUE(writer.Write());
  }
  {
    gdcm::ImageReader check;
    check.SetFileName(files[0].c_str());
    ASSERT_TRUE(check.Read());
    ASSERT_EQ(check.GetImage().GetTransferSyntax(), gdcm::TransferSyntax::RLELossless);
  }
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->ValueAt(v->Index(2, 3, 2)), 232);
  EXPECT_EQ(v->ValueAt(v->Index(1, 0, 1)), 101);
}

TEST(DicomTest, ImplicitVrWithNestedSequenceReads) {
  for (auto ts : {gdcm::TransferSyntax::ImplicitVRLittleEndian,
                  gdcm::TransferSyntax::ExplicitVRLittleEndian}) {
    const fs::path dir = testing::MakeScratchDir("dicom-implicit");
    SliceSpec base;
    base.transfer_syntax = ts;
    base.with_sequence = true;
    WriteSeries(dir, base, {1, 1});
    absl::StatusOr<Volume> v = ReadDicomSeries(dir);
    ASSERT_TRUE(v.ok()) << v.status();
    EXPECT_EQ(v->ValueAt(v->Index(2, 3, 2)), 232);
  }
}

std::string ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// Writes s00, s01, s02 (1 mm apart), keeps s01's bytes, and checks that every damaged version
// of s01 made by `damage` gives either a volume without s01 (it was skipped as non-DICOM) or
// an error naming s01 - never a crash, an abort inside GDCM, or a volume with garbage in it.
// `damage` returns nullopt when it has no more variants.
void ExpectDamageIsContained(
    const SliceSpec& base, bool rle,
    const std::function<std::optional<std::string>(const std::string&, int)>& damage) {
  const fs::path dir = testing::MakeScratchDir("dicom-damage");
  std::vector<fs::path> files = WriteSeries(dir, base, {1, 1});
  if (rle) {
    for (const fs::path& f : files) {
      gdcm::ImageReader reader;
      reader.SetFileName(f.c_str());
      ASSERT_TRUE(reader.Read());
      gdcm::ImageChangeTransferSyntax change;
      change.SetTransferSyntax(gdcm::TransferSyntax::RLELossless);
      change.SetInput(reader.GetImage());
      ASSERT_TRUE(change.Change());
      gdcm::ImageWriter writer;
      writer.SetFile(reader.GetFile());
      writer.SetImage(change.GetOutput());
      writer.SetFileName(f.c_str());
      ASSERT_TRUE(writer.Write());
    }
  }
  const std::string original = ReadBytes(files[1]);
  for (int variant = 0;; ++variant) {
    const std::optional<std::string> damaged = damage(original, variant);
    if (!damaged) break;
    WriteBytes(files[1], *damaged);
    absl::StatusOr<Volume> v = ReadDicomSeries(dir);
    if (v.ok()) {
      // Either s01 was skipped, or the damage hit bytes that do not matter (a value we ignore).
      if (v->dims[2] == 3) {
        EXPECT_EQ(v->ValueAt(v->Index(2, 3, 0)), 32) << "variant " << variant;
        EXPECT_EQ(v->ValueAt(v->Index(2, 3, 2)), 232) << "variant " << variant;
      } else {
        EXPECT_EQ(v->dims[2], 2) << "variant " << variant;
      }
    } else {
      // A damaged SeriesInstanceUID makes s01 a series of its own, which is reported as such.
      EXPECT_THAT(std::string(v.status().message()),
                  AnyOf(HasSubstr("s01.dcm"), HasSubstr("holds 2 series")))
          << "variant " << variant;
    }
  }
}

TEST(DicomTest, TruncationAnywhereIsContained) {
  SliceSpec explicit_vr;
  explicit_vr.with_sequence = true;
  SliceSpec implicit_vr = explicit_vr;
  implicit_vr.transfer_syntax = gdcm::TransferSyntax::ImplicitVRLittleEndian;
  for (const SliceSpec& base : {explicit_vr, implicit_vr}) {
    for (bool rle : {false, true}) {
      if (rle && base.transfer_syntax != gdcm::TransferSyntax::ExplicitVRLittleEndian) continue;
      ExpectDamageIsContained(
          base, rle, [](const std::string& bytes, int variant) -> std::optional<std::string> {
            // Every byte through the headers, where the parser is at risk; then every 5th.
            const int cut = variant < 420 ? variant : 420 + 5 * (variant - 420);
            if (cut >= static_cast<int>(bytes.size())) return std::nullopt;
            return bytes.substr(0, cut);
          });
    }
  }
}

TEST(DicomTest, RandomByteCorruptionIsContained) {
  SliceSpec base;
  base.with_sequence = true;
  for (bool rle : {false, true}) {
    std::mt19937 rng(rle ? 11 : 5);
    ExpectDamageIsContained(
        base, rle, [&rng](const std::string& bytes, int variant) -> std::optional<std::string> {
          if (variant == 250) return std::nullopt;
          std::string out = bytes;
          const int flips = 1 + static_cast<int>(rng() % 6);
          for (int f = 0; f < flips; ++f) {
            // Mostly past the preamble, where GDCM would see the damage.
            const size_t at = 128 + rng() % (out.size() - 128);
            out[at] = static_cast<char>(rng());
          }
          return out;
        });
  }
}

// The real CT head series of ../shared/data (see MANIFEST.md): 113 files, instance 1 at the
// vertex (z = 224), slices 2 mm apart downwards.
TEST(DicomTest, RealCtHeadSeries) {
  DECIMA_REQUIRE_SHARED_DATA(dir, "ct-head-256x256x113-dicom");
  absl::StatusOr<Volume> v = ReadDicomSeries(dir);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(v->dims, (std::array<int64_t, 3>{256, 256, 113}));
  EXPECT_EQ(v->type, VoxelType::kUInt16);
  EXPECT_EQ(v->modality, "CT");
  EXPECT_TRUE(v->spacing.isApprox(Eigen::Vector3d(1, 1, 2)));
  const auto [lo, hi] = v->ValueRange();
  EXPECT_EQ(lo, 0);
  EXPECT_EQ(hi, 3272);
  // Positions increase along k, so k runs from the chin (z = 0) to the vertex (z = 224); the
  // NIfTI copy indexes the other way: its voxel (i, j, kn) at (-127.5 + i, -127.5 + j, 224 - 2kn)
  // is this volume's (i, j, 112 - kn).
  EXPECT_TRUE(v->direction.isApprox(Eigen::Matrix3d::Identity()));
  for (int kn : {0, 50, 112}) {
    const Eigen::Vector3d expected(-127.5 + 10, -127.5 + 20, 224 - 2.0 * kn);
    EXPECT_TRUE(v->PhysicalPoint(10, 20, 112 - kn).isApprox(expected)) << kn;
  }
  // Slice k = 112 is IM0001.dcm, decoded independently here.
  gdcm::ImageReader reader;
  reader.SetFileName((dir / "IM0001.dcm").c_str());
  ASSERT_TRUE(reader.Read());
  std::vector<uint16_t> first(256 * 256);
  ASSERT_EQ(reader.GetImage().GetBufferLength(), first.size() * 2);
  ASSERT_TRUE(reader.GetImage().GetBuffer(reinterpret_cast<char*>(first.data())));
  EXPECT_TRUE(std::equal(first.begin(), first.end(), v->data<uint16_t>() + v->Index(0, 0, 112)));
}

}  // namespace
}  // namespace decima
