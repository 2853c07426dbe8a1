#include <signal.h>
#include <sys/resource.h>

#include <fstream>
#include <thread>

#include "client/client_lib.h"
#include "client/dicomweb.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/process.h"
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

// A file that vanished after it was listed, or a folder where a file was listed, is an error
// that names it; neither is hashed as if it were empty.
TEST(HashInputsTest, AFileThatCannotBeReadIsAnErrorNamingIt) {
  fs::path d = testing::MakeScratchDir("hash_broken");
  std::string err;
  std::vector<InputFile> gone{{"gone.dcm", d / "gone.dcm", 0, ""}};
  EXPECT_FALSE(HashInputs(&gone, &err));
  EXPECT_THAT(err, HasSubstr("gone.dcm"));
  EXPECT_THAT(err, HasSubstr("cannot open"));
  fs::create_directories(d / "folder.dcm");
  std::vector<InputFile> folder{{"folder.dcm", d / "folder.dcm", 0, ""}};
  err.clear();
  EXPECT_FALSE(HashInputs(&folder, &err));
  EXPECT_THAT(err, HasSubstr("folder.dcm"));
  EXPECT_THAT(err, HasSubstr("read error"));
  EXPECT_TRUE(folder[0].sha256.empty());
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

TEST(HeaderDataFilesTest, MetaImageAndNrrdHeadersBringTheirDataFiles) {
  fs::path d = testing::MakeScratchDir("headers");
  std::ofstream(d / "a.mhd") << "ObjectType = Image\nNDims = 3\nElementDataFile = a.zraw\n";
  std::ofstream(d / "a.zraw") << "zz";
  std::vector<InputFile> files;
  std::string err;
  ASSERT_TRUE(CollectInputs(d / "a.mhd", &files, &err)) << err;
  ASSERT_TRUE(AddHeaderDataFiles(&files, &err)) << err;
  ASSERT_EQ(files.size(), 2u);
  EXPECT_EQ(files[1].name, "a.zraw");
  EXPECT_EQ(files[1].size, 2);

  fs::create_directories(d / "data");
  std::ofstream(d / "b.nhdr") << "NRRD0004\ntype: short\ndata file: data/b.raw\n\n";
  std::ofstream(d / "data" / "b.raw") << "1234";
  ASSERT_TRUE(CollectInputs(d / "b.nhdr", &files, &err)) << err;
  ASSERT_TRUE(AddHeaderDataFiles(&files, &err)) << err;
  ASSERT_EQ(files.size(), 2u);
  EXPECT_EQ(files[1].name, "data/b.raw");

  std::ofstream(d / "c.nhdr") << "NRRD0004\ndata file: LIST\ns1.raw\ns2.raw\n";
  std::ofstream(d / "s1.raw") << "1";
  std::ofstream(d / "s2.raw") << "2";
  ASSERT_TRUE(CollectInputs(d / "c.nhdr", &files, &err)) << err;
  ASSERT_TRUE(AddHeaderDataFiles(&files, &err)) << err;
  EXPECT_EQ(files.size(), 3u);

  std::ofstream(d / "local.mhd") << "NDims = 3\nElementDataFile = LOCAL\n";
  ASSERT_TRUE(CollectInputs(d / "local.mhd", &files, &err)) << err;
  ASSERT_TRUE(AddHeaderDataFiles(&files, &err)) << err;
  EXPECT_EQ(files.size(), 1u);

  // Missing, outside the folder, pattern: refused with the header's name.
  std::ofstream(d / "m.mhd") << "ElementDataFile = missing.raw\n";
  ASSERT_TRUE(CollectInputs(d / "m.mhd", &files, &err));
  EXPECT_FALSE(AddHeaderDataFiles(&files, &err));
  EXPECT_THAT(err, HasSubstr("m.mhd"));
  EXPECT_THAT(err, HasSubstr("missing.raw"));
  std::ofstream(d / "o.mhd") << "ElementDataFile = ../etc/passwd\n";
  ASSERT_TRUE(CollectInputs(d / "o.mhd", &files, &err));
  EXPECT_FALSE(AddHeaderDataFiles(&files, &err));
  EXPECT_THAT(err, HasSubstr("outside"));
  std::ofstream(d / "p.nhdr") << "NRRD0004\ndata file: s%d.raw 1 2 1\n\n";
  ASSERT_TRUE(CollectInputs(d / "p.nhdr", &files, &err));
  EXPECT_FALSE(AddHeaderDataFiles(&files, &err));
  EXPECT_THAT(err, HasSubstr("pattern"));
}

// Issue 35 part 5: the earlier check looked at the data file only, so a linked folder on its path
// (`sub -> /etc`, then `sub/passwd`) uploaded the target. Every component below the header's
// folder is checked now.
TEST(HeaderDataFilesTest, ASymbolicLinkedFolderOnTheDataFilesPathIsRefused) {
  fs::path d = testing::MakeScratchDir("header_link");
  fs::create_directories(d / "outside");
  std::ofstream(d / "outside" / "passwd") << "root:x:0:0";
  fs::create_directories(d / "scan" / "real");
  fs::create_directory_symlink(d / "outside", d / "scan" / "sub");
  fs::create_directory_symlink(d / "outside", d / "scan" / "real" / "deeper");
  std::string err;
  for (const char* data : {"sub/passwd", "real/deeper/passwd", "real/../sub/passwd"}) {
    std::vector<InputFile> files;
    std::ofstream(d / "scan" / "h.mhd") << "NDims = 3\nElementDataFile = " << data << "\n";
    ASSERT_TRUE(CollectInputs(d / "scan" / "h.mhd", &files, &err)) << err;
    EXPECT_FALSE(AddHeaderDataFiles(&files, &err)) << data;
    EXPECT_THAT(err, HasSubstr("symbolic link")) << data;
    EXPECT_EQ(files.size(), 1u) << data;
  }
  // A real folder on the path is fine.
  std::ofstream(d / "scan" / "real" / "v.raw") << "ab";
  std::vector<InputFile> files;
  std::ofstream(d / "scan" / "h.mhd") << "NDims = 3\nElementDataFile = real/v.raw\n";
  ASSERT_TRUE(CollectInputs(d / "scan" / "h.mhd", &files, &err)) << err;
  ASSERT_TRUE(AddHeaderDataFiles(&files, &err)) << err;
  ASSERT_EQ(files.size(), 2u);
  EXPECT_EQ(files[1].name, "real/v.raw");
}

TEST(TerminalSafeTest, ControlCharactersAndBrokenUtf8AreEscapedPrintableTextIsKept) {
  EXPECT_EQ(TerminalSafe("scan.nii"), "scan.nii");
  EXPECT_EQ(TerminalSafe("t\xc3\xaate \xe2\x9c\x93"), "t\xc3\xaate \xe2\x9c\x93");  // UTF-8 kept
  EXPECT_EQ(TerminalSafe("\x1b]0;owned\x07"), "\\x1b]0;owned\\x07");
  EXPECT_EQ(TerminalSafe("a\nb\rc\td\x7f"), "a\\x0ab\\x0dc\\x09d\\x7f");
  EXPECT_EQ(TerminalSafe("\xc2\x9b"
                         "2J"),
            "\\u009b2J");  // C1 CSI as UTF-8
  EXPECT_EQ(TerminalSafe("\x9b"
                         "2J"),
            "\\x9b2J");                               // a raw 8-bit CSI byte
  EXPECT_EQ(TerminalSafe("\xe2\x82"), "\\xe2\\x82");  // cut sequence
  EXPECT_EQ(TerminalSafe("\xc0\xaf"), "\\xc0\\xaf");  // overlong '/'
}

TEST(Sha256HexOfTest, HashesInMemory) {
  EXPECT_EQ(Sha256HexOf(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  EXPECT_EQ(Sha256HexOf("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
}

// A WADO-RS server in python3 (http.server) answering every GET with `parts` application/dicom
// parts of `part_mb` MiB each, written in 1 MiB pieces; stopped by PID.
class FakeWadoServer {
 public:
  FakeWadoServer(int parts, int part_mb) {
    port_ = testing::FreePort();
    const std::string script = R"(
import http.server, sys
parts, size = int(sys.argv[2]), int(sys.argv[3]) << 20
class H(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        b = b"b0und4ry"
        self.send_response(200)
        self.send_header("Content-Type", 'multipart/related; type="application/dicom"; boundary=' + b.decode())
        # HTTP/1.0 without Content-Length: the answer ends when the connection closes.
        self.end_headers()
        chunk = bytes(range(256)) * 4096
        for i in range(parts):
            self.wfile.write(b"--" + b + b"\r\nContent-Type: application/dicom\r\n\r\n")
            left = size
            while left > 0:
                n = min(left, len(chunk)); self.wfile.write(chunk[:n]); left -= n
            self.wfile.write(b"\r\n")
        self.wfile.write(b"--" + b + b"--\r\n")
    def log_message(self, *a): pass
http.server.HTTPServer(("127.0.0.1", int(sys.argv[1])), H).serve_forever()
)";
    pid_ = testing::Spawn({"/usr/bin/python3", "-c", script, std::to_string(port_),
                           std::to_string(parts), std::to_string(part_mb)},
                          "/dev/null");
    for (int i = 0; i < 100 && !TcpPortAnswers("127.0.0.1:" + std::to_string(port_),
                                               std::chrono::milliseconds(100));
         ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  }
  ~FakeWadoServer() {
    if (pid_ > 0) {
      kill(pid_, SIGKILL);
      testing::WaitExit(pid_, std::chrono::seconds(10));
    }
  }
  std::string url() const { return "http://127.0.0.1:" + std::to_string(port_) + "/dicom-web"; }

 private:
  int port_ = 0;
  pid_t pid_ = -1;
};

long PeakRssMb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss / 1024;
}

// Issue 35 part 7: the pull buffered the whole answer (600 MB -> 1.07 GB RSS). Parsed as it
// arrives, a 256 MiB answer raises the peak by far less than its size, and every part is
// written whole.
TEST(DicomWebPullTest, ALargeAnswerIsWrittenPartByPartWithoutBufferingIt) {
  if (!fs::exists("/usr/bin/python3")) GTEST_SKIP() << "python3 not installed";
  FakeWadoServer server(16, 16);
  const fs::path out = testing::MakeScratchDir("wado_pull");
  DicomWebPull pull;
  pull.base_url = server.url();
  pull.study_uid = "1.2.3";
  const long before = PeakRssMb();
  DicomWebResult result;
  std::string err;
  ASSERT_TRUE(PullDicomWeb(pull, out, &result, &err)) << err;
  const long grew = PeakRssMb() - before;
  EXPECT_EQ(result.instances, 16);
  EXPECT_EQ(result.bytes, int64_t{256} << 20);
  for (int i = 1; i <= 16; ++i) {
    char name[16];
    std::snprintf(name, sizeof name, "%05d.dcm", i);
    ASSERT_EQ(fs::file_size(out / name), uintmax_t{16} << 20) << name;
  }
  std::ifstream first(out / "00001.dcm", std::ios::binary);
  char head[4];
  first.read(head, 4);
  EXPECT_EQ(std::string(head, 4), std::string("\x00\x01\x02\x03", 4)) << "the part's own bytes";
  EXPECT_LT(grew, 64) << "peak RSS grew by " << grew << " MB for a 256 MiB answer";
  std::printf("256 MiB WADO-RS answer: peak RSS +%ld MB, %.2f s\n", grew, result.seconds);
}

// The number of parts is limited: an answer with more than max_instances parts is refused.
TEST(DicomWebPullTest, AnAnswerWithMorePartsThanTheLimitIsRefused) {
  if (!fs::exists("/usr/bin/python3")) GTEST_SKIP() << "python3 not installed";
  FakeWadoServer server(20, 0);
  DicomWebPull pull;
  pull.base_url = server.url();
  pull.study_uid = "1.2.3";
  pull.max_instances = 5;
  DicomWebResult result;
  std::string err;
  EXPECT_FALSE(PullDicomWeb(pull, testing::MakeScratchDir("wado_limit"), &result, &err));
  EXPECT_THAT(err, HasSubstr("more than 5 instances"));
}

TEST(KeepDicomFilesTest, DropsDicomdirAndFilesWithoutTheMarker) {
  fs::path d = testing::MakeScratchDir("dicomfilter");
  std::string dicm(128, '\0');
  dicm += "DICM";
  dicm += std::string(16, 'x');
  std::ofstream(d / "IM0001", std::ios::binary) << dicm;
  std::ofstream(d / "DICOMDIR", std::ios::binary) << dicm;  // a directory record, not an image
  std::ofstream(d / "SHA256SUMS") << "abc  IM0001\n";
  std::vector<InputFile> files;
  std::string err;
  ASSERT_TRUE(CollectInputs(d, &files, &err)) << err;
  ASSERT_EQ(files.size(), 3u);
  std::vector<std::string> dropped = KeepDicomFiles(&files);
  ASSERT_EQ(files.size(), 1u);
  EXPECT_EQ(files[0].name, "IM0001");
  EXPECT_THAT(dropped, ::testing::UnorderedElementsAre("DICOMDIR", "SHA256SUMS"));
}

TEST(ProgressTest, OverallFractionIsMonotonicAcrossStagesAndTheBarHasAnEta) {
  double last = -1;
  for (const char* stage : {"load", "segment", "tetra", "simplify", "write", "render", "diff"}) {
    for (double f : {0.0, 0.5, 1.0}) {
      const double o = OverallFraction(stage, f);
      EXPECT_GE(o, last) << stage << " " << f;
      last = o;
    }
  }
  EXPECT_DOUBLE_EQ(OverallFraction("diff", 1), 1.0);
  EXPECT_DOUBLE_EQ(OverallFraction("load", 0), 0.0);
  // The curve stage counts only for a job that asked for it, and then it is long: the bar does
  // not sit at 99 % while it runs.
  last = -1;
  for (const char* stage :
       {"load", "segment", "tetra", "simplify", "write", "render", "curve", "diff"}) {
    for (double f : {0.0, 0.5, 1.0}) {
      const double o = OverallFraction(stage, f, /*with_curve=*/true);
      EXPECT_GE(o, last) << stage << " " << f;
      last = o;
    }
  }
  EXPECT_DOUBLE_EQ(OverallFraction("diff", 1, true), 1.0);
  EXPECT_LT(OverallFraction("curve", 0, true), 0.5);
  EXPECT_GT(OverallFraction("curve", 1, true), 0.95);
  EXPECT_DOUBLE_EQ(OverallFraction("render", 1), OverallFraction("diff", 0));
  v1::Job job;
  EXPECT_FALSE(JobWithCurve(job));
  job.mutable_spec()->add_outputs("curve");
  EXPECT_TRUE(JobWithCurve(job));
  // Simplify dominates the measured weights: half of it is well past a third overall.
  EXPECT_GT(OverallFraction("simplify", 0.5), 0.35);
  EXPECT_EQ(FormatDuration(65), "1:05");
  EXPECT_EQ(FormatDuration(3 * 3600 + 62), "3:01:02");
  EXPECT_EQ(FormatBytes(15600000), "15.6 MB");
  v1::Progress p;
  p.set_stage("simplify");
  p.set_fraction(0.5);
  const std::string bar = OverallBar(p, 20, 10);
  EXPECT_THAT(bar, HasSubstr("elapsed 0:20"));
  EXPECT_THAT(bar, HasSubstr("ETA "));
  p.set_stage("load");
  p.set_fraction(0);
  EXPECT_THAT(OverallBar(p, 1, 10), ::testing::Not(HasSubstr("ETA")));  // too early to say
}

// An event with the job's own figures (its stage model and measured rates) drives the bar and
// the ETA from the first event after load, and the ETA counts down between events.
TEST(ProgressTest, TheJobsOwnFractionAndEtaWinOverTheFixedWeights) {
  v1::Progress p;
  p.set_stage("load");
  p.set_fraction(1);
  EXPECT_LT(JobFraction(p), 0.01);  // the fixed weights: load is nothing
  p.set_overall_fraction(0.25);
  p.set_eta_seconds(90);
  EXPECT_DOUBLE_EQ(JobFraction(p), 0.25);
  const std::string bar = OverallBar(p, 1, 8);
  EXPECT_THAT(bar, HasSubstr("[##......]  25% load 100%"));
  EXPECT_THAT(bar, HasSubstr("ETA 1:30"));  // not "too early to say" at 1 s
  EXPECT_THAT(OverallBar(p, 31, 8, false, 30), HasSubstr("ETA 1:00"));
  EXPECT_THAT(OverallBar(p, 200, 8, false, 199), HasSubstr("ETA 0:00"));  // never negative
}

// A field reproduced exactly has an infinite PSNR, which metrics.json writes as null: shown as
// "inf (rmse 0)", not as the 0 dB that strtod makes of "null".
TEST(FidelityLinesTest, ShowsTheFiguresAndAnExactFieldAsInfinitePsnr) {
  EXPECT_EQ(FidelityLines(R"({"rmse": 2.5, "psnr_db": 63.7, "mean_dice": 1.0, "diff1": 0.017})"),
            (std::vector<std::string>{"diff1 0.017", "psnr_db 63.7", "mean_dice 1"}));
  EXPECT_EQ(FidelityLines(R"({"rmse": 0.0, "psnr_db": null, "mean_dice": 1.0, "diff1": 0})"),
            (std::vector<std::string>{"diff1 0", "psnr_db inf (rmse 0)", "mean_dice 1"}));
  EXPECT_EQ(FidelityLines(R"({"rmse": 3.0, "psnr_db": null})"),
            (std::vector<std::string>{"psnr_db n/a"}));
  EXPECT_TRUE(FidelityLines("{}").empty());
}

TEST(SummaryTest, ReadsTheReductionFromMetricsAndWarnsWhenShort) {
  v1::Job job;
  job.mutable_spec()->set_target_reduction(0.95);
  job.set_metrics_json(
      R"({"simplification": {"target_reduction": 0.95, "achieved_reduction": 0.81,)"
      R"( "reached_target": false, "stop_message": "no collapse below tolerance",)"
      R"( "cells_before": 1000, "cells_after": 190}})");
  job.add_artifacts()->set_size_bytes(3000);
  job.add_artifacts()->set_size_bytes(1000);
  const JobSummary s = SummarizeJob(job, 2000);
  EXPECT_DOUBLE_EQ(s.achieved_reduction, 0.81);
  EXPECT_FALSE(s.reached_target);
  EXPECT_EQ(s.cells_before, 1000);
  EXPECT_EQ(s.cells_after, 190);
  EXPECT_EQ(s.artifact_bytes, 4000);
  EXPECT_EQ(s.stop_message, "no collapse below tolerance");
  const std::vector<std::string> lines = SummaryLines(s);
  ASSERT_EQ(lines.size(), 3u);
  EXPECT_THAT(lines[0], HasSubstr("81.0%"));
  EXPECT_THAT(lines[1], HasSubstr("2.0x"));
  EXPECT_THAT(lines[2], HasSubstr("WARNING"));
  EXPECT_THAT(lines[2], HasSubstr("exit code 10"));
  job.set_metrics_json(R"({"achieved_reduction": 0.5, "reached_target": true})");
  EXPECT_TRUE(SummarizeJob(job, 0).reached_target);
  EXPECT_EQ(SummaryLines(SummarizeJob(job, 0)).size(), 2u);
}

TEST(ParseJobStateTest, AnyCase) {
  v1::JobState s;
  ASSERT_TRUE(ParseJobState("succeeded", &s));
  EXPECT_EQ(s, v1::SUCCEEDED);
  ASSERT_TRUE(ParseJobState("Failed", &s));
  EXPECT_EQ(s, v1::FAILED);
  EXPECT_FALSE(ParseJobState("done", &s));
  EXPECT_FALSE(ParseJobState("job_state_unspecified", &s));
}

}  // namespace
}  // namespace decima::client
