// A batch's studies (client/batch.h) on small folders written here: volume files, DICOM series
// told apart by SeriesInstanceUID, files that are neither, empty folders; the batch's exit code
// and the --out folder names.
#include "client/batch.h"

#include <fstream>

#include "gtest/gtest.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/test_data.h"

namespace decima::client {
namespace {
namespace fs = std::filesystem;

void Touch(const fs::path& p, const std::string& text = "x") {
  fs::create_directories(p.parent_path());
  std::ofstream(p) << text;
}

TEST(Batch, VolumeFileNamesAreTheFormatsTheServerReads) {
  for (const char* yes : {"a.nii", "a.NII.GZ", "b.mha", "b.mhd", "c.nrrd", "c.nhdr"}) {
    EXPECT_TRUE(IsVolumeFileName(yes)) << yes;
  }
  for (const char* no : {"a.raw", "a.zraw", "notes.txt", ".nii", "DICOMDIR", "a.nii.bak"}) {
    EXPECT_FALSE(IsVolumeFileName(no)) << no;
  }
}

TEST(Batch, DicomFilesAreGroupedBySeriesAndVolumeFilesAreStudiesOfTheirOwn) {
  const fs::path dir = testing::MakeScratchDir("batch_find") / "study";
  fs::create_directories(dir / "sub");
  testing::SliceSpec slice;
  slice.series_uid = "1.2.3.4.100";
  testing::WriteSeries(dir, slice, {1.0, 1.0}, {}, "a");  // 3 files
  slice.series_uid = "1.2.3.4.200";
  testing::WriteSeries(dir / "sub", slice, {1.0}, {}, "b");  // 2 files, below
  Touch(dir / "scan.nii.gz");
  Touch(dir / "notes.txt");
  Touch(dir / "DICOMDIR");

  std::vector<Study> studies;
  std::string error;
  ASSERT_TRUE(FindStudies(dir, &studies, &error)) << error;
  ASSERT_EQ(studies.size(), 3u);
  EXPECT_EQ(studies[0].input, dir / "scan.nii.gz");
  EXPECT_FALSE(studies[0].dicom());
  EXPECT_EQ(studies[1].series_uid, "1.2.3.4.100");
  EXPECT_EQ(studies[1].files.size(), 3u);
  EXPECT_EQ(studies[2].series_uid, "1.2.3.4.200");
  ASSERT_EQ(studies[2].files.size(), 2u);
  EXPECT_EQ(studies[2].files[0].name.rfind("sub/", 0), 0u) << studies[2].files[0].name;
  // Two series of one folder get names that tell them apart.
  EXPECT_NE(studies[1].display_name, studies[2].display_name);
}

TEST(Batch, AFolderWithNoVolumeHasNoStudyAndAMissingOneIsAnError) {
  const fs::path root = testing::MakeScratchDir("batch_empty");
  Touch(root / "only-notes" / "readme.txt");
  fs::create_directories(root / "empty");
  std::vector<Study> studies;
  std::string error;
  EXPECT_TRUE(FindStudies(root / "only-notes", &studies, &error)) << error;
  EXPECT_TRUE(studies.empty());
  EXPECT_TRUE(FindStudies(root / "empty", &studies, &error)) << error;
  EXPECT_TRUE(studies.empty());
  EXPECT_FALSE(FindStudies(root / "missing", &studies, &error));
  EXPECT_NE(error.find("missing"), std::string::npos) << error;
}

TEST(Batch, EachTakesSubfoldersAndVolumeFilesOnly) {
  const fs::path root = testing::MakeScratchDir("batch_each");
  fs::create_directories(root / "b-folder");
  Touch(root / "a.nii");
  Touch(root / "c.mhd");
  Touch(root / "c.zraw");
  Touch(root / "notes.txt");
  Touch(root / ".hidden.nii");
  std::vector<fs::path> entries;
  std::string error;
  ASSERT_TRUE(EachEntry(root, &entries, &error)) << error;
  EXPECT_EQ(entries, (std::vector<fs::path>{root / "a.nii", root / "b-folder", root / "c.mhd"}));
  EXPECT_FALSE(EachEntry(root / "a.nii", &entries, &error));
}

TEST(Batch, TheExitCodeIsZeroOnlyWhenEveryStudySucceeded) {
  EXPECT_EQ(BatchExitCode({kOk, kOk}), kOk);
  EXPECT_EQ(BatchExitCode({}), kOk);
  EXPECT_EQ(BatchExitCode({kOk, kJobFailed, kOk}), kJobFailed);
  // The worst outcome wins: failed over cancelled over short of target.
  EXPECT_EQ(BatchExitCode({kTargetNotReached, kJobCancelled, kJobFailed}), kJobFailed);
  EXPECT_EQ(BatchExitCode({kTargetNotReached, kJobCancelled}), kJobCancelled);
  EXPECT_EQ(BatchExitCode({kOk, kTargetNotReached}), kTargetNotReached);
  EXPECT_EQ(BatchExitCode({kOk, kTimeout}), kTimeout);
}

TEST(Batch, ArtifactFolderNamesAreSafeAndUnique) {
  std::vector<std::string> taken;
  EXPECT_EQ(ArtifactFolderName("scans/a b.nii.gz", &taken), "scans_a_b.nii.gz");
  EXPECT_EQ(ArtifactFolderName("scans/a b.nii.gz", &taken), "scans_a_b.nii.gz-2");
  EXPECT_EQ(ArtifactFolderName("../x", &taken), "_._x");  // never hidden, never ".."
  EXPECT_EQ(ArtifactFolderName("", &taken), "study");
}

}  // namespace
}  // namespace decima::client
