// End-to-end: the real decima-server and the real decima CLI on loopback. Each test starts its
// own server on a free port with a scratch data dir. Timing assertions are generous (a loaded
// 2-core machine) except the one the issue states: cancel takes effect within a second.
#include <grpcpp/grpcpp.h>
#include <png.h>
#include <signal.h>

#include <atomic>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>
#include <thread>

#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/util/sha256.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;
using namespace std::chrono_literals;

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

bool PngDecodes(const fs::path& p) {
  png_image img{};
  img.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_file(&img, p.c_str())) return false;
  img.format = PNG_FORMAT_RGBA;
  std::vector<unsigned char> px(PNG_IMAGE_SIZE(img));
  bool ok = png_image_finish_read(&img, nullptr, px.data(), 0, nullptr) != 0;
  return ok && img.width > 0 && img.height > 0;
}

std::unique_ptr<grpc::ClientContext> Ctx(const std::string& token = "") {
  auto ctx = std::make_unique<grpc::ClientContext>();
  ctx->set_deadline(std::chrono::system_clock::now() + 30s);
  if (!token.empty()) ctx->AddMetadata("authorization", "Bearer " + token);
  return ctx;
}

class ServiceE2E : public ScratchTest {
 protected:
  ServiceE2E() : ScratchTest("service_e2e") {}
};

TEST_F(ServiceE2E, HealthServesAndReportsUnavailableWhenNoServer) {
  ServerProcess server(scratch_ / "data");
  CliResult r = RunCli(server.address(), {"health"});
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("SERVING"));
  server.Kill(SIGKILL);
  r = RunCli(server.address(), {"--timeout", "2", "health"});
  EXPECT_EQ(r.rc, 8) << r.out << r.err;
}

TEST_F(ServiceE2E, SubmitWatchOutLeavesEveryArtifact) {
  ServerProcess server(scratch_ / "data");
  std::vector<fs::path> inputs = {volume_};
#ifdef __SANITIZE_THREAD__
  // Under ThreadSanitizer the job child runs the whole pipeline instrumented and on one thread
  // (OpenMP is off: libgomp is not instrumented), ~15x slower: the real CT took longer than the
  // CLI's 60 s timeout. It exercises no concurrency the phantom does not, so only the phantom
  // runs here; the plain and ASan builds run both.
  std::fprintf(stderr, "ThreadSanitizer build: the real CT is left to the other builds\n");
#else
  if (auto ct = testing::SharedDataFile("ct-head-128x128x53.nii.gz")) inputs.push_back(*ct);
#endif
  for (const auto& input : inputs) {
    fs::path out = scratch_ / ("out-" + input.filename().string());
    // The real CT job takes ~11 s alone; 240 s leaves room for a machine busy with the other
    // tests of a parallel ctest (it once went past 60 s at load 10-28).
    CliResult r =
        RunCli(server.address(),
               {"submit", input.string(), "--watch", "--out", out.string(), "--image-size", "64"},
               std::chrono::seconds(240));
    ASSERT_EQ(r.rc, 0) << r.err << server.Log();
    EXPECT_THAT(FirstLine(r.out), HasSubstr("jobs/"));
    EXPECT_THAT(r.err, HasSubstr("SUCCEEDED"));
    std::string vtu = ReadFile(out / "mesh.vtu");
    EXPECT_THAT(vtu, HasSubstr("<VTKFile"));
    EXPECT_THAT(vtu, HasSubstr("UnstructuredGrid"));
    EXPECT_FALSE(fs::exists(out / "mesh.msh"));  // only when asked for (--outputs msh)
    EXPECT_TRUE(fs::exists(out / "report.html"));
    EXPECT_TRUE(PngDecodes(out / "segmentation.png"));
    for (const char* png : {"original.png", "simplified.png", "diff.png", "comparison.png"}) {
      EXPECT_TRUE(PngDecodes(out / png)) << png;
    }
    auto metrics = nlohmann::json::parse(ReadFile(out / "metrics.json"), nullptr, false);
    ASSERT_TRUE(metrics.is_object()) << ReadFile(out / "metrics.json");
    EXPECT_TRUE(metrics.contains("diff1")) << metrics.dump();
  }
}

TEST_F(ServiceE2E, CancelStopsARunningJobWithinASecondAndTheWorkerTakesTheNext) {
  ServerProcess server(scratch_ / "data", {"--workers", "1", "--allow-faults"});
  CliResult a = RunCli(server.address(), {"submit", volume_.string(), "--fault", "sleep:40"});
  ASSERT_EQ(a.rc, 0) << a.err;
  std::string job_a = FirstLine(a.out);
  CliResult b = RunCli(server.address(), {"submit", volume_.string()});
  ASSERT_EQ(b.rc, 0) << b.err;
  std::string job_b = FirstLine(b.out);
  ASSERT_TRUE(WaitFor([&] { return GetJob(server.address(), job_a).state() == v1::RUNNING; }, 30s));
  EXPECT_EQ(GetJob(server.address(), job_b).state(), v1::QUEUED);

  auto t0 = std::chrono::steady_clock::now();
  CliResult c = RunCli(server.address(), {"cancel", job_a});
  auto cancel_time = std::chrono::steady_clock::now() - t0;
  ASSERT_EQ(c.rc, 0) << c.err;
  EXPECT_THAT(c.out, HasSubstr("CANCELLED"));
#ifdef __SANITIZE_THREAD__
  // The time includes starting the CLI process, which under ThreadSanitizer (its runtime set-up,
  // every gRPC call instrumented) took 1.17 s on a loaded machine; the promise is checked at 1 s
  // by the plain and ASan builds.
  constexpr auto kCancelBound = 3s;
#else
  constexpr auto kCancelBound = 1s;
#endif
  EXPECT_LT(cancel_time, kCancelBound)
      << "cancel took " << std::chrono::duration<double>(cancel_time).count() << " s";
  EXPECT_EQ(GetJob(server.address(), job_a).state(), v1::CANCELLED);

  CliResult w = RunCli(server.address(), {"watch", job_b});
  EXPECT_EQ(w.rc, 0) << w.err;
  EXPECT_EQ(GetJob(server.address(), job_b).state(), v1::SUCCEEDED);
  // A cancelled job can be retried.
  CliResult rt = RunCli(server.address(), {"retry", job_a});
  EXPECT_EQ(rt.rc, 0) << rt.err;
  EXPECT_THAT(rt.out, HasSubstr("QUEUED"));
}

TEST_F(ServiceE2E, ServerKilledWithJobsQueuedAndRunningCompletesEveryJobAfterRestart) {
  fs::path data = scratch_ / "data";
  std::vector<std::string> jobs;
  {
    ServerProcess server(data, {"--workers", "1", "--allow-faults"});
    // The first job must still be running when the third submit returns: under ThreadSanitizer
    // each CLI process takes over a second to start, and a one-second job had finished before the
    // test looked (CI, stop 42).
    const std::string first_sleep = "sleep:" + std::to_string(kSlowdown == 1 ? 1 : 6);
    for (int i = 0; i < 3; ++i) {
      CliResult r = RunCli(server.address(),
                           {"submit", volume_.string(), "--fault", i == 0 ? first_sleep : "sleep:1"});
      ASSERT_EQ(r.rc, 0) << r.err;
      jobs.push_back(FirstLine(r.out));
    }
    ASSERT_TRUE(
        WaitFor([&] { return GetJob(server.address(), jobs[0]).state() == v1::RUNNING; }, 30s));
    server.Kill(SIGKILL);
  }
  ServerProcess server(data, {"--workers", "1", "--allow-faults"});
  for (const auto& j : jobs) {
    CliResult w = RunCli(server.address(), {"watch", j});
    EXPECT_EQ(w.rc, 0) << j << ": " << w.err << server.Log();
  }
  v1::Job first = GetJob(server.address(), jobs[0]);
  EXPECT_EQ(first.state(), v1::SUCCEEDED);
  EXPECT_EQ(first.attempts(), 2) << "the job running at the kill runs again";
  // Its event log is one gapless sequence across both server lives.
  auto seqs = Sequences(WatchAll(server.address(), jobs[0]));
  for (size_t i = 0; i < seqs.size(); ++i) EXPECT_EQ(seqs[i], static_cast<int64_t>(i + 1));
}

TEST_F(ServiceE2E, CrashingPipelineFailsTheJobAndTheServerStaysUp) {
  ServerProcess server(scratch_ / "data", {"--allow-faults"});
  CliResult r =
      RunCli(server.address(), {"submit", volume_.string(), "--fault", "crash", "--watch"});
  EXPECT_EQ(r.rc, 3) << r.err;
  std::string job = FirstLine(r.out);
  v1::Job j = GetJob(server.address(), job);
  EXPECT_EQ(j.state(), v1::FAILED);
  EXPECT_THAT(j.error().message(), HasSubstr("signal"));
  EXPECT_EQ(RunCli(server.address(), {"health"}).rc, 0);
  CliResult ok = RunCli(server.address(), {"submit", volume_.string(), "--watch"});
  EXPECT_EQ(ok.rc, 0) << ok.err;
}

// Twenty jobs per client in the plain build; five under ThreadSanitizer, where the 80 pipeline
// runs alone took 3.5 of the sanitizer half's 7 e2e minutes (CI's 45-minute budget) and 20
// concurrent submits and watchers exercise the same queue, lease and watch code as 80.
TEST_F(ServiceE2E, FourClientsManyJobsEachTwoWorkersAllSucceedOnceInOrder) {
  constexpr int kJobsPerClient = kSlowdown == 1 ? 20 : 5;
  ServerProcess server(scratch_ / "data", {"--workers", "2", "--max-queued", "1000"});
  // Different volumes per client so uploads really happen (and dedup within a client).
  std::vector<fs::path> vols;
  for (int c = 0; c < 4; ++c) {
    vols.push_back(scratch_ / ("client" + std::to_string(c) + ".nii"));
    WriteTinyNifti(vols.back(), 10, 10, 6, c + 1);
  }
  std::atomic<int> max_running{0};
  std::atomic<bool> sampling{true};
  std::thread sampler_thread([&] {
    auto stub = v1::Jobs::NewStub(
        grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials()));
    while (sampling) {
      v1::ListJobsRequest req;
      req.add_states(v1::RUNNING);
      req.set_page_size(100);
      v1::ListJobsResponse resp;
      if (stub->ListJobs(Ctx().get(), req, &resp).ok()) {
        int n = resp.jobs_size();
        int prev = max_running.load();
        while (n > prev && !max_running.compare_exchange_weak(prev, n)) {
        }
      }
      std::this_thread::sleep_for(5ms);
    }
  });
  // Stopped and joined on every way out, a failed ASSERT included (a joinable std::thread
  // destroyed would abort the whole test binary).
  struct StopSampler {
    std::atomic<bool>& sampling;
    std::thread& thread;
    void Stop() {
      sampling = false;
      if (thread.joinable()) thread.join();
    }
    ~StopSampler() { Stop(); }
  } sampler{sampling, sampler_thread};
  std::vector<std::vector<std::string>> jobs(4);
  std::vector<std::thread> clients;
  for (int c = 0; c < 4; ++c) {
    clients.emplace_back([&, c] {
      for (int i = 0; i < kJobsPerClient; ++i) {
        // Small renders keep 80 real pipeline runs within the watchers' deadline on 2 cores.
        // Not quiet: if a submit fails, what it said (retries included) is in the failure.
        CliResult r = RunCli(server.address(), {"submit", vols[c].string(), "--image-size", "32"});
        if (r.rc != 0) {
          ADD_FAILURE() << "client " << c << ", submit " << i << ": exit " << r.rc << "\n" << r.err;
          return;
        }
        jobs[c].push_back(FirstLine(r.out));
      }
    });
  }
  for (auto& t : clients) t.join();
  // One watcher per job, all at once, each must see ordered events ending in SUCCEEDED.
  std::vector<std::string> all;
  for (auto& v : jobs) all.insert(all.end(), v.begin(), v.end());
  ASSERT_EQ(all.size(), size_t{4 * kJobsPerClient});
  std::vector<std::vector<v1::JobEvent>> seen(all.size());
  std::vector<std::thread> watchers;
  for (size_t i = 0; i < all.size(); ++i) {
    watchers.emplace_back([&, i] { seen[i] = WatchAll(server.address(), all[i]); });
  }
  for (auto& t : watchers) t.join();
  sampler.Stop();
  for (size_t i = 0; i < all.size(); ++i) {
    const auto& ev = seen[i];
    ASSERT_FALSE(ev.empty()) << all[i];
    EXPECT_TRUE(ev.front().has_snapshot());
    auto seqs = Sequences(ev);
    for (size_t k = 0; k < seqs.size(); ++k) {
      ASSERT_EQ(seqs[k], static_cast<int64_t>(k + 1)) << all[i];
    }
    ASSERT_TRUE(ev.back().has_state_change()) << all[i];
    EXPECT_EQ(ev.back().state_change().state(), v1::SUCCEEDED) << all[i];
    int runs = 0;
    for (const auto& e : ev)
      runs += e.has_state_change() && e.state_change().state() == v1::RUNNING;
    EXPECT_EQ(runs, 1) << all[i] << " ran more than once";
    EXPECT_EQ(GetJob(server.address(), all[i]).attempts(), 1);
  }
  EXPECT_LE(max_running.load(), 2) << "more jobs ran at once than workers";
  EXPECT_GE(max_running.load(), 1);
}

TEST_F(ServiceE2E, WatcherThatReconnectsWithItsLastSequenceSeesNoGap) {
  ServerProcess server(scratch_ / "data", {"--allow-faults"});
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--fault", "sleep:1.5"});
  ASSERT_EQ(r.rc, 0) << r.err;
  std::string job = FirstLine(r.out);
  // First connection: leave after 5 progress events.
  auto part1 = WatchAll(server.address(), job, 0, 5);
  auto seq1 = Sequences(part1);
  ASSERT_FALSE(seq1.empty());
  // Resume from the last sequence seen.
  auto part2 = WatchAll(server.address(), job, seq1.back());
  auto seq2 = Sequences(part2);
  std::vector<int64_t> all = seq1;
  all.insert(all.end(), seq2.begin(), seq2.end());
  for (size_t k = 0; k < all.size(); ++k) ASSERT_EQ(all[k], static_cast<int64_t>(k + 1));
  ASSERT_FALSE(part2.empty());
  EXPECT_TRUE(part2.back().has_state_change());
  EXPECT_EQ(part2.back().state_change().state(), v1::SUCCEEDED);
  // The CLI's own watch of the finished job ends at once with the job's exit code.
  CliResult w = RunCli(server.address(), {"--json", "watch", job});
  EXPECT_EQ(w.rc, 0) << w.err;
  EXPECT_THAT(w.out, HasSubstr("\"snapshot\""));
}

TEST_F(ServiceE2E, InterruptedUploadResumesWhereTheServerSaysItStopped) {
  ServerProcess server(scratch_ / "data");
  fs::path big = scratch_ / "big.nii";
  WriteTinyNifti(big, 160, 160, 64, 7);  // 3.3 MB: four chunks
  std::string bytes = ReadFile(big);
  auto sha = server::Sha256OfFile(big);
  ASSERT_TRUE(sha.ok());
  auto channel = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto stub = v1::Uploads::NewStub(channel);
  {
    grpc::ClientContext ctx;
    v1::Blob blob;
    auto writer = stub->Upload(&ctx, &blob);
    v1::UploadRequest req;
    req.set_sha256(*sha);
    req.set_size_bytes(static_cast<int64_t>(bytes.size()));
    req.set_data(bytes.substr(0, 1 << 20));
    ASSERT_TRUE(writer->Write(req));
    req.Clear();
    req.set_data(bytes.substr(1 << 20, 1 << 20));
    ASSERT_TRUE(writer->Write(req));
    writer->WritesDone();  // ends half-way: the server keeps the prefix
    grpc::Status s = writer->Finish();
    EXPECT_EQ(s.error_code(), grpc::StatusCode::ABORTED) << s.error_message();
  }
  v1::GetUploadStatusRequest sreq;
  sreq.set_sha256(*sha);
  sreq.set_size_bytes(static_cast<int64_t>(bytes.size()));
  v1::UploadStatus st;
  ASSERT_TRUE(stub->GetUploadStatus(Ctx().get(), sreq, &st).ok());
  EXPECT_FALSE(st.complete());
  EXPECT_EQ(st.committed_size(), 2 << 20);
  CliResult r = RunCli(server.address(), {"submit", big.string()});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.err, HasSubstr("resumed upload of big.nii at byte 2097152"));
  ASSERT_TRUE(stub->GetUploadStatus(Ctx().get(), sreq, &st).ok());
  EXPECT_TRUE(st.complete());
}

TEST_F(ServiceE2E, BadRequestsGetTheirCodesAndStoreNothing) {
  fs::path token_file = scratch_ / "token";
  std::ofstream(token_file) << "s3cret\n";
  // A blob named by a failed CreateVolume belongs to its upload until the grace lapses (1 s).
  ServerProcess server(scratch_ / "data", {"--token-file", token_file.string(), "--max-upload-mb",
                                           "1", "--blob-grace-seconds", "1"});
  std::map<std::string, std::string> env = {{"DECIMA_TOKEN", "s3cret"}};
  // Wrong and missing token.
  CliResult r = RunCli(server.address(), {"--token", "nope", "list"});
  EXPECT_EQ(r.rc, 7) << r.err;
  EXPECT_THAT(r.err, HasSubstr("UNAUTHENTICATED"));
  r = RunCli(server.address(), {"list"});
  EXPECT_EQ(r.rc, 7) << r.err;
  EXPECT_EQ(RunCli(server.address(), {"list"}, 60s, env).rc, 0);
  // Unknown id.
  r = RunCli(server.address(), {"status", "0123456789abcdef"}, 60s, env);
  EXPECT_EQ(r.rc, 6) << r.err;
  EXPECT_THAT(r.err, HasSubstr("NOT_FOUND"));
  // Oversized upload.
  fs::path big = scratch_ / "big.nii";
  WriteTinyNifti(big, 128, 128, 40);  // 1.3 MB > 1 MiB
  r = RunCli(server.address(), {"submit", big.string()}, 60s, env);
  EXPECT_EQ(r.rc, 1) << r.err;
  EXPECT_THAT(r.err, HasSubstr("INVALID_ARGUMENT"));
  EXPECT_THAT(r.err, HasSubstr("max-upload-mb"));
  // Garbage submitted as a volume.
  fs::path garbage = scratch_ / "garbage.nii.gz";
  std::ofstream(garbage) << std::string(4000, 'x');
  r = RunCli(server.address(), {"submit", garbage.string()}, 60s, env);
  EXPECT_EQ(r.rc, 1) << r.err;
  EXPECT_THAT(r.err, HasSubstr("INVALID_ARGUMENT"));
  EXPECT_THAT(r.err, HasSubstr("garbage.nii.gz"));
  // Corrupted upload: the data does not match the declared digest.
  auto stub = v1::Uploads::NewStub(
      grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials()));
  std::string data(1000, 'a');
  std::string wrong_sha(64, 'b');
  {
    auto ctx = Ctx("s3cret");
    v1::Blob blob;
    auto writer = stub->Upload(ctx.get(), &blob);
    v1::UploadRequest req;
    req.set_sha256(wrong_sha);
    req.set_size_bytes(1000);
    req.set_data(data);
    writer->Write(req);
    writer->WritesDone();
    grpc::Status s = writer->Finish();
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_THAT(s.error_message(), HasSubstr("checksum mismatch"));
  }
  v1::GetUploadStatusRequest sreq;
  sreq.set_sha256(wrong_sha);
  sreq.set_size_bytes(1000);
  v1::UploadStatus st;
  ASSERT_TRUE(stub->GetUploadStatus(Ctx("s3cret").get(), sreq, &st).ok());
  EXPECT_FALSE(st.complete());
  EXPECT_EQ(st.committed_size(), 0);
  // Nothing kept by any of the failures: no blob once the collector ran, no partial, no
  // volume, no job.
  auto blob_files = [&] {
    size_t files = 0;
    for (auto& e : fs::recursive_directory_iterator(server.data_dir() / "blobs")) {
      files += e.is_regular_file();
    }
    return files;
  };
  EXPECT_TRUE(WaitFor([&] { return blob_files() == 0; }, 10s)) << blob_files() << " files left";
  auto vstub = v1::Volumes::NewStub(
      grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials()));
  v1::ListVolumesResponse vols;
  ASSERT_TRUE(vstub->ListVolumes(Ctx("s3cret").get(), v1::ListVolumesRequest(), &vols).ok());
  EXPECT_EQ(vols.volumes_size(), 0);
  r = RunCli(server.address(), {"list"}, 60s, env);
  EXPECT_EQ(r.out, "");
}

TEST_F(ServiceE2E, FullQueueIsResourceExhaustedDrainingIsUnavailableAndSigtermRequeues) {
  // The drain window must outlast the health and list calls below even under ThreadSanitizer on
  // a loaded machine (at 3 s it closed before them: "connection refused", or CANCELLED mid-call).
  ServerProcess server(scratch_ / "data", {"--workers", "1", "--max-queued", "1", "--allow-faults",
                                           "--drain-seconds", "12"});
  CliResult a = RunCli(server.address(), {"submit", volume_.string(), "--fault", "sleep:30"});
  ASSERT_EQ(a.rc, 0) << a.err;
  ASSERT_TRUE(WaitFor(
      [&] { return GetJob(server.address(), FirstLine(a.out)).state() == v1::RUNNING; }, 30s));
  CliResult b = RunCli(server.address(), {"submit", volume_.string()});
  ASSERT_EQ(b.rc, 0) << b.err;
  CliResult c = RunCli(server.address(), {"submit", volume_.string()});
  EXPECT_EQ(c.rc, 1) << c.err;
  EXPECT_THAT(c.err, HasSubstr("RESOURCE_EXHAUSTED"));
  // SIGTERM: health turns NOT_SERVING and calls are UNAVAILABLE while the running job gets its
  // drain time; then it goes back to the queue and the server stops cleanly.
  fs::path data = server.data_dir();
  server.Signal(SIGTERM);
  ASSERT_TRUE(WaitFor([&] { return RunCli(server.address(), {"health"}).rc == 8; }, 10s));
  CliResult l = RunCli(server.address(), {"--reconnect", "0", "list"});
  EXPECT_EQ(l.rc, 8) << l.err;
  EXPECT_THAT(l.err, HasSubstr("UNAVAILABLE"));
  server.Kill(SIGTERM);
  ServerProcess again(data, {"--workers", "1", "--allow-faults"});
  v1::Job job = GetJob(again.address(), FirstLine(a.out));
  EXPECT_TRUE(job.state() == v1::QUEUED || job.state() == v1::RUNNING)
      << v1::JobState_Name(job.state());
  EXPECT_THAT(again.Log(), ::testing::Not(HasSubstr("error")));
}

}  // namespace
}  // namespace decima::e2e
