// A graceful restart loses no work (issue 35, part 6), end to end with real server processes:
// a job stopped at a stage boundary (SIGTERM: drained and requeued; SIGKILL: the server and its
// job child die, the restarted server recovers the job) resumes from that stage's checkpoint,
// and its outputs are identical to an uninterrupted run's. While the server drains, a watcher
// of the running job sees how long the drain has left.
#include <signal.h>

#include <atomic>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;
using Json = nlohmann::json;
using namespace std::chrono_literals;

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// metrics.json without what differs between two runs of one job by design: timings, memory and
// the stages resumed.
Json Comparable(const fs::path& metrics) {
  Json j = Json::parse(ReadFile(metrics), nullptr, false);
  // What depends on the clock or the machine: times, the ETA's forecasts, memory.
  for (const char* k : {"seconds", "eta", "peak_rss_mb", "stage_peak_rss_mb",
                        "stage_peak_rss_per_stage", "resumed_stages", "resumed_simplify_windows"}) {
    j.erase(k);
  }
  return j;
}

// Waits (bounded) until `job` ends on `server`, which it must have SUCCEEDED, and fetches its
// artifacts into `out`.
void ExpectSucceededAndFetch(const ServerProcess& server, const std::string& job,
                             const fs::path& out) {
  ASSERT_TRUE(WaitFor(
      [&] {
        const v1::JobState st = GetJob(server.address(), job).state();
        return st == v1::SUCCEEDED || st == v1::FAILED || st == v1::CANCELLED;
      },
      120s * kSlowdown))
      << server.Log();
  const v1::Job done = GetJob(server.address(), job);
  ASSERT_EQ(done.state(), v1::SUCCEEDED) << done.DebugString() << server.Log();
  const CliResult f = RunCli(server.address(), {"fetch", job, "--out", out.string()});
  ASSERT_EQ(f.rc, 0) << f.err;
}

const std::vector<std::string> kJobFlags = {"--image-size", "48", "--outputs", "vtu,labels"};

std::vector<std::string> Submit(const fs::path& volume, std::vector<std::string> extra) {
  std::vector<std::string> args = {"submit", volume.string()};
  args.insert(args.end(), kJobFlags.begin(), kJobFlags.end());
  args.insert(args.end(), extra.begin(), extra.end());
  return args;
}

struct Case {
  std::string boundary;  // the stage whose checkpoint was the last saved
  int signal;            // what stops the server there
};

// How ctest and gtest name a case's parameter (instead of its bytes).
void PrintTo(const Case& c, std::ostream* os) {
  *os << "pause after " << c.boundary << ", then " << (c.signal == SIGTERM ? "SIGTERM" : "SIGKILL");
}

std::string CaseName(const ::testing::TestParamInfo<Case>& info) {
  return "After" + std::string(1, char(std::toupper(info.param.boundary[0]))) +
         info.param.boundary.substr(1) + (info.param.signal == SIGTERM ? "Sigterm" : "Sigkill");
}

class ResumeE2E : public ::testing::TestWithParam<Case> {
 protected:
  // One uninterrupted run of the same job, shared by every case (the pipeline is deterministic).
  static void SetUpTestSuite() {
    scratch_ = testing::MakeScratchDir("resume_e2e");
    volume_ = scratch_ / "phantom.nii";
    WriteTinyNifti(volume_, 20, 18, 14);
    ServerProcess server(scratch_ / "reference-data");
    std::vector<std::string> args = Submit(volume_, {"--out", (scratch_ / "reference").string()});
    const CliResult r = RunCli(server.address(), args, 120s * kSlowdown);
    ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  }
  static inline fs::path scratch_, volume_;
};

TEST_P(ResumeE2E, StoppedAtTheBoundaryTheRestartedServerResumesWithIdenticalOutputs) {
  const Case c = GetParam();
  ASSERT_TRUE(fs::exists(scratch_ / "reference" / "mesh.vtu"));
  const fs::path data = scratch_ / ("data-" + CaseName({c, 0}));
  const std::vector<std::string> flags = {"--workers", "1", "--allow-faults", "--drain-seconds",
                                          "2"};
  std::string job;
  std::vector<v1::JobEvent> drain_events;
  grpc::Status watch_status;
  {
    ServerProcess server(data, flags);
    const CliResult s =
        RunCli(server.address(), Submit(volume_, {"--fault", "pause-after:" + c.boundary}));
    ASSERT_EQ(s.rc, 0) << s.err;
    job = FirstLine(s.out);
    // The job child pauses right after it saved the boundary's checkpoint.
    const std::string paused = "paused after the " + c.boundary + " checkpoint";
    ASSERT_TRUE(WaitFor(
        [&] {
          return GetJob(server.address(), job).progress().message().find(paused) !=
                 std::string::npos;
        },
        120s * kSlowdown))
        << GetJob(server.address(), job).DebugString() << server.Log();
    ASSERT_TRUE(fs::exists(data / "jobs" / job.substr(5) / "checkpoints" / (c.boundary + ".ckpt")));
    if (c.signal == SIGTERM) {
      // A watcher on before the signal: it sees the drain's progress, then the requeue.
      const int64_t from = GetJob(server.address(), job).last_sequence();
      std::atomic<int> on{0};
      std::thread watcher([&] {
        drain_events = WatchAll(server.address(), job, from, -1, &watch_status, 60s, &on);
      });
      ASSERT_TRUE(WaitFor([&] { return on.load() > 0; }, 10s));
      server.Kill(SIGTERM);  // drains 2 s, requeues the paused job, stops
      watcher.join();
      EXPECT_THAT(server.Log(), HasSubstr("resumes after " + c.boundary));
    } else {
      server.Kill(SIGKILL);  // the job child dies with it (PR_SET_PDEATHSIG)
    }
  }
  if (c.signal == SIGTERM) {
    bool drain_progress = false, requeued = false;
    for (const auto& ev : drain_events) {
      if (ev.has_progress() && ev.progress().metrics().count("drain_remaining_s")) {
        drain_progress = true;
        EXPECT_THAT(ev.progress().message(), HasSubstr("server draining"));
        EXPECT_LE(ev.progress().metrics().at("drain_remaining_s"), 2.0);
        EXPECT_EQ(ev.progress().stage(), c.boundary) << "the job's own stage while it drains";
      }
      if (ev.has_state_change() && ev.state_change().state() == v1::QUEUED) requeued = true;
    }
    EXPECT_TRUE(drain_progress) << "no drain progress among " << drain_events.size() << " events";
    EXPECT_TRUE(requeued) << "the watcher did not see the requeue";
    EXPECT_EQ(watch_status.error_code(), grpc::StatusCode::UNAVAILABLE)
        << watch_status.error_message();
  }

  ServerProcess again(data, flags);
  const fs::path out = scratch_ / ("out-" + CaseName({c, 0}));
  ASSERT_NO_FATAL_FAILURE(ExpectSucceededAndFetch(again, job, out));

  EXPECT_EQ(ReadFile(out / "mesh.vtu"), ReadFile(scratch_ / "reference" / "mesh.vtu"));
  EXPECT_EQ(ReadFile(out / "labels.nii.gz"), ReadFile(scratch_ / "reference" / "labels.nii.gz"));
  EXPECT_EQ(Comparable(out / "metrics.json"), Comparable(scratch_ / "reference" / "metrics.json"));
  const Json resumed = Json::parse(ReadFile(out / "metrics.json"))["resumed_stages"];
  EXPECT_EQ(resumed, c.boundary == "segment" ? Json({"segment"}) : Json({"segment", "simplify"}));
  EXPECT_FALSE(fs::exists(data / "jobs" / job.substr(5) / "checkpoints"))
      << "a succeeded job keeps no checkpoint";
}

INSTANTIATE_TEST_SUITE_P(Boundaries, ResumeE2E,
                         ::testing::Values(Case{"segment", SIGTERM}, Case{"simplify", SIGTERM},
                                           Case{"segment", SIGKILL}, Case{"simplify", SIGKILL}),
                         CaseName);

// A job killed inside a streamed simplify stage loses no work beyond the window it was in
// (issue 30): the server is SIGKILLed right after the job saved the record of its third window;
// the restarted server's attempt reads those three windows back and simplifies from the fourth,
// and the outputs are those of the job run in one go.
TEST(ResumeStreamedE2E, KilledInsideAStreamedSimplifyStageItResumesAfterTheLastSavedSlab) {
  const fs::path scratch = testing::MakeScratchDir("resume_stream_e2e");
  const fs::path volume = scratch / "phantom.nii";
  WriteTinyNifti(volume, 20, 18, 14);  // 13 cube layers: 4 windows a pass in slabs of 4
  const std::vector<std::string> streamed = {"--stream-slab-voxels", "4", "--reduction", "0.8"};
  {
    ServerProcess server(scratch / "reference-data");
    std::vector<std::string> args = Submit(volume, streamed);
    args.insert(args.end(), {"--out", (scratch / "reference").string()});
    const CliResult r = RunCli(server.address(), args, 120s * kSlowdown);
    ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  }
  const fs::path data = scratch / "data";
  const std::vector<std::string> flags = {"--workers", "1", "--allow-faults"};
  std::string job;
  {
    ServerProcess server(data, flags);
    std::vector<std::string> args = Submit(volume, streamed);
    args.insert(args.end(), {"--fault", "pause-after:simplify-window-3"});
    const CliResult s = RunCli(server.address(), args);
    ASSERT_EQ(s.rc, 0) << s.err;
    job = FirstLine(s.out);
    ASSERT_TRUE(WaitFor(
        [&] {
          return GetJob(server.address(), job)
                     .progress()
                     .message()
                     .find("paused after the simplify-window-3 checkpoint") != std::string::npos;
        },
        120s * kSlowdown))
        << GetJob(server.address(), job).DebugString() << server.Log();
    const fs::path ckpt = data / "jobs" / job.substr(5) / "checkpoints";
    EXPECT_TRUE(fs::exists(ckpt / "simplify.pass-0.window-2.ckpt"));
    EXPECT_FALSE(fs::exists(ckpt / "simplify.pass-0.window-3.ckpt"));
    EXPECT_EQ(GetJob(server.address(), job).progress().stage(), "simplify");
    server.Kill(SIGKILL);  // the job child dies with it (PR_SET_PDEATHSIG)
  }
  ServerProcess again(data, flags);
  const fs::path out = scratch / "out";
  ASSERT_NO_FATAL_FAILURE(ExpectSucceededAndFetch(again, job, out));
  EXPECT_EQ(ReadFile(out / "mesh.vtu"), ReadFile(scratch / "reference" / "mesh.vtu"));
  EXPECT_EQ(Comparable(out / "metrics.json"), Comparable(scratch / "reference" / "metrics.json"));
  const Json metrics = Json::parse(ReadFile(out / "metrics.json"));
  EXPECT_EQ(metrics["resumed_simplify_windows"], 3);
  EXPECT_EQ(metrics["resumed_stages"], Json({"segment", "simplify"}));
  EXPECT_EQ(metrics["simplification"]["stream_slab_voxels"], 4);
}

}  // namespace
}  // namespace decima::e2e
