// Every command line README.md shows (its indented code blocks) either runs here exactly as
// written - with a tiny volume for scan.nii.gz, the shared DICOM series for dicom-folder/, a
// folder of two tiny studies and an empty one for studies/, a scratch folder for result/ and
// the data dir, a free port, and the last job for JOB - or is
// listed below with the reason it cannot run inside a unit-test budget. A new command line in
// the README that is in neither list fails this test.
#include <signal.h>

#include <fstream>
#include <sstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using namespace std::chrono_literals;

// Command lines of the indented (4-space) code blocks, continuation lines joined.
std::vector<std::string> ReadmeCommands(const fs::path& readme) {
  std::ifstream in(readme);
  std::vector<std::string> out;
  std::string line, pending;
  bool in_fence = false;
  while (std::getline(in, line)) {
    if (line.rfind("```", 0) == 0) in_fence = !in_fence;
    if (in_fence || line.rfind("    ", 0) != 0) {
      if (!pending.empty()) out.push_back(pending);
      pending.clear();
      continue;
    }
    std::string text = line.substr(line.find_first_not_of(' '));
    const bool continued = !text.empty() && text.back() == '\\';
    if (continued) text.pop_back();
    pending += (pending.empty() ? "" : " ") + text;
    if (!continued) {
      out.push_back(pending);
      pending.clear();
    }
  }
  if (!pending.empty()) out.push_back(pending);
  return out;
}

std::vector<std::string> Split(const std::string& s) {
  std::istringstream in(s);
  std::vector<std::string> out;
  for (std::string w; in >> w;) out.push_back(w);
  return out;
}

// Command lines that cannot run in a ctest, by their start, with the reason.
const std::pair<const char*, const char*> kNotRunHere[] = {
    {"deploy/demo.sh", "installs packages as root and runs the 35 M-cell MRI job (many minutes)"},
    {"deploy/build-and-test.sh", "is CI itself: it runs this test"},
    {"DECIMA_SANITIZE=", "is a second full build under sanitizers (CI runs it)"},
    {"cmake ", "configures or builds another build tree (CI's sanitizer and fuzz jobs)"},
    {"TSAN_OPTIONS=", "needs the ThreadSanitizer build tree"},
    {"CC=clang", "configures the clang fuzz build tree"},
    {"ninja -C build-fuzz", "needs the clang fuzz build tree"},
    {"mkdir -p /tmp/vtu-corpus", "runs libFuzzer until stopped (fuzz build tree)"},
    {"tests/fuzz/campaign.sh", "runs every libFuzzer target for SECONDS (fuzz build tree)"},
    {"build/tests/bench/decima-bench",
     "is a benchmark: it repeats each stage 3 times on the CT head"},
    {"build/tests/bench/decima-compare", "runs VTK's decimation in python: minutes per row"},
    {"tests/bench/make_clinical_ct.py",
     "writes a 59 M-voxel CT in about 40 s (make_clinical_ct_test runs it on a tiny volume)"},
    {"decima-server --listen 0.0.0.0:50051 --data-dir /mnt/shared/decima",
     "needs a PostgreSQL database and a shared folder (scale_e2e_test runs three replicas on a "
     "real PostgreSQL)"},
};

TEST(ReadmeCommands, EveryCommandLineRunsOrSaysWhyNot) {
  const fs::path root = DECIMA_SOURCE_DIR;
  const std::vector<std::string> commands = ReadmeCommands(root / "README.md");
  ASSERT_GE(commands.size(), 10u);
  const fs::path scratch = testing::MakeScratchDir("readme");
  const fs::path scan = scratch / "scan.nii.gz";
  WriteTinyNifti(scratch / "scan.nii", 12, 10, 8);
  // The README names a .nii.gz: the same bytes, gzip-compressed.
  ASSERT_EQ(
      std::system(("gzip -c " + (scratch / "scan.nii").string() + " > " + scan.string()).c_str()),
      0);
  auto dicom = testing::SharedDataFile("ct-head-256x256x113-dicom");
  const fs::path studies = scratch / "studies";
  fs::create_directories(studies / "a");
  fs::create_directories(studies / "empty");
  WriteTinyNifti(studies / "a" / "scan.nii", 12, 10, 8, 1);
  WriteTinyNifti(studies / "b.nii", 12, 10, 8, 2);

  std::unique_ptr<ServerProcess> server;
  std::string last_job;
  int ran = 0;
  for (const std::string& line : commands) {
    bool skipped = false;
    for (const auto& [prefix, why] : kNotRunHere) {
      if (line.rfind(prefix, 0) == 0) {
        std::printf("not run: %s\n  because it %s\n", line.c_str(), why);
        skipped = true;
      }
    }
    if (skipped) continue;
    std::vector<std::string> argv = Split(line);
    if (!argv.empty() && argv.back() == "&") argv.pop_back();
    ASSERT_FALSE(argv.empty());
    if (argv[0] == "build/server/decima-server") {
      // As written, on a free port and a scratch data dir instead of /var/lib/decima.
      std::vector<std::string> extra;
      for (size_t i = 1; i < argv.size(); ++i) {
        if (argv[i] == "--listen" || argv[i] == "--data-dir") {
          ++i;
          continue;
        }
        extra.push_back(argv[i]);
      }
      server = std::make_unique<ServerProcess>(scratch / "data", extra);
      std::printf("ran: %s (on %s)\n", line.c_str(), server->address().c_str());
      ++ran;
      continue;
    }
    ASSERT_EQ(argv[0], "build/client/decima")
        << "README.md shows a command line this test neither runs nor explains: " << line;
    ASSERT_NE(server, nullptr) << "the README uses the client before starting a server";
    std::vector<std::string> args;
    bool creates_job = false, waits = false, batch = false;
    for (size_t i = 1; i < argv.size(); ++i) {
      std::string a = argv[i];
      if (a == "scan.nii.gz") a = scan.string();
      if (a == "result/") a = (scratch / "result").string() + "/";
      if (a == "studies/") a = studies.string() + "/";
      if (a == "--each") batch = true;
      if (a == "JOB") a = last_job;
      if (a == "dicom-folder/") {
        if (!dicom) {
          std::printf("not run: %s\n  because ../shared/data is absent\n", line.c_str());
          args.clear();
          break;
        }
        a = dicom->string() + "/";
      }
      if (a == "submit") creates_job = true;
      if (a == "--watch" || a == "--out") waits = true;
      args.push_back(a);
    }
    if (args.empty()) continue;
    if (line.find(" JOB") != std::string::npos) {
      ASSERT_FALSE(last_job.empty()) << line << ": JOB before any job was watched to its end";
    }
    CliResult r = RunCli(server->address(), args, 300s);
    std::printf("ran: %s -> exit %d\n", line.c_str(), r.rc);
    EXPECT_EQ(r.rc, 0) << line << "\n" << r.err << server->Log();
    ++ran;
    // A batch prints a table of jobs, not one job name.
    if (creates_job && !batch && r.rc == 0) {
      const std::string job = FirstLine(r.out);
      EXPECT_EQ(job.rfind("jobs/", 0), 0u) << r.out;
      if (!waits) {
        // Queued only (a full-size DICOM job): cancelled so the next commands do not wait.
        EXPECT_EQ(RunCli(server->address(), {"cancel", job}).rc, 0);
      } else {
        last_job = job;
      }
    }
  }
  EXPECT_GE(ran, 8);
}

}  // namespace
}  // namespace decima::e2e
