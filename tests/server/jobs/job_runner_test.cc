// JobRunner and WorkerPool on a real SQLite store in a scratch data dir, with the real job child
// (decima-server --run-job) and the test faults (faults.h) for crashes and slow jobs; a shell
// script stands in for a child that exits with a code of its own.
#include "server/jobs/job_runner.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <thread>

#include "core/io/volume_io.h"
#include "core/volume/phantom.h"
#include "server/jobs/job_spec.h"
#include "server/jobs/worker_pool.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono_literals;
using ::testing::HasSubstr;
using ::testing::Not;

using Clock = std::chrono::steady_clock;

class JobRunnerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = testing::MakeScratchDir("job_runner");
    auto s = OpenSqliteJobStore((root_ / "jobs.sqlite").string());
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = std::move(*s);
    // A small noisy head phantom: the whole pipeline runs on it in about a second.
    HeadPhantomOptions o;
    o.dims = {24, 24, 20};
    o.spacing = {2, 2, 2};
    o.noise_sigma = 20;
    auto p = MakeHeadPhantom(o);
    ASSERT_TRUE(p.ok()) << p.status();
    const fs::path files = DataDir(root_).volume_files("v");
    fs::create_directories(files);
    ASSERT_TRUE(io::WriteNifti(p->image, files / "phantom.nii.gz").ok());
    v1::Volume vol;
    vol.set_name("volumes/v");
    vol.set_display_name("phantom.nii.gz");
    v1::VolumeFile* file = vol.add_files();
    file->set_path("phantom.nii.gz");
    file->set_blob("blobs/" + std::string(64, 'a'));  // the runner reads the file, not the blob
    vol.set_format(v1::VOLUME_FORMAT_NIFTI);
    for (int64_t d : o.dims) vol.add_dims(d);
    vol.set_scalar_type("float32");
    bool created = false;
    ASSERT_TRUE(store_->CreateVolume("v", vol, "", "", &created).ok());
  }

  JobRunnerOptions Options() const {
    JobRunnerOptions o;
    o.data_dir = DataDir(root_);
    o.worker_exe = DECIMA_SERVER_BIN;
    o.lease_ms = 3000;
    o.allow_faults = true;
    return o;
  }

  // Queues job `id` on the phantom, with `fault` kept beside it as CreateJob does.
  void Queue(const std::string& id, const std::string& fault = "") {
    v1::JobSpec spec;
    spec.set_volume("volumes/v");
    spec.set_image_size(48);
    spec.add_outputs("vtu");
    spec.add_outputs("labels");
    auto normalized = NormalizeJobSpec(spec);
    ASSERT_TRUE(normalized.ok()) << normalized.status();
    if (!fault.empty()) {
      const DataDir dd(root_);
      ASSERT_TRUE(dd.WriteFileAtomically(dd.job_fault(id), fault).ok());
    }
    bool created = false;
    ASSERT_TRUE(store_->CreateJob(id, *normalized, "", 100, "tester", &created).ok());
  }

  Claim ClaimOne(const std::string& owner = "runner-test") {
    auto c = store_->ClaimNext(owner, Options().lease_ms);
    EXPECT_TRUE(c.ok() && c->has_value()) << c.status();
    return c.ok() && c->has_value() ? **c : Claim{};
  }

  // Claims the oldest queued job and runs it to its end with a runner of the default options.
  Claim RunOne() {
    Claim claim = ClaimOne();
    JobRunner runner(store_.get(), Options());
    StopFlags stop;
    runner.Run(claim, stop);
    return claim;
  }

  v1::Job Job(const std::string& id) {
    auto j = store_->GetJob(id);
    EXPECT_TRUE(j.ok()) << j.status();
    return j.ok() ? *j : v1::Job{};
  }

  // Waits up to `limit` for job `id` to reach `state`.
  bool WaitFor(const std::string& id, v1::JobState state, std::chrono::milliseconds limit) {
    const auto end = Clock::now() + limit;
    while (Clock::now() < end) {
      if (Job(id).state() == state) return true;
      std::this_thread::sleep_for(20ms);
    }
    return false;
  }

  // Waits for the child of job `id` to report the fault's prepare stage (it runs).
  bool WaitForStage(const std::string& id, const std::string& stage) {
    const auto end = Clock::now() + 30s;
    while (Clock::now() < end) {
      if (Job(id).progress().stage() == stage) return true;
      std::this_thread::sleep_for(20ms);
    }
    return false;
  }

  // A stand-in child: a shell script whose body is `body`.
  fs::path Script(const std::string& body) {
    const fs::path path = root_ / "fake-worker.sh";
    std::ofstream(path) << "#!/bin/sh\n" << body << "\n";
    fs::permissions(path, fs::perms::owner_all);
    return path;
  }

  fs::path root_;
  std::unique_ptr<JobStore> store_;
};

TEST_F(JobRunnerTest, AJobThatRunsToTheEndSucceedsWithItsArtifactsHashed) {
  Queue("ok");
  const Claim claim = RunOne();
  const v1::Job job = Job("ok");
  ASSERT_EQ(job.state(), v1::SUCCEEDED) << job.error().message();
  ASSERT_GE(job.artifacts_size(), 2);
  const fs::path out = DataDir(root_).job_out("ok", claim.lease.epoch);
  for (const auto& a : job.artifacts()) {
    EXPECT_EQ(a.name(), "jobs/ok/artifacts/" + a.file_name());
    EXPECT_EQ(a.sha256().size(), 64u);
    EXPECT_EQ(a.size_bytes(), static_cast<int64_t>(fs::file_size(out / a.file_name())));
  }
  EXPECT_FALSE(job.metrics_json().empty());
}

TEST_F(JobRunnerTest, AChildThatCrashesFailsTheJobWithTheSignalAndTheStage) {
  Queue("crash", "crash");
  const Claim claim = RunOne();
  const v1::Job job = Job("crash");
  ASSERT_EQ(job.state(), v1::FAILED);
  EXPECT_EQ(job.error().code(), static_cast<int>(absl::StatusCode::kInternal));
  EXPECT_THAT(job.error().message(), HasSubstr("the worker was killed by signal"));
  EXPECT_THAT(job.error().message(), HasSubstr("during stage load"));
  EXPECT_FALSE(fs::exists(DataDir(root_).job_out("crash", claim.lease.epoch)))
      << "a failed job serves no artifact";
}

TEST_F(JobRunnerTest, AnErrorFrameFailsTheJobWithThePipelinesCodeAndMessage) {
  // A fault the child refuses to parse reaches it only through the data dir, never CreateJob.
  Queue("bad-fault", "sleep:99999");
  RunOne();
  const v1::Job job = Job("bad-fault");
  ASSERT_EQ(job.state(), v1::FAILED);
  EXPECT_EQ(job.error().code(), static_cast<int>(absl::StatusCode::kInvalidArgument));
  EXPECT_THAT(job.error().message(), HasSubstr("sleep"));
}

TEST_F(JobRunnerTest, EveryUnexpectedExitFailsTheJobNamingTheCodeAndTheLastLogLine) {
  for (int code : {0, 1, 2, 3, 5}) {
    SCOPED_TRACE(code);
    const std::string id = "exit" + std::to_string(code);
    Queue(id);
    Claim claim = ClaimOne();
    JobRunnerOptions o = Options();
    // Each exit code without its final frame: the protocol says the child crashed.
    o.worker_exe = Script("echo \"fake worker giving up\" >&2; exit " + std::to_string(code));
    JobRunner runner(store_.get(), o);
    StopFlags stop;
    runner.Run(claim, stop);
    const v1::Job job = Job(id);
    ASSERT_EQ(job.state(), v1::FAILED);
    EXPECT_THAT(job.error().message(),
                HasSubstr("the worker exited with code " + std::to_string(code)));
    EXPECT_THAT(job.error().message(), HasSubstr("last log line: fake worker giving up"));
    EXPECT_THAT(job.error().message(), Not(HasSubstr(root_.string())))
        << "clients never see where the data dir is";
  }
}

TEST_F(JobRunnerTest, CancelStopsAHangingChildAndRecordsCancelled) {
  Queue("hang", "sleep:60");
  Claim claim = ClaimOne();
  JobRunner runner(store_.get(), Options());
  StopFlags stop;
  std::thread t([&] { runner.Run(claim, stop); });
  ASSERT_TRUE(WaitForStage("hang", "prepare"));
  const auto t0 = Clock::now();
  stop.cancel = true;
  t.join();
  EXPECT_LT(Clock::now() - t0, 5s);
  const v1::Job job = Job("hang");
  ASSERT_EQ(job.state(), v1::CANCELLED);
  EXPECT_THAT(job.error().message(), HasSubstr("cancelled by request during prepare"));
}

TEST_F(JobRunnerTest, ACancelStoredThroughAnotherReplicaIsPolled) {
  Queue("remote-cancel", "sleep:60");
  Claim claim = ClaimOne();
  JobRunner runner(store_.get(), Options());
  StopFlags stop;
  std::thread t([&] { runner.Run(claim, stop); });
  ASSERT_TRUE(WaitForStage("remote-cancel", "prepare"));
  ASSERT_TRUE(store_->Cancel("remote-cancel").ok());
  t.join();
  EXPECT_EQ(Job("remote-cancel").state(), v1::CANCELLED);
  EXPECT_TRUE(stop.cancel) << "the runner learnt of the cancel from the store";
}

TEST_F(JobRunnerTest, ARequeueGivesTheJobAndItsAttemptBack) {
  Queue("drained", "sleep:60");
  Claim claim = ClaimOne();
  ASSERT_EQ(claim.job.attempts(), 1);
  JobRunner runner(store_.get(), Options());
  StopFlags stop;
  std::thread t([&] { runner.Run(claim, stop); });
  ASSERT_TRUE(WaitForStage("drained", "prepare"));
  stop.requeue = true;
  t.join();
  const v1::Job job = Job("drained");
  ASSERT_EQ(job.state(), v1::QUEUED);
  EXPECT_EQ(job.attempts(), 0);
  Claim again = ClaimOne();
  EXPECT_EQ(again.job.name(), "jobs/drained");
  EXPECT_GT(again.lease.epoch, claim.lease.epoch);
}

TEST_F(JobRunnerTest, ARunnerThatLostItsLeaseStopsItsChildAndChangesNothing) {
  Queue("stolen", "sleep:60");
  Claim claim = ClaimOne("first");
  JobRunnerOptions o = Options();
  o.lease_ms = 600;  // renewed every 200 ms
  JobRunner runner(store_.get(), o);
  StopFlags stop;
  std::thread t([&] { runner.Run(claim, stop); });
  ASSERT_TRUE(WaitForStage("stolen", "prepare"));
  // What the reaper and another replica do when this runner's lease lapsed.
  ASSERT_TRUE(store_->Requeue(claim.lease, "lapsed").ok());
  Claim other = ClaimOne("second");
  ASSERT_GT(other.lease.epoch, claim.lease.epoch);
  const auto t0 = Clock::now();
  t.join();
  EXPECT_LT(Clock::now() - t0, 5s);
  const v1::Job job = Job("stolen");
  EXPECT_EQ(job.state(), v1::RUNNING) << "the job belongs to the second claim";
  EXPECT_FALSE(fs::exists(DataDir(root_).job_attempt("stolen", claim.lease.epoch)))
      << "the lost attempt's folder is removed";
  EXPECT_TRUE(store_->Finish(other.lease, v1::CANCELLED, v1::Job{}).ok())
      << "the second claim still holds a valid lease";
}

TEST_F(JobRunnerTest, AVolumeThatIsGoneFailsTheJobWithoutAChild) {
  // The store refuses to delete a volume a queued job uses; a job can still outlive its volume
  // (it was deleted on another replica between CreateJob's check and the insert).
  ASSERT_TRUE(store_->DeleteVolume("v").ok());
  Queue("orphan");
  const Claim claim = RunOne();
  const v1::Job job = Job("orphan");
  ASSERT_EQ(job.state(), v1::FAILED);
  EXPECT_EQ(job.error().code(), static_cast<int>(absl::StatusCode::kNotFound));
  EXPECT_FALSE(fs::exists(DataDir(root_).job_log("orphan", claim.lease.epoch)))
      << "no child was started";
}

TEST_F(JobRunnerTest, APoolOfTwoTakesTheOldestJobsFirstAndRunsThemAll) {
  Queue("first", "sleep:1");
  Queue("second", "sleep:1");
  Queue("third", "sleep:1");
  WorkerPoolOptions o;
  o.workers = 2;
  o.owner = "pool-test";
  o.runner = Options();
  WorkerPool pool(store_.get(), o);
  pool.Start();
  ASSERT_TRUE(WaitForStage("first", "prepare"));
  ASSERT_TRUE(WaitForStage("second", "prepare"));
  EXPECT_EQ(Job("third").state(), v1::QUEUED) << "two workers run two jobs at once";
  EXPECT_EQ(pool.running(), 2);
  ASSERT_TRUE(WaitFor("third", v1::SUCCEEDED, 60s)) << Job("third").error().message();
  EXPECT_EQ(Job("first").state(), v1::SUCCEEDED);
  EXPECT_EQ(Job("second").state(), v1::SUCCEEDED);
  pool.Drain(1s);
}

TEST_F(JobRunnerTest, PoolCancelStopsTheRunningChildAndDrainRequeuesTheRest) {
  Queue("cancelled", "sleep:60");
  Queue("requeued", "sleep:60");
  WorkerPoolOptions o;
  o.workers = 2;
  o.owner = "pool-test";
  o.runner = Options();
  WorkerPool pool(store_.get(), o);
  pool.Start();
  ASSERT_TRUE(WaitForStage("cancelled", "prepare"));
  ASSERT_TRUE(WaitForStage("requeued", "prepare"));
  pool.Cancel("cancelled");
  ASSERT_TRUE(WaitFor("cancelled", v1::CANCELLED, 5s));
  const auto t0 = Clock::now();
  pool.Drain(200ms);
  EXPECT_LT(Clock::now() - t0, 5s);
  EXPECT_EQ(Job("requeued").state(), v1::QUEUED);
  EXPECT_EQ(pool.running(), 0);
}

}  // namespace
}  // namespace decima::server
