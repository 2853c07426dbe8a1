#include <fstream>

#include "client/client_lib.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/test_data.h"

namespace decima::client {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;

TEST(ExitCodeTest, StatusCodesMapToTheDocumentedExitCodes) {
  EXPECT_EQ(ExitCodeFor(grpc::StatusCode::OK), 0);
  EXPECT_EQ(ExitCodeFor(grpc::StatusCode::INVALID_ARGUMENT), 1);
  EXPECT_EQ(ExitCodeFor(grpc::StatusCode::DEADLINE_EXCEEDED), 5);
  EXPECT_EQ(ExitCodeFor(grpc::StatusCode::NOT_FOUND), 6);
  EXPECT_EQ(ExitCodeFor(grpc::StatusCode::UNAUTHENTICATED), 7);
  EXPECT_EQ(ExitCodeFor(grpc::StatusCode::UNAVAILABLE), 8);
  EXPECT_EQ(ExitCodeFor(v1::SUCCEEDED), 0);
  EXPECT_EQ(ExitCodeFor(v1::FAILED), 3);
  EXPECT_EQ(ExitCodeFor(v1::CANCELLED), 4);
  EXPECT_EQ(StatusCodeName(grpc::StatusCode::RESOURCE_EXHAUSTED), "RESOURCE_EXHAUSTED");
}

TEST(CollectInputsTest, FolderGivesSortedRelativeNamesWithoutHiddenFiles) {
  fs::path d = testing::MakeScratchDir("collect");
  fs::create_directories(d / "sub");
  fs::create_directories(d / ".git");
  std::ofstream(d / "b.dcm") << "b";
  std::ofstream(d / "a.dcm") << "a";
  std::ofstream(d / "sub" / "c.dcm") << "c";
  std::ofstream(d / ".DS_Store") << "x";
  std::ofstream(d / ".git" / "x") << "x";
  std::vector<InputFile> files;
  std::string err;
  ASSERT_TRUE(CollectInputs(d, &files, &err)) << err;
  ASSERT_EQ(files.size(), 3u);
  EXPECT_EQ(files[0].name, "a.dcm");
  EXPECT_EQ(files[1].name, "b.dcm");
  EXPECT_EQ(files[2].name, "sub/c.dcm");
  ASSERT_TRUE(HashInputs(&files, &err));
  EXPECT_EQ(files[0].sha256, "ca978112ca1bbdcafac231b39a23dc4da786eff8147c4e72b9807785afee48bb");
  EXPECT_EQ(files[0].size, 1);
}

TEST(CollectInputsTest, ASymbolicLinkInTheFolderIsRefusedByName) {
  fs::path d = testing::MakeScratchDir("collect_link");
  std::ofstream(d / "scan.mhd") << "NDims = 3";
  fs::create_symlink("/etc/passwd", d / "scan.zraw");
  std::vector<InputFile> files;
  std::string err;
  EXPECT_FALSE(CollectInputs(d, &files, &err));
  EXPECT_THAT(err, HasSubstr("scan.zraw"));
  EXPECT_THAT(err, HasSubstr("symbolic link"));
  // A linked folder is refused too, instead of being skipped without a word.
  fs::remove(d / "scan.zraw");
  fs::create_directories(d / "real");
  std::ofstream(d / "real" / "x.dcm") << "x";
  fs::create_directory_symlink(d / "real", d / "linked");
  EXPECT_FALSE(CollectInputs(d, &files, &err));
  EXPECT_THAT(err, HasSubstr("linked"));
}

TEST(CollectInputsTest, MissingInputAndEmptyFolderAreErrors) {
  fs::path d = testing::MakeScratchDir("collect_empty");
  std::vector<InputFile> files;
  std::string err;
  EXPECT_FALSE(CollectInputs(d / "nope.nii", &files, &err));
  EXPECT_THAT(err, HasSubstr("nope.nii"));
  EXPECT_FALSE(CollectInputs(d, &files, &err));
  EXPECT_THAT(err, HasSubstr("no files"));
}

TEST(ProgressBarTest, ShowsStageFractionAndMessage) {
  v1::Progress p;
  p.set_stage("segment");
  p.set_fraction(0.5);
  p.set_message("iteration 3");
  std::string bar = ProgressBar(p, 10);
  EXPECT_THAT(bar, HasSubstr("[#####.....]"));
  EXPECT_THAT(bar, HasSubstr(" 50%"));
  EXPECT_THAT(bar, HasSubstr("iteration 3"));
  p.set_fraction(7);  // out of range: clamped
  EXPECT_THAT(ProgressBar(p, 4), HasSubstr("[####] 100%"));
}

}  // namespace
}  // namespace decima::client
