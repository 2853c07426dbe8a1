// Scale-out end to end: a real PostgreSQL 15 (initdb in a temp folder, run as the `postgres`
// user), three real decima-server replicas on loopback sharing one data dir and one database,
// a 2 s lease (the reaper sweeps every 0.25 s), the real CLI and gRPC clients. Every process is
// stopped by its PID. Skipped when PostgreSQL is not installed.
#include <grpcpp/grpcpp.h>
#include <signal.h>

#include <atomic>
#include <fstream>
#include <map>
#include <mutex>
#include <regex>
#include <set>
#include <sstream>
#include <thread>

#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/util/sha256.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/postgres_server.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;
using namespace std::chrono_literals;

constexpr double kLeaseSeconds = 2.0;  // the reaper runs every lease / 8

testing::PostgresServer* Postgres() {
  static testing::PostgresServer* pg = [] {
    auto* p = new testing::PostgresServer();
    std::atexit([] { delete Postgres(); });
    return p;
  }();
  return pg;
}

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::unique_ptr<v1::Jobs::Stub> JobsStub(const std::string& address) {
  return v1::Jobs::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
}

absl::StatusOr<v1::Job> TryGetJob(const std::string& address, const std::string& name) {
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + 30s);
  v1::GetJobRequest req;
  req.set_name(name);
  v1::Job job;
  grpc::Status s = JobsStub(address)->GetJob(&ctx, req, &job);
  if (!s.ok()) return absl::UnavailableError(s.error_message());
  return job;
}

v1::Job GetJob(const std::string& address, const std::string& name) {
  auto j = TryGetJob(address, name);
  EXPECT_TRUE(j.ok()) << j.status();
  return j.ok() ? *j : v1::Job();
}

bool IsFinal(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

void ExpectGapless(const std::vector<int64_t>& seqs, const std::string& what) {
  for (size_t i = 0; i < seqs.size(); ++i) {
    ASSERT_EQ(seqs[i], static_cast<int64_t>(i + 1)) << what << " at index " << i;
  }
}

class ScaleE2E : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!testing::PostgresServer::BinDir()) GTEST_SKIP() << testing::PostgresServer::WhyAbsent();
    ASSERT_EQ(Postgres()->error(), "") << "PostgreSQL did not start";
    static int counter = 0;
    db_ = "scale" + std::to_string(::getpid()) + "_" + std::to_string(counter++);
    ASSERT_EQ(Postgres()->CreateDatabase(db_), "");
    scratch_ = testing::MakeScratchDir("scale_e2e");
    data_ = scratch_ / "shared";
    volume_ = scratch_ / "phantom.nii";
    WriteTinyNifti(volume_, 12, 10, 8);
  }

  // Starts one more replica on the shared data dir and database.
  ServerProcess& AddReplica(int workers = 1) {
    replicas_.push_back(std::make_unique<ServerProcess>(
        data_, std::vector<std::string>{"--store", Postgres()->Dsn(db_), "--workers",
                                        std::to_string(workers), "--lease-seconds",
                                        std::to_string(kLeaseSeconds), "--heartbeat-seconds", "1",
                                        "--allow-faults", "--drain-seconds", "1"}));
    return *replicas_.back();
  }
  void StartReplicas(int n, int workers = 1) {
    for (int i = 0; i < n; ++i) AddReplica(workers);
  }
  std::string addr(size_t i) const { return replicas_[i]->address(); }

  // Submits through the CLI on replica `i`; the job name.
  std::string Submit(size_t i, const std::string& fault = "") {
    std::vector<std::string> args = {"submit", volume_.string(), "--image-size", "64"};
    if (!fault.empty()) {
      args.push_back("--fault");
      args.push_back(fault);
    }
    CliResult r = RunCli(addr(i), args);
    EXPECT_EQ(r.rc, 0) << r.err;
    return FirstLine(r.out);
  }

  // The index of the replica whose log says it runs `job` attempt `attempt`, or -1 after 30 s.
  int RunnerOf(const std::string& job, int attempt) {
    const std::string needle =
        "job " + job.substr(5) + " RUNNING attempt " + std::to_string(attempt) + " ";
    int found = -1;
    WaitFor(
        [&] {
          for (size_t i = 0; i < replicas_.size(); ++i) {
            if (replicas_[i]->pid() > 0 && replicas_[i]->Log().find(needle) != std::string::npos) {
              found = static_cast<int>(i);
              return true;
            }
          }
          return false;
        },
        30s);
    return found;
  }

  // Waits until `job` is final (asking the replicas still alive); the job.
  v1::Job WaitFinal(const std::string& job, std::chrono::seconds timeout = 120s) {
    v1::Job out;
    WaitFor(
        [&] {
          for (auto& r : replicas_) {
            if (r->pid() <= 0) continue;
            auto j = TryGetJob(r->address(), job);
            if (j.ok()) {
              out = *j;
              return IsFinal(j->state());
            }
          }
          return false;
        },
        timeout);
    return out;
  }

  std::string AllLogs() const {
    std::string s;
    for (const auto& r : replicas_) s += r->Log();
    return s;
  }

  // The job's artifacts are the files of its last claim (attempt folder = lease epoch), and no
  // earlier claim left a folder.
  void ExpectArtifactsOfClaim(const v1::Job& job, int64_t epoch) {
    const fs::path attempts = data_ / "jobs" / job.name().substr(5) / "attempts";
    std::set<std::string> folders;
    for (const auto& e : fs::directory_iterator(attempts)) folders.insert(e.path().filename());
    EXPECT_EQ(folders, std::set<std::string>{std::to_string(epoch)});
    ASSERT_GT(job.artifacts_size(), 0);
    for (const auto& a : job.artifacts()) {
      auto sha = server::Sha256OfFile(attempts / std::to_string(epoch) / "out" / a.file_name());
      ASSERT_TRUE(sha.ok()) << sha.status();
      EXPECT_EQ(*sha, a.sha256()) << a.file_name();
    }
  }

  std::string db_;
  fs::path scratch_, data_, volume_;
  std::vector<std::unique_ptr<ServerProcess>> replicas_;
};

TEST_F(ScaleE2E, KilledReplicasJobRunsElsewhereOnceWithinLeaseAndReaperPeriod) {
  StartReplicas(3);
  const std::string job = Submit(0, "sleep:3");
  const int runner = RunnerOf(job, 1);
  ASSERT_GE(runner, 0) << AllLogs();
  const auto t0 = std::chrono::steady_clock::now();
  replicas_[runner]->Kill(SIGKILL);
  const size_t other = (runner + 1) % 3;
  ASSERT_TRUE(WaitFor(
      [&] {
        v1::Job j = GetJob(addr(other), job);
        return j.state() == v1::RUNNING && j.attempts() == 2;
      },
      30s));
  const double failover =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  // The bound, lease + lease / 4, plus 1 s for a loaded 2-core machine.
  EXPECT_LT(failover, kLeaseSeconds * 1.25 + 1.0) << "failover took " << failover << " s";
  const int second = RunnerOf(job, 2);
  EXPECT_NE(second, runner);
  v1::Job done = WaitFinal(job);
  EXPECT_EQ(done.state(), v1::SUCCEEDED) << AllLogs();
  EXPECT_EQ(done.attempts(), 2);
  ExpectArtifactsOfClaim(done, 2);
}

// Issue 30, "SIGKILL of one replica mid-slab": a job simplified in slabs whose replica dies right
// after the record of its third window goes on with another replica, which reads the three
// windows back from the shared data dir and simplifies from the fourth; the mesh is the one a
// job run in one go on one replica makes. (One job's windows follow each other: they run on one
// replica at a time, core/simplify README "Streamed simplification".)
TEST_F(ScaleE2E, KilledReplicasStreamedJobResumesOnAnotherAfterTheLastSavedSlab) {
  StartReplicas(2);
  const fs::path volume = scratch_ / "slabs.nii";
  WriteTinyNifti(volume, 20, 18, 14);  // 13 cube layers: 4 windows a pass in slabs of 4
  auto submit = [&](size_t i, const std::vector<std::string>& extra) {
    std::vector<std::string> args = {
        "submit", volume.string(), "--image-size", "48", "--stream-slab-voxels",
        "4",      "--reduction",   "0.8"};
    args.insert(args.end(), extra.begin(), extra.end());
    CliResult r = RunCli(addr(i), args);
    EXPECT_EQ(r.rc, 0) << r.err;
    return FirstLine(r.out);
  };
  const std::string reference = submit(0, {});
  const v1::Job ref = WaitFinal(reference);
  ASSERT_EQ(ref.state(), v1::SUCCEEDED) << AllLogs();
  ASSERT_EQ(ref.attempts(), 1);

  const std::string job = submit(1, {"--fault", "pause-after:simplify-window-3"});
  const int runner = RunnerOf(job, 1);
  ASSERT_GE(runner, 0) << AllLogs();
  ASSERT_TRUE(WaitFor(
      [&] {
        return GetJob(addr(runner), job)
                   .progress()
                   .message()
                   .find("paused after the simplify-window-3 checkpoint") != std::string::npos;
      },
      120s))
      << AllLogs();
  const fs::path ckpt = data_ / "jobs" / job.substr(5) / "checkpoints";
  EXPECT_TRUE(fs::exists(ckpt / "simplify.pass-0.window-2.ckpt"));
  replicas_[runner]->Kill(SIGKILL);
  const v1::Job done = WaitFinal(job);
  ASSERT_EQ(done.state(), v1::SUCCEEDED) << AllLogs();
  EXPECT_EQ(done.attempts(), 2);
  EXPECT_NE(RunnerOf(job, 2), runner);

  const size_t alive = 1 - runner;
  const fs::path out = scratch_ / "out", ref_out = scratch_ / "ref-out";
  for (const auto& [name, folder] : {std::pair{job, out}, std::pair{reference, ref_out}}) {
    const CliResult f = RunCli(addr(alive), {"fetch", name, "--out", folder.string()});
    ASSERT_EQ(f.rc, 0) << f.err;
  }
  EXPECT_EQ(ReadFile(out / "mesh.vtu"), ReadFile(ref_out / "mesh.vtu"));
  const std::string metrics = ReadFile(out / "metrics.json");
  EXPECT_THAT(metrics, HasSubstr("\"resumed_simplify_windows\": 3"));
  EXPECT_FALSE(fs::exists(ckpt)) << "a succeeded job keeps no checkpoint";
}

TEST_F(ScaleE2E, ReplicaPausedPastItsLeaseIsRefusedWhenItWakes) {
  StartReplicas(3);
  const std::string job = Submit(0, "sleep:4");
  const int runner = RunnerOf(job, 1);
  ASSERT_GE(runner, 0) << AllLogs();
  replicas_[runner]->Signal(SIGSTOP);
  const size_t other = (runner + 1) % 3;
  ASSERT_TRUE(WaitFor([&] { return GetJob(addr(other), job).attempts() == 2; }, 30s)) << AllLogs();
  std::this_thread::sleep_for(1s);
  replicas_[runner]->Signal(SIGCONT);
  v1::Job done = WaitFinal(job);
  EXPECT_EQ(done.state(), v1::SUCCEEDED) << AllLogs();
  EXPECT_EQ(done.attempts(), 2);
  // The woken replica's renew or finish was refused (its child had finished, or was stopped).
  const std::string paused_log = replicas_[runner]->Log();
  ASSERT_TRUE(WaitFor(
      [&] {
        const std::string log = replicas_[runner]->Log();
        return log.find("is no longer leased to") != std::string::npos ||
               log.find("is not running under lease") != std::string::npos;
      },
      15s))
      << replicas_[runner]->Log();
  ExpectArtifactsOfClaim(GetJob(addr(other), job), 2);
  EXPECT_EQ(GetJob(addr(runner), job).state(), v1::SUCCEEDED);
}

TEST_F(ScaleE2E, CrossReplicaWatchIsCompleteAndOrderedAcrossTheRunnersDeath) {
  StartReplicas(3);
  const std::string job = Submit(0, "sleep:3");
  const int runner = RunnerOf(job, 1);
  ASSERT_GE(runner, 0);
  const size_t watcher = (runner + 1) % 3, third = (runner + 2) % 3;
  // First watcher on a replica that does not run the job: leaves after 5 progress events.
  auto part1 = WatchAll(addr(watcher), job, 0, 5);
  auto seq1 = Sequences(part1);
  ASSERT_GE(seq1.size(), 5u);
  ExpectGapless(seq1, "first watch");
  // The running replica dies; the watcher resumes on the third replica.
  replicas_[runner]->Kill(SIGKILL);
  auto part2 = WatchAll(addr(third), job, seq1.back());
  std::vector<int64_t> all = seq1;
  for (int64_t s : Sequences(part2)) all.push_back(s);
  ExpectGapless(all, "watch across the runner's death");
  ASSERT_FALSE(part2.empty());
  ASSERT_TRUE(part2.back().has_state_change());
  EXPECT_EQ(part2.back().state_change().state(), v1::SUCCEEDED);
  // The whole log read again from another replica is the same gapless sequence.
  auto again = Sequences(WatchAll(addr(watcher), job));
  EXPECT_EQ(again, all);
}

TEST_F(ScaleE2E, CancelThroughAnotherReplicaStopsTheJobWithinTwoSeconds) {
  StartReplicas(3);
  const std::string job = Submit(0, "sleep:30");
  const int runner = RunnerOf(job, 1);
  ASSERT_GE(runner, 0);
  ASSERT_TRUE(WaitFor([&] { return GetJob(addr(runner), job).state() == v1::RUNNING; }, 30s));
  const size_t other = (runner + 1) % 3;
  const auto t0 = std::chrono::steady_clock::now();
  CliResult c = RunCli(addr(other), {"cancel", job});
  ASSERT_EQ(c.rc, 0) << c.err;
  ASSERT_TRUE(WaitFor([&] { return GetJob(addr(other), job).state() == v1::CANCELLED; }, 10s));
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_LE(secs, 2.0) << "cancel through another replica took " << secs << " s";
}

TEST_F(ScaleE2E, ThreeHundredJobsOnThreeReplicasAreEachClaimedExactlyOnce) {
  StartReplicas(3, /*workers=*/2);
  // Short jobs: the tiny phantom (its level set converges in 3 iterations; a smaller one
  // runs to the iteration limit) and the smallest image the pipeline accepts.
  CliResult r = RunCli(addr(0), {"submit", volume_.string(), "--image-size", "16"});
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string first = FirstLine(r.out);
  const v1::Job first_job = GetJob(addr(0), first);
  constexpr int kJobs = 299;  // + the first
  std::vector<std::string> names = {first};
  for (int i = 0; i < kJobs; ++i) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::CreateJobRequest req;
    *req.mutable_spec() = first_job.spec();
    v1::Job job;
    grpc::Status s = JobsStub(addr(i % 3))->CreateJob(&ctx, req, &job);
    ASSERT_TRUE(s.ok()) << s.error_message();
    names.push_back(job.name());
  }
  for (const auto& n : names) {
    v1::Job j = WaitFinal(n, 300s);
    ASSERT_EQ(j.state(), v1::SUCCEEDED) << n << " " << j.error().message();
    EXPECT_EQ(j.attempts(), 1) << n;
  }
  // Each job was claimed by exactly one replica, once.
  const std::string logs = AllLogs();
  for (const auto& n : names) {
    const std::string needle = "job " + n.substr(5) + " RUNNING attempt";
    size_t count = 0;
    for (size_t p = logs.find(needle); p != std::string::npos; p = logs.find(needle, p + 1)) {
      ++count;
    }
    EXPECT_EQ(count, 1u) << n;
  }
  std::set<std::string> runners;
  for (size_t i = 0; i < 3; ++i) {
    if (replicas_[i]->Log().find("RUNNING attempt") != std::string::npos) runners.insert(addr(i));
  }
  EXPECT_EQ(runners.size(), 3u) << "every replica claimed some of the 300 jobs";
}

TEST_F(ScaleE2E, HundredConcurrentCreatesWithOneRequestIdMakeOneJob) {
  StartReplicas(3);
  const std::string first = Submit(0);
  const v1::Job first_job = GetJob(addr(0), first);
  std::mutex mu;
  std::set<std::string> names;
  std::atomic<int> failures{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 100; ++t) {
    threads.emplace_back([&, t] {
      grpc::ClientContext ctx;
      ctx.set_deadline(std::chrono::system_clock::now() + 60s);
      v1::CreateJobRequest req;
      *req.mutable_spec() = first_job.spec();
      req.set_request_id("8d2f6a4e-one-request");
      v1::Job job;
      grpc::Status s = JobsStub(addr(t % 3))->CreateJob(&ctx, req, &job);
      if (!s.ok()) {
        ++failures;
        return;
      }
      std::lock_guard<std::mutex> lock(mu);
      names.insert(job.name());
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(failures.load(), 0);
  EXPECT_EQ(names.size(), 1u);
  grpc::ClientContext ctx;
  v1::ListJobsRequest req;
  req.set_page_size(1000);
  v1::ListJobsResponse resp;
  ASSERT_TRUE(JobsStub(addr(1))->ListJobs(&ctx, req, &resp).ok());
  EXPECT_EQ(resp.jobs_size(), 2);  // the first submit's job and the one created 100 times
}

TEST_F(ScaleE2E, DatabaseRestartMidRunReplicasReconnectWatchersResyncEveryJobEnds) {
  StartReplicas(3);
  std::vector<std::string> jobs;
  for (int i = 0; i < 4; ++i) jobs.push_back(Submit(i % 3, "sleep:2"));
  std::vector<std::vector<int64_t>> seen(jobs.size());
  std::vector<grpc::Status> ends(jobs.size());
  std::vector<std::thread> watchers;
  std::atomic<int> watching{0};
  for (size_t i = 0; i < jobs.size(); ++i) {
    watchers.emplace_back([&, i] {
      seen[i] = Sequences(WatchAll(addr((i + 1) % 3), jobs[i], 0, -1, &ends[i],
                                   std::chrono::seconds(120), &watching));
    });
  }
  // Not an ASSERT: the watcher threads must be joined whatever happens. Every watcher has its
  // snapshot before the database goes away (the case is watchers that resync, not a watch
  // opened while the database is down).
  EXPECT_TRUE(WaitFor([&] { return GetJob(addr(0), jobs[0]).state() == v1::RUNNING; }, 60s));
  EXPECT_TRUE(WaitFor([&] { return watching.load() == static_cast<int>(jobs.size()); }, 60s));
  Postgres()->Stop();
  std::this_thread::sleep_for(1s);
  EXPECT_EQ(Postgres()->Start(), "");
  for (auto& w : watchers) w.join();
  for (size_t i = 0; i < jobs.size(); ++i) {
    EXPECT_TRUE(ends[i].ok()) << jobs[i] << ": " << ends[i].error_message();
    ExpectGapless(seen[i], jobs[i]);
    v1::Job j = WaitFinal(jobs[i]);
    EXPECT_EQ(j.state(), v1::SUCCEEDED) << jobs[i] << AllLogs();
    ASSERT_FALSE(seen[i].empty());
    EXPECT_EQ(seen[i].back(), j.last_sequence()) << "the watcher saw the job to its end";
  }
  EXPECT_THAT(AllLogs(), HasSubstr("event feed reconnected"));
}

// Issue 35 part 7: with PostgreSQL down, CreateJob answered NOT_FOUND for an existing volume and
// health stayed SERVING. Now a store that cannot answer is UNAVAILABLE (after
// --store-retry-seconds), health turns NOT_SERVING within a few seconds, and SERVING again once
// the database is back.
TEST_F(ScaleE2E, WithTheDatabaseDownCallsAreUnavailableAndHealthFollowsTheStore) {
  replicas_.push_back(std::make_unique<ServerProcess>(
      data_,
      std::vector<std::string>{"--store", Postgres()->Dsn(db_), "--store-retry-seconds", "2"}));
  CliResult r = RunCli(addr(0), {"submit", volume_.string(), "--image-size", "32"});
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string volume = GetJob(addr(0), FirstLine(r.out)).spec().volume();
  ASSERT_FALSE(volume.empty());
  auto health = [&] { return RunCli(addr(0), {"--timeout", "5", "health"}); };
  EXPECT_EQ(health().rc, 0);

  Postgres()->Stop();
  v1::CreateJobRequest req;
  req.mutable_spec()->set_volume(volume);
  v1::Job job;
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + 30s);
  grpc::Status st = JobsStub(addr(0))->CreateJob(&ctx, req, &job);
  EXPECT_EQ(st.error_code(), grpc::StatusCode::UNAVAILABLE) << st.error_message();
  EXPECT_THAT(st.error_message(), HasSubstr("PostgreSQL unreachable"));
  bool not_serving = WaitFor(
      [&] {
        CliResult h = health();
        return h.rc == 8 && h.out.find("NOT_SERVING") != std::string::npos;
      },
      15s);
  EXPECT_TRUE(not_serving) << AllLogs();

  EXPECT_EQ(Postgres()->Start(), "");
  EXPECT_TRUE(WaitFor([&] { return health().rc == 0; }, 30s)) << AllLogs();
  EXPECT_THAT(AllLogs(), HasSubstr("job store unreachable, health NOT_SERVING"));
  EXPECT_THAT(AllLogs(), HasSubstr("job store reachable again: health SERVING"));
}

TEST_F(ScaleE2E, FourthReplicaStartingMidRunRequeuesNothing) {
  StartReplicas(3);
  std::vector<std::string> jobs;
  for (int i = 0; i < 3; ++i) jobs.push_back(Submit(i, "sleep:3"));
  for (const auto& j : jobs) ASSERT_GE(RunnerOf(j, 1), 0);
  AddReplica();
  for (const auto& j : jobs) {
    v1::Job done = WaitFinal(j);
    EXPECT_EQ(done.state(), v1::SUCCEEDED);
    EXPECT_EQ(done.attempts(), 1) << j << " was claimed again";
  }
  EXPECT_THAT(AllLogs(), ::testing::Not(HasSubstr("QUEUED again")));
}

TEST_F(ScaleE2E, UploadBegunOnOneReplicaResumesOnAnotherAndConcurrentWritersAreAborted) {
  StartReplicas(2);
  fs::path big = scratch_ / "big.nii";
  WriteTinyNifti(big, 160, 160, 64, 7);  // 3.3 MB: four chunks
  const std::string bytes = ReadFile(big);
  auto sha = server::Sha256OfFile(big);
  ASSERT_TRUE(sha.ok());
  auto stub_a =
      v1::Uploads::NewStub(grpc::CreateChannel(addr(0), grpc::InsecureChannelCredentials()));
  auto stub_b =
      v1::Uploads::NewStub(grpc::CreateChannel(addr(1), grpc::InsecureChannelCredentials()));
  auto chunk = [&](int64_t offset, bool first) {
    v1::UploadRequest req;
    if (first) {
      req.set_sha256(*sha);
      req.set_size_bytes(static_cast<int64_t>(bytes.size()));
      req.set_write_offset(offset);
    }
    req.set_data(bytes.substr(static_cast<size_t>(offset), 1 << 20));
    return req;
  };
  {
    // Begun on A: two chunks, then the stream ends (A keeps the prefix).
    grpc::ClientContext ctx;
    v1::Blob blob;
    auto writer = stub_a->Upload(&ctx, &blob);
    ASSERT_TRUE(writer->Write(chunk(0, true)));
    ASSERT_TRUE(writer->Write(chunk(1 << 20, false)));
    writer->WritesDone();
    EXPECT_EQ(writer->Finish().error_code(), grpc::StatusCode::ABORTED);
  }
  v1::GetUploadStatusRequest sreq;
  sreq.set_sha256(*sha);
  sreq.set_size_bytes(static_cast<int64_t>(bytes.size()));
  v1::UploadStatus st;
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(stub_b->GetUploadStatus(&ctx, sreq, &st).ok());
  }
  EXPECT_EQ(st.committed_size(), 2 << 20) << "B sees the prefix A received";
  {
    // Continued on B at that offset while A holds a writer open: B's second writer is refused.
    grpc::ClientContext ctx_b;
    v1::Blob blob_b;
    auto writer_b = stub_b->Upload(&ctx_b, &blob_b);
    ASSERT_TRUE(writer_b->Write(chunk(2 << 20, true)));
    // Wait until B's writer holds the upload (the partial grew), then race it from A.
    ASSERT_TRUE(WaitFor(
        [&] {
          grpc::ClientContext ctx;
          v1::UploadStatus s;
          return stub_a->GetUploadStatus(&ctx, sreq, &s).ok() && s.committed_size() > (2 << 20);
        },
        10s));
    {
      grpc::ClientContext ctx_a;
      v1::Blob blob_a;
      auto writer_a = stub_a->Upload(&ctx_a, &blob_a);
      writer_a->Write(chunk(3 << 20, true));
      writer_a->WritesDone();
      grpc::Status s = writer_a->Finish();
      EXPECT_EQ(s.error_code(), grpc::StatusCode::ABORTED) << s.error_message();
      EXPECT_THAT(s.error_message(), HasSubstr("another upload of blob"));
    }
    ASSERT_TRUE(writer_b->Write(chunk(3 << 20, false)));
    writer_b->WritesDone();
    grpc::Status s = writer_b->Finish();
    ASSERT_TRUE(s.ok()) << s.error_message();
  }
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(stub_a->GetUploadStatus(&ctx, sreq, &st).ok());
  }
  EXPECT_TRUE(st.complete());
  EXPECT_EQ(st.committed_size(), static_cast<int64_t>(bytes.size()));
}

}  // namespace
}  // namespace decima::e2e
