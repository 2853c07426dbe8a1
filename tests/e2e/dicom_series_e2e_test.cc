// The received-series history end to end: a real decima-server with the C-STORE receiver, DCMTK's
// storescu as the senders and storescp as each route's PACS, the real `decima` CLI. A tiny
// synthetic series (4 slices of 16 x 16) so that its job runs in seconds.
#include <signal.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/process.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;

const fs::path kStorescu = "/usr/bin/storescu";
const fs::path kStorescp = "/usr/bin/storescp";

std::string Slurp(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

int CountFiles(const fs::path& dir) {
  int n = 0;
  std::error_code ec;
  for (const auto& e : fs::recursive_directory_iterator(dir, ec)) n += e.is_regular_file();
  return n;
}

// A storescp that stores what it receives under `dir`; stopped by its PID.
class Pacs {
 public:
  Pacs(const fs::path& dir, const std::string& aet) : dir_(dir), port_(testing::FreePort()) {
    fs::create_directories(dir_ / "in");
    pid_ = testing::Spawn(
        {kStorescp.string(), "-aet", aet, "-od", (dir_ / "in").string(), std::to_string(port_)},
        (dir_ / "storescp.log").string());
  }
  ~Pacs() {
    if (pid_ > 0) {
      ::kill(pid_, SIGTERM);
      testing::WaitExit(pid_, std::chrono::seconds(10));
    }
  }
  int port() const { return port_; }
  int received() const { return CountFiles(dir_ / "in"); }

 private:
  fs::path dir_;
  int port_;
  pid_t pid_ = -1;
};

class DicomSeriesE2eTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!fs::exists(kStorescu) || !fs::exists(kStorescp)) {
      GTEST_SKIP() << "storescu / storescp (Debian package dcmtk) are not installed";
    }
    dir_ = testing::MakeScratchDir("dicom_series_e2e");
    // The series: slices at z = 0, 2, 4, 6 mm; slice s holds value(i, j) + 100 s.
    testing::SliceSpec base;
    base.rows = 16;
    base.columns = 16;
    base.pixel_spacing = {1.0, 1.0};
    base.value = [](int i, int j) { return (i - 8) * (i - 8) + (j - 8) * (j - 8) < 20 ? 900 : 50; };
    fs::create_directories(dir_ / "series");
    slices_ = testing::WriteSeries(dir_ / "series", base, {2, 2, 2});
    ASSERT_EQ(slices_.size(), 4u);
    series_uid_ = base.series_uid;
  }

  // storescu from `ae` to the server's receiver; its exit code, the log in *log.
  int Send(const std::string& ae, const std::vector<fs::path>& files, std::string* log = nullptr) {
    const fs::path out = dir_ / ("storescu-" + std::to_string(sends_++) + ".log");
    std::vector<std::string> argv = {
        kStorescu.string(),         "-v", "-aet", ae, "-aec", "DECIMA", "127.0.0.1",
        std::to_string(dicom_port_)};
    for (const auto& f : files) argv.push_back(f.string());
    const int rc = testing::WaitExit(testing::Spawn(argv, out.string()), std::chrono::seconds(60));
    if (log != nullptr) *log = Slurp(out);
    return rc;
  }

  // `decima series -o json --all`: the receives of `ae`, newest first.
  std::vector<nlohmann::json> Receives(const std::string& address, const std::string& ae) {
    CliResult r = RunCli(address, {"series", "--all", "-o", "json"});
    EXPECT_EQ(r.rc, 0) << r.err;
    std::vector<nlohmann::json> out;
    std::istringstream lines(r.out);
    for (std::string line; std::getline(lines, line);) {
      if (line.empty()) continue;
      auto j = nlohmann::json::parse(line);
      if (j.value("calling_ae", "") == ae) out.push_back(j);
    }
    return out;
  }

  // Waits (at most `seconds`) until `ae`'s newest receive is in `state`; that receive.
  nlohmann::json WaitForState(const std::string& address, const std::string& ae,
                              const std::string& state, int seconds) {
    nlohmann::json newest;
    WaitFor(
        [&] {
          auto r = Receives(address, ae);
          if (r.empty()) return false;
          newest = r.front();
          return newest.value("state", "") == state;
        },
        std::chrono::seconds(seconds));
    EXPECT_EQ(newest.value("state", ""), state) << newest.dump();
    return newest;
  }

  fs::path dir_;
  std::vector<fs::path> slices_;
  std::string series_uid_;
  int dicom_port_ = 0;
  int sends_ = 0;
};

// Two senders of one series, each on its own route with its own PACS. ORTHANC's series misses a
// slice; EVIL sends that slice: it completes nothing of ORTHANC's (EVIL's is its own series).
// ORTHANC's own re-send completes it: the earlier INCOMPLETE receive becomes COMPLETE, the new
// one goes QUEUED -> RUNNING -> SUCCEEDED -> SENT, its job is ORTHANC's principal's, and the
// results go to ORTHANC's PACS only. EVIL's series, once complete, gets its own job whose
// results go to EVIL's PACS. Each association has its own id: the two receives of ORTHANC's
// series (one per association) show theirs in `decima series` (-o json and -o wide), the
// server's log names each when it is accepted, and the audit records of the job and of its
// results' send carry the completing association's.
TEST_F(DicomSeriesE2eTest, EachSenderCompletesOnlyItsOwnSeriesAndGetsItsOwnResults) {
  Pacs pacs_a(dir_ / "pacs-a", "PACSA"), pacs_b(dir_ / "pacs-b", "PACSB");
  dicom_port_ = testing::FreePort();
  ASSERT_GT(dicom_port_, 0);
  const std::string spec = R"("spec": {"regions": 2, "targetReduction": 0.3, "imageSize": 32,
                                       "views": ["anterior"]})";
  {
    std::ofstream routes(dir_ / "routes.json");
    routes << R"({"refuse_unknown_calling_ae": true, "routes": [
      {"name": "a", "calling_ae": "ORTHANC", )"
           << spec << R"(, "destination": {"dicom": "127.0.0.1:)" << pacs_a.port()
           << R"(", "aet": "PACSA"}},
      {"name": "b", "calling_ae": "EVIL", )"
           << spec << R"(, "destination": {"dicom": "127.0.0.1:)" << pacs_b.port()
           << R"(", "aet": "PACSB"}}]})";
  }
  const fs::path audit = dir_ / "audit.log";
  ServerProcess server(
      dir_ / "data", {"--dicom-listen", "127.0.0.1:" + std::to_string(dicom_port_),
                      "--dicom-min-free-mb", "0", "--dicom-quiet-seconds", "0.5", "--dicom-routes",
                      (dir_ / "routes.json").string(), "--audit-log", audit.string()});
  const std::string addr = server.address();

  std::string log;
  ASSERT_EQ(Send("ORTHANC", {slices_[0], slices_[1], slices_[3]}, &log), 0) << log;
  nlohmann::json first = WaitForState(addr, "ORTHANC", "INCOMPLETE", 30 * kSlowdown);
  EXPECT_THAT(first.value("reason", ""), HasSubstr("1 slice(s) missing"));
  ASSERT_EQ(Send("EVIL", {slices_[2]}, &log), 0) << log;
  WaitForState(addr, "EVIL", "INCOMPLETE", 30 * kSlowdown);
  // EVIL's slice did not complete ORTHANC's series: no job, ORTHANC still waits.
  std::vector<nlohmann::json> orthanc = Receives(addr, "ORTHANC");
  ASSERT_EQ(orthanc.size(), 1u);
  EXPECT_EQ(orthanc[0].value("state", ""), "INCOMPLETE");
  EXPECT_EQ(orthanc[0].value("instance_count", 0), 3);
  EXPECT_TRUE(RunCli(addr, {"list", "--all", "-o", "json"}).out.empty());

  // ORTHANC's re-send completes its series.
  ASSERT_EQ(Send("ORTHANC", {slices_[2]}, &log), 0) << log;
  nlohmann::json sent = WaitForState(addr, "ORTHANC", "SENT", 180 * kSlowdown);
  EXPECT_THAT(sent.value("send_status", ""), HasSubstr("sent"));
  EXPECT_EQ(sent.value("instance_count", 0), 4);
  EXPECT_EQ(sent.value("route", ""), "a");
  const std::string job = sent.value("job", "");
  ASSERT_FALSE(job.empty());
  EXPECT_EQ(GetJob(addr, job).creator(), "dicom:ORTHANC");
  EXPECT_EQ(GetJob(addr, job).state(), v1::SUCCEEDED);
  orthanc = Receives(addr, "ORTHANC");
  ASSERT_EQ(orthanc.size(), 2u);  // the history: both receives
  EXPECT_EQ(orthanc[1].value("state", ""), "COMPLETE");
  EXPECT_EQ(orthanc[1].value("job", ""), job);
  // One id per association: the first receive's is the first send's, the completing one's the
  // re-send's; EVIL's association had another.
  const std::string first_id = orthanc[1].value("association_id", "");
  const std::string second_id = orthanc[0].value("association_id", "");
  EXPECT_THAT(first_id, ::testing::MatchesRegex("[0-9a-f]{16}"));
  EXPECT_THAT(second_id, ::testing::MatchesRegex("[0-9a-f]{16}"));
  EXPECT_NE(first_id, second_id);
  EXPECT_EQ(first_id, first.value("association_id", ""));
  const std::string evil_id = Receives(addr, "EVIL").at(0).value("association_id", "");
  EXPECT_THAT(evil_id, ::testing::MatchesRegex("[0-9a-f]{16}"));
  EXPECT_NE(evil_id, first_id);
  EXPECT_NE(evil_id, second_id);
  for (const std::string& id : {first_id, second_id}) {
    EXPECT_THAT(server.Log(), HasSubstr("association " + id +
                                        " accepted from 127.0.0.1: calling AE 'ORTHANC', "
                                        "called AE 'DECIMA'"));
  }
  CliResult wide = RunCli(addr, {"series", "-o", "wide"});
  ASSERT_EQ(wide.rc, 0) << wide.err;
  EXPECT_THAT(wide.out, HasSubstr("ASSOCIATION"));
  EXPECT_THAT(wide.out, HasSubstr(first_id));
  EXPECT_THAT(wide.out, HasSubstr(second_id));
  // The audit records of the job queued from the completing receive and of its results' send.
  const std::string audited = Slurp(audit);
  EXPECT_THAT(audited, HasSubstr("\"rpc\":\"DicomCreateJob\",\"resource\":\"" + job +
                                 "\",\"association\":\"" + second_id + "\""));
  EXPECT_THAT(audited, HasSubstr("\"rpc\":\"DicomSendResults\",\"resource\":\"" + job +
                                 "\",\"association\":\"" + second_id + "\""));
  EXPECT_GT(pacs_a.received(), 0);
  EXPECT_EQ(pacs_b.received(), 0);
  // The states on the way were logged by the server as they happened.
  EXPECT_THAT(server.Log(), HasSubstr("QUEUED from DICOM series " + series_uid_));

  // EVIL's own series, once complete, is EVIL's job with EVIL's results.
  const int at_a = pacs_a.received();
  ASSERT_EQ(Send("EVIL", {slices_[0], slices_[1], slices_[3]}, &log), 0) << log;
  nlohmann::json evil = WaitForState(addr, "EVIL", "SENT", 180 * kSlowdown);
  EXPECT_NE(evil.value("job", ""), job);
  EXPECT_EQ(GetJob(addr, evil.value("job", "")).creator(), "dicom:EVIL");
  EXPECT_GT(pacs_b.received(), 0);
  EXPECT_EQ(pacs_a.received(), at_a);
}

// `decima series delete` removes a series' waiting instances and their blobs; the history
// shows it DELETED, and a second delete finds nothing.
TEST_F(DicomSeriesE2eTest, SeriesDeleteRemovesTheWaitingInstancesAndTheirBlobs) {
  dicom_port_ = testing::FreePort();
  ASSERT_GT(dicom_port_, 0);
  ServerProcess server(dir_ / "data", {"--dicom-listen", "127.0.0.1:" + std::to_string(dicom_port_),
                                       "--dicom-min-free-mb", "0", "--dicom-quiet-seconds", "0.5"});
  const std::string addr = server.address();
  std::string log;
  ASSERT_EQ(Send("JUNK", {slices_[0]}, &log), 0) << log;
  WaitForState(addr, "JUNK", "INCOMPLETE", 30 * kSlowdown);
  const fs::path blobs = dir_ / "data" / "blobs";
  const int with_instance = CountFiles(blobs);
  ASSERT_GT(with_instance, 0);
  CliResult r = RunCli(addr, {"series", "delete", series_uid_, "--from", "JUNK"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("deleted 1 waiting instance(s) of series " + series_uid_));
  EXPECT_EQ(CountFiles(blobs), with_instance - 1);
  std::vector<nlohmann::json> junk = Receives(addr, "JUNK");
  ASSERT_EQ(junk.size(), 1u);
  EXPECT_EQ(junk[0].value("state", ""), "DELETED");
  r = RunCli(addr, {"series", "delete", series_uid_});
  EXPECT_NE(r.rc, 0);
  EXPECT_THAT(r.err, HasSubstr("NOT_FOUND"));
}

}  // namespace
}  // namespace decima::e2e
