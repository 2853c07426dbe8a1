// The job child's main (`decima-server --run-job REQUEST`), run as the runner runs it: a request
// it cannot read gives exit 2 and one error frame; a small phantom job gives progress frames,
// then exactly one result, and exit 0.
#include "server/jobs/worker_process.h"

#include <sys/wait.h>
#include <unistd.h>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <vector>

#include "core/io/volume_io.h"
#include "core/volume/phantom.h"
#include "server/jobs/child_process.h"
#include "server/jobs/job_spec.h"
#include "server/jobs/worker.pb.h"
#include "server/jobs/worker_protocol.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

struct ChildRun {
  std::vector<worker::WorkerMessage> frames;
  absl::Status protocol;
  int wait_status = 0;
};

ChildRun RunChild(const fs::path& request, const fs::path& dir) {
  ChildOptions o;
  o.argv = {DECIMA_SERVER_BIN, "--run-job", request.string()};
  o.log = dir / "worker.log";
  o.protocol_fd = kWorkerFd;
  ChildRun run;
  auto child = ChildProcess::Spawn(o);
  EXPECT_TRUE(child.ok()) << child.status();
  if (!child.ok()) return run;
  FrameReader reader;
  char buf[65536];
  for (ssize_t n; (n = ::read((*child)->fd(), buf, sizeof buf)) != 0;) {
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) break;
    reader.Append(buf, static_cast<size_t>(n));
    worker::WorkerMessage m;
    while (reader.Next(&m)) run.frames.push_back(m);
  }
  run.protocol = reader.status();
  if (run.protocol.ok() && reader.pending() > 0) run.protocol = absl::DataLossError("cut off");
  run.wait_status = (*child)->Wait();
  return run;
}

int ExitCode(const ChildRun& run) {
  return WIFEXITED(run.wait_status) ? WEXITSTATUS(run.wait_status) : -1;
}

TEST(WorkerProcess, AMissingRequestFileGivesExit2AndOneErrorFrame) {
  const fs::path dir = testing::MakeScratchDir("worker_process");
  const ChildRun run = RunChild(dir / "no-such-request.pb", dir);
  EXPECT_EQ(ExitCode(run), kWorkerExitError);
  ASSERT_TRUE(run.protocol.ok()) << run.protocol;
  ASSERT_EQ(run.frames.size(), 1u);
  ASSERT_TRUE(run.frames[0].has_error());
  EXPECT_EQ(run.frames[0].error().code(), static_cast<int>(absl::StatusCode::kInternal));
  EXPECT_THAT(run.frames[0].error().message(), HasSubstr("no-such-request.pb"));
}

TEST(WorkerProcess, AGarbageRequestFileGivesExit2AndOneErrorFrame) {
  const fs::path dir = testing::MakeScratchDir("worker_process");
  const fs::path request = dir / "request.pb";
  // Not a RunRequest: field 1 says length 0x7f but the bytes end first.
  std::ofstream(request, std::ios::binary) << std::string("\x0a\x7f garbage", 10);
  const ChildRun run = RunChild(request, dir);
  EXPECT_EQ(ExitCode(run), kWorkerExitError);
  ASSERT_EQ(run.frames.size(), 1u);
  ASSERT_TRUE(run.frames[0].has_error());
  EXPECT_THAT(run.frames[0].error().message(), HasSubstr("cannot read " + request.string()));
}

TEST(WorkerProcess, AnInvalidStoredSpecGivesExit2AndAnErrorNamingTheField) {
  const fs::path dir = testing::MakeScratchDir("worker_process");
  worker::RunRequest req;
  req.mutable_spec()->set_volume("volumes/v");
  req.mutable_spec()->set_target_reduction(7);  // a fraction 0..1
  req.set_input((dir / "none.nii").string());
  req.set_out_dir((dir / "out").string());
  const fs::path request = dir / "request.pb";
  std::ofstream(request, std::ios::binary) << req.SerializeAsString();
  const ChildRun run = RunChild(request, dir);
  EXPECT_EQ(ExitCode(run), kWorkerExitError);
  ASSERT_EQ(run.frames.size(), 1u);
  ASSERT_TRUE(run.frames[0].has_error());
  EXPECT_EQ(run.frames[0].error().code(), static_cast<int>(absl::StatusCode::kInvalidArgument));
  EXPECT_THAT(run.frames[0].error().message(), HasSubstr("target_reduction"));
}

TEST(WorkerProcess, APhantomJobGivesProgressFramesThenOneResult) {
  const fs::path dir = testing::MakeScratchDir("worker_process");
  HeadPhantomOptions o;
  o.dims = {24, 24, 20};
  o.spacing = {2, 2, 2};
  o.noise_sigma = 20;
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok()) << p.status();
  ASSERT_TRUE(io::WriteNifti(p->image, dir / "phantom.nii.gz").ok());
  v1::JobSpec spec;
  spec.set_volume("volumes/v");
  spec.set_image_size(48);
  spec.add_outputs("vtu");
  spec.add_outputs("labels");
  auto normalized = NormalizeJobSpec(spec);
  ASSERT_TRUE(normalized.ok()) << normalized.status();
  worker::RunRequest req;
  *req.mutable_spec() = *normalized;
  req.set_input((dir / "phantom.nii.gz").string());
  req.set_out_dir((dir / "out").string());
  fs::create_directories(dir / "out");
  const fs::path request = dir / "request.pb";
  std::ofstream(request, std::ios::binary) << req.SerializeAsString();

  const ChildRun run = RunChild(request, dir);
  EXPECT_EQ(ExitCode(run), kWorkerExitOk);
  ASSERT_TRUE(run.protocol.ok()) << run.protocol;
  ASSERT_GE(run.frames.size(), 2u);
  std::set<std::string> stages;
  for (size_t i = 0; i + 1 < run.frames.size(); ++i) {
    ASSERT_TRUE(run.frames[i].has_progress()) << "frame " << i << " before the last";
    stages.insert(run.frames[i].progress().stage());
  }
  for (const char* stage : {"load", "segment", "simplify"})
    EXPECT_TRUE(stages.count(stage)) << stage;
  const worker::WorkerMessage& last = run.frames.back();
  ASSERT_TRUE(last.has_result()) << last.DebugString();
  std::set<std::string> names;
  for (const auto& a : last.result().artifacts()) {
    names.insert(a.name());
    EXPECT_EQ(fs::path(a.path()).parent_path(), dir / "out");
    EXPECT_EQ(a.size_bytes(), static_cast<int64_t>(fs::file_size(a.path())));
  }
  EXPECT_TRUE(names.count("labels.nii.gz") || names.count("labels.nii")) << last.DebugString();
  EXPECT_FALSE(last.result().metrics_json().empty());
}

}  // namespace
}  // namespace decima::server
