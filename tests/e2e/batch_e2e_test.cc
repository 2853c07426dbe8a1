// Batches (issue 33, part 2) through the real server and CLI processes: `decima submit DIR1
// DIR2 ...` and `decima submit --each FOLDER` make one job per study (a volume file, or a
// DICOM series by SeriesInstanceUID), a failed study does not stop the others, a folder with
// no volume is reported and skipped, `decima watch J1 J2 ...` follows several jobs at once,
// and the exit code says whether every study succeeded.
#include <fstream>
#include <regex>
#include <set>
#include <sstream>

#include <zlib.h>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;
using namespace std::chrono_literals;

// Small and fast: each tiny job takes about a second.
const std::vector<std::string> kFastJob = {"--image-size", "32",        "--reduction",
                                           "0.3",          "--regions", "2"};

std::vector<std::string> Lines(const std::string& s) {
  std::vector<std::string> out;
  std::istringstream in(s);
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

// The table's data rows (after the JOB INPUT STATE DETAIL header), split into
// {job, input-and-state-and-detail line}.
struct Row {
  std::string job, line;
};
std::vector<Row> TableRows(const std::string& out) {
  std::vector<Row> rows;
  bool in_table = false;
  for (const auto& l : Lines(out)) {
    if (l.rfind("JOB ", 0) == 0 && l.find("STATE") != std::string::npos) {
      in_table = true;
      continue;
    }
    if (in_table && !l.empty()) rows.push_back({l.substr(0, l.find(' ')), l});
  }
  return rows;
}

int CountState(const std::vector<Row>& rows, const std::string& state) {
  int n = 0;
  for (const auto& r : rows) n += r.line.find("   " + state + "   ") != std::string::npos;
  return n;
}

std::vector<std::string> Args(std::vector<std::string> head, const std::vector<std::string>& tail) {
  head.insert(head.end(), tail.begin(), tail.end());
  return head;
}

// A .nii.gz cut off in the middle of its compressed stream: the header probe accepts it (it
// decompresses the header only), the job's load stage fails on the missing data. (A cut .nii
// is refused at CreateVolume already: its size gives it away.)
void WriteTruncatedNiftiGz(const fs::path& path) {
  const fs::path plain = path.parent_path() / "plain.nii";
  WriteTinyNifti(plain, 12, 10, 8, 3);
  std::ifstream in(plain, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  gzFile gz = gzopen(path.c_str(), "wb");
  ASSERT_NE(gz, nullptr);
  ASSERT_EQ(gzwrite(gz, bytes.data(), static_cast<unsigned>(bytes.size())),
            static_cast<int>(bytes.size()));
  ASSERT_EQ(gzclose(gz), Z_OK);
  fs::remove(plain);
  // Its last bytes (the deflate end and the gzip trailer) gone; the header stays readable.
  fs::resize_file(path, fs::file_size(path) - 12);
}

class BatchE2E : public ScratchTest {
 protected:
  BatchE2E() : ScratchTest("batch_e2e", /*phantom=*/false) {}
};

TEST_F(BatchE2E, TenStudiesOneBrokenNineSucceedOneFailsClearlyAndTheExitCodeSaysSo) {
  ServerProcess server(scratch_ / "data", {"--workers", "2"});
  std::vector<std::string> args = {"submit"};
  for (int i = 1; i <= 10; ++i) {
    const fs::path dir = scratch_ / ("study" + std::to_string(i));
    fs::create_directories(dir);
    if (i == 7) {
      WriteTruncatedNiftiGz(dir / "broken.nii.gz");
    } else {
      WriteTinyNifti(dir / "scan.nii", 12, 10, 8, i);
    }
    args.push_back(dir.string());
  }
  // A folder with no volume in it: reported and skipped, not a failure of the batch.
  fs::create_directories(scratch_ / "empty");
  std::ofstream(scratch_ / "empty" / "notes.txt") << "no scan here\n";
  args.push_back((scratch_ / "empty").string());

  CliResult r = RunCli(server.address(), Args(args, Args({"--watch"}, kFastJob)), 180s);
  EXPECT_EQ(r.rc, 3) << r.out << r.err << server.Log();  // one study failed
  const std::vector<Row> rows = TableRows(r.out);
  ASSERT_EQ(rows.size(), 11u) << r.out;
  EXPECT_EQ(CountState(rows, "SUCCEEDED"), 9) << r.out;
  EXPECT_EQ(CountState(rows, "FAILED"), 1) << r.out;
  EXPECT_EQ(CountState(rows, "SKIPPED"), 1) << r.out;
  for (const auto& row : rows) {
    if (row.line.find("broken.nii.gz") != std::string::npos) {
      // The failed row has its job and says why.
      EXPECT_THAT(row.line, HasSubstr("FAILED")) << row.line;
      EXPECT_THAT(row.line, HasSubstr("broken.nii.gz: truncated")) << row.line;
      EXPECT_NE(row.job, "-");
    }
    if (row.line.find("empty") != std::string::npos) {
      EXPECT_THAT(row.line, HasSubstr("SKIPPED"));
      EXPECT_THAT(row.line, HasSubstr("no volume in it"));
      EXPECT_EQ(row.job, "-");
    }
  }
  EXPECT_THAT(r.err, HasSubstr("skipped " + (scratch_ / "empty").string() + ": no volume in it"));
  EXPECT_THAT(r.err, HasSubstr("10 studies: 1 FAILED, 9 SUCCEEDED; 1 skipped"));

  // The same jobs watched again, all at once: the same outcome and exit code.
  std::vector<std::string> watch = {"watch"};
  for (const auto& row : rows) {
    if (row.job != "-") watch.push_back(row.job);
  }
  ASSERT_EQ(watch.size(), 11u);
  CliResult w = RunCli(server.address(), watch, 60s);
  EXPECT_EQ(w.rc, 3) << w.out << w.err;
  const std::vector<Row> watched = TableRows(w.out);
  EXPECT_EQ(CountState(watched, "SUCCEEDED"), 9) << w.out;
  EXPECT_EQ(CountState(watched, "FAILED"), 1) << w.out;

  // Only the nine good jobs: exit code 0.
  std::vector<std::string> good = {"watch"};
  for (const auto& row : watched) {
    if (row.line.find("SUCCEEDED") != std::string::npos) good.push_back(row.job);
  }
  CliResult g = RunCli(server.address(), good, 60s);
  EXPECT_EQ(g.rc, 0) << g.out << g.err;
  EXPECT_EQ(CountState(TableRows(g.out), "SUCCEEDED"), 9) << g.out;
}

TEST_F(BatchE2E, EachFindsVolumeFilesAndOneStudyPerDicomSeriesAndSkipsAnEmptyFolder) {
  ServerProcess server(scratch_ / "data", {"--workers", "2"});
  const fs::path each = scratch_ / "incoming";
  fs::create_directories(each / "a");
  fs::create_directories(each / "c");
  WriteTinyNifti(each / "a" / "scan.nii", 12, 10, 8, 1);
  WriteTinyNifti(each / "b.nii", 12, 10, 8, 2);
  // Two series in one folder (files interleaved by name): one job each.
  testing::SliceSpec slice;
  slice.rows = 10;
  slice.columns = 12;
  slice.series_uid = "1.2.826.0.1.3680043.9.7777.101";
  testing::WriteSeries(each / "c", slice, std::vector<double>(5, 1.0), {}, "x");
  slice.series_uid = "1.2.826.0.1.3680043.9.7777.202";
  slice.value = [](int i, int j) { return 3 * i + j; };
  testing::WriteSeries(each / "c", slice, std::vector<double>(5, 1.0), {}, "y");
  fs::create_directories(each / "d-empty");

  CliResult r = RunCli(server.address(), Args({"submit", "--each", each.string()}, kFastJob));
  ASSERT_EQ(r.rc, 0) << r.out << r.err << server.Log();
  const std::vector<Row> rows = TableRows(r.out);
  ASSERT_EQ(rows.size(), 5u) << r.out;
  EXPECT_EQ(CountState(rows, "QUEUED") + CountState(rows, "RUNNING"), 4) << r.out;
  EXPECT_EQ(CountState(rows, "SKIPPED"), 1) << r.out;
  EXPECT_THAT(r.out, HasSubstr("series ...7777.101, 6 files"));
  EXPECT_THAT(r.out, HasSubstr("series ...7777.202, 6 files"));

  std::vector<std::string> watch = {"watch"};
  for (const auto& row : rows) {
    if (row.job != "-") watch.push_back(row.job);
  }
  CliResult w = RunCli(server.address(), watch, 120s);
  EXPECT_EQ(w.rc, 0) << w.out << w.err << server.Log();
  EXPECT_EQ(CountState(TableRows(w.out), "SUCCEEDED"), 4) << w.out;
  // Several jobs at once: lines prefixed by each job's id, every job reaching its end.
  for (size_t i = 1; i < watch.size(); ++i) {
    EXPECT_THAT(w.err, HasSubstr(watch[i] + " SUCCEEDED")) << w.err;
  }
}

TEST_F(BatchE2E, AnEachFolderWithNoVolumeAnywhereIsAUsageError) {
  ServerProcess server(scratch_ / "data");
  fs::create_directories(scratch_ / "nothing" / "x");
  std::ofstream(scratch_ / "nothing" / "readme.txt") << "no scan\n";
  CliResult r =
      RunCli(server.address(), {"submit", "--each", (scratch_ / "nothing").string()}, 30s);
  EXPECT_EQ(r.rc, 2) << r.out << r.err;
  EXPECT_THAT(r.err, HasSubstr("no volume found"));
}

}  // namespace
}  // namespace decima::e2e
