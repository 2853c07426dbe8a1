// End-to-end cases of the hardening issue: each was a failure probed from outside (a
// decompression bomb, a full disk, one client deleting another's upload, series selection, a
// busy port, watchers across a graceful restart, leftovers of refused and cancelled work). Real
// decima-server and decima processes on loopback, one server per test.
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <unistd.h>
#include <zlib.h>

#include <cstring>
#include <fstream>
#include <optional>
#include <sstream>
#include <utility>

#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/util/sha256.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/process.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;
using namespace std::chrono_literals;

std::unique_ptr<grpc::ClientContext> Ctx() {
  auto ctx = std::make_unique<grpc::ClientContext>();
  ctx->set_deadline(std::chrono::system_clock::now() + 30s);
  return ctx;
}

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::string Sha(const std::string& bytes) {
  server::Sha256 h;
  h.Update(bytes.data(), bytes.size());
  return h.HexDigest();
}

// Uploads `bytes` whole (or only the first `send` bytes when >= 0, leaving a partial upload).
grpc::Status Upload(const std::string& address, const std::string& bytes, int64_t send = -1) {
  auto stub = v1::Uploads::NewStub(SharedChannel(address));
  auto ctx = Ctx();
  v1::Blob blob;
  auto writer = stub->Upload(ctx.get(), &blob);
  const size_t n = send < 0 ? bytes.size() : static_cast<size_t>(send);
  v1::UploadRequest req;
  req.set_sha256(Sha(bytes));
  req.set_size_bytes(static_cast<int64_t>(bytes.size()));
  for (size_t at = 0; at < n || at == 0; at += size_t{1} << 20) {
    req.set_data(bytes.substr(at, std::min(n - at, size_t{1} << 20)));
    if (!writer->Write(req)) break;
    req.clear_sha256();
    req.clear_size_bytes();
    if (n == 0) break;
  }
  writer->WritesDone();
  return writer->Finish();
}

grpc::Status CreateVolume(const std::string& address, const std::string& path,
                          const std::string& sha, v1::Volume* out) {
  auto stub = v1::Volumes::NewStub(SharedChannel(address));
  v1::CreateVolumeRequest req;
  auto* f = req.mutable_volume()->add_files();
  f->set_path(path);
  f->set_blob("blobs/" + sha);
  return stub->CreateVolume(Ctx().get(), req, out);
}

grpc::Status DeleteJob(const std::string& address, const std::string& name) {
  auto stub = v1::Jobs::NewStub(SharedChannel(address));
  v1::DeleteJobRequest req;
  req.set_name(name);
  v1::DeleteJobResponse resp;
  return stub->DeleteJob(Ctx().get(), req, &resp);
}

grpc::Status DeleteVolume(const std::string& address, const std::string& name) {
  auto stub = v1::Volumes::NewStub(SharedChannel(address));
  v1::DeleteVolumeRequest req;
  req.set_name(name);
  v1::DeleteVolumeResponse resp;
  return stub->DeleteVolume(Ctx().get(), req, &resp);
}

std::vector<v1::Volume> ListVolumes(const std::string& address) {
  auto stub = v1::Volumes::NewStub(SharedChannel(address));
  v1::ListVolumesResponse resp;
  EXPECT_TRUE(stub->ListVolumes(Ctx().get(), v1::ListVolumesRequest(), &resp).ok());
  return {resp.volumes().begin(), resp.volumes().end()};
}

// Regular files under `dir` (0 if it does not exist).
size_t FileCount(const fs::path& dir) {
  size_t n = 0;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    n += it->is_regular_file();
  }
  return n;
}

// The peak resident set of process `pid` in bytes (VmHWM), or -1.
int64_t PeakRss(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::stoll(line.substr(6)) * 1024;
  }
  return -1;
}

// A gzip-compressed NIfTI-1 of uint8 zeros, nx*ny*nz voxels: a few hundred KB that declare
// hundreds of MB.
void WriteNiftiGzBomb(const fs::path& path, int nx, int ny, int nz) {
  const std::string hdr = NiftiHeader(nx, ny, nz, /*uint8*/ 2, 8, 1.0f);
  gzFile gz = gzopen(path.c_str(), "wb1");
  ASSERT_NE(gz, nullptr);
  gzwrite(gz, hdr.data(), static_cast<unsigned>(hdr.size()));
  const std::vector<char> zeros(1 << 20, 0);
  int64_t left = int64_t{nx} * ny * nz;
  while (left > 0) {
    const int n = static_cast<int>(std::min<int64_t>(left, zeros.size()));
    ASSERT_EQ(gzwrite(gz, zeros.data(), n), n);
    left -= n;
  }
  gzclose(gz);
}

class HardeningE2E : public ScratchTest {
 protected:
  HardeningE2E() : ScratchTest("hardening_e2e", /*phantom=*/true, 24, 24, 16) {}
};

// Issue case 3: a CreateVolume whose header check fails used to delete every blob of its
// manifest that no volume used, so naming another client's fresh upload destroyed it.
TEST_F(HardeningE2E, FailedCreateVolumeDeletesNoBlobAnotherClientUploaded) {
  ServerProcess server(scratch_ / "data");
  const std::string nifti = ReadFile(volume_);
  ASSERT_TRUE(Upload(server.address(), nifti).ok());  // client A
  v1::Volume vol;
  // Client B names A's blob as a MetaImage: the header check fails.
  grpc::Status b = CreateVolume(server.address(), "x.mha", Sha(nifti), &vol);
  EXPECT_EQ(b.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << b.error_message();
  // A goes on as planned.
  grpc::Status a = CreateVolume(server.address(), "head.nii", Sha(nifti), &vol);
  EXPECT_TRUE(a.ok()) << a.error_message();
  EXPECT_EQ(vol.dims_size(), 3);
}

// Found by upload_fuzz: for a blob it already holds the server answers after the first message
// (deduplicated). A client still streaming its chunks (a second client sending the same scan, a
// retry after a lost answer) must get that answer, not wait on flow control for ever.
TEST_F(HardeningE2E, AnUploadOfABlobTheServerHoldsIsAnsweredWhileTheClientIsStillSending) {
  ServerProcess server(scratch_ / "data");
  const std::string bytes(size_t{6} << 20, 'z');  // 6 chunks of 1 MiB
  ASSERT_TRUE(Upload(server.address(), bytes).ok());
  const auto start = std::chrono::steady_clock::now();
  const grpc::Status again = Upload(server.address(), bytes);  // deadline 30 s
  const auto took = std::chrono::steady_clock::now() - start;
  EXPECT_TRUE(again.ok()) << again.error_code() << " " << again.error_message();
  EXPECT_LT(took, 10s);
  // The fuzzer's case: the empty blob, declared alone, then an over-long chunk.
  ASSERT_TRUE(Upload(server.address(), "").ok());
  auto stub = v1::Uploads::NewStub(SharedChannel(server.address()));
  auto ctx = Ctx();
  v1::Blob blob;
  auto writer = stub->Upload(ctx.get(), &blob);
  v1::UploadRequest req;
  req.set_sha256(Sha(""));
  EXPECT_TRUE(writer->Write(req));
  v1::UploadRequest chunk;
  chunk.set_data(std::string((size_t{1} << 20) + 1, 'z'));
  writer->Write(chunk);
  writer->WritesDone();
  const grpc::Status s = writer->Finish();
  EXPECT_TRUE(s.ok()) << s.error_code() << " " << s.error_message();
  EXPECT_TRUE(blob.deduplicated());  // answered from what the server holds
  EXPECT_EQ(blob.sha256(), Sha(""));
  EXPECT_EQ(blob.size_bytes(), 0);
  EXPECT_LT(std::chrono::steady_clock::now() - start, 10s);
}

// Issue case 2 (collection): a blob leaves once no volume holds it and its upload's claim
// lapsed; an interrupted upload leaves after its expiry; deleting everything returns the data
// dir to its empty size.
TEST_F(HardeningE2E, UnreferencedBlobsAndAbandonedUploadsAreCollected) {
  ServerProcess server(scratch_ / "data",
                       {"--blob-grace-seconds", "1", "--upload-expiry-seconds", "2"});
  const fs::path blobs = server.data_dir() / "blobs";
  CliResult r =
      RunCli(server.address(), {"-q", "submit", volume_.string(), "--watch"}, 60s * kSlowdown);
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string job = FirstLine(r.out);
  EXPECT_EQ(FileCount(blobs / "sha256"), 1u);
  // Past the grace, a referenced blob stays.
  std::this_thread::sleep_for(2500ms);
  EXPECT_EQ(FileCount(blobs / "sha256"), 1u);
  // An upload that stopped half-way.
  const std::string other(300000, 'z');
  EXPECT_FALSE(Upload(server.address(), other, 100000).ok());
  EXPECT_EQ(FileCount(blobs / "partial"), 1u);
  const auto volumes = ListVolumes(server.address());
  ASSERT_EQ(volumes.size(), 1u);
  ASSERT_TRUE(DeleteJob(server.address(), job).ok());
  ASSERT_TRUE(DeleteVolume(server.address(), volumes[0].name()).ok());
  // The volume's blob goes with the volume (its claim lapsed long ago).
  EXPECT_EQ(FileCount(blobs / "sha256"), 0u);
  EXPECT_TRUE(WaitFor([&] { return FileCount(blobs / "partial") == 0; }, 15s))
      << "the abandoned partial upload was not collected";
  EXPECT_EQ(FileCount(server.data_dir() / "volumes"), 0u);
  EXPECT_EQ(FileCount(server.data_dir() / "jobs"), 0u);
}

// A 48 MB tmpfs at `dir` for as long as the object lives (root only: nullopt otherwise), so a
// test can fill a disk without filling the machine's.
class SmallDisk {
 public:
  static std::optional<SmallDisk> Mount(const fs::path& dir) {
    fs::create_directories(dir);
    const std::string mount = "mount -t tmpfs -o size=48m tmpfs '" + dir.string() + "' 2>/dev/null";
    if (::geteuid() != 0 || std::system(mount.c_str()) != 0) return std::nullopt;
    return SmallDisk(dir);
  }
  SmallDisk(SmallDisk&& other) noexcept : dir_(std::exchange(other.dir_, fs::path())) {}
  SmallDisk(const SmallDisk&) = delete;
  SmallDisk& operator=(const SmallDisk&) = delete;
  SmallDisk& operator=(SmallDisk&&) = delete;
  ~SmallDisk() {
    if (!dir_.empty()) (void)std::system(("umount -l '" + dir_.string() + "'").c_str());
  }

 private:
  explicit SmallDisk(fs::path dir) : dir_(std::move(dir)) {}
  fs::path dir_;
};

// Issue case 2 (full disk): uploads are RESOURCE_EXHAUSTED with free and needed bytes and keep
// nothing; deletes work on the full disk (the reserve); freeing space heals it. Needs a small
// filesystem: a tmpfs mounted by the test (root only; skipped otherwise).
TEST_F(HardeningE2E, FullDiskRefusesUploadsKeepsNothingAndDeletesHealIt) {
  const fs::path mnt = scratch_ / "small";
  const std::optional<SmallDisk> disk = SmallDisk::Mount(mnt);
  if (!disk) GTEST_SKIP() << "cannot mount a 48 MB tmpfs here (needs root and CAP_SYS_ADMIN)";
  std::string job;
  {
    ServerProcess server(mnt / "data", {"--disk-reserve-mb", "4", "--blob-grace-seconds", "4"});
    ASSERT_TRUE(fs::exists(server.data_dir() / "reserve"));
    CliResult r =
        RunCli(server.address(), {"-q", "submit", volume_.string(), "--watch"}, 60s * kSlowdown);
    ASSERT_EQ(r.rc, 0) << r.err << server.Log();
    job = FirstLine(r.out);
    // Something else fills the disk.
    {
      std::ofstream filler(mnt / "filler", std::ios::binary);
      const std::string mb(1 << 20, 'f');
      for (int i = 0; i < 64 && filler.write(mb.data(), mb.size()); ++i) {
      }
    }
    fs::path second = scratch_ / "second.nii";
    WriteTinyNifti(second, 64, 64, 64, 7);  // 512 KB: more than the few KB left
    r = RunCli(server.address(), {"submit", second.string()});
    EXPECT_NE(r.rc, 0);
    EXPECT_THAT(r.err, HasSubstr("RESOURCE_EXHAUSTED"));
    EXPECT_THAT(r.err, HasSubstr("free"));
    EXPECT_THAT(r.err, Not(HasSubstr(mnt.string())));
    EXPECT_EQ(FileCount(server.data_dir() / "blobs" / "partial"), 0u)
        << "a refused upload must not keep the disk full";
    // Deletes work on the full disk and free its space.
    grpc::Status d = DeleteJob(server.address(), job);
    EXPECT_TRUE(d.ok()) << d.error_message();
    fs::remove(mnt / "filler");
    r = RunCli(server.address(), {"-q", "submit", second.string(), "--watch"}, 60s * kSlowdown);
    EXPECT_EQ(r.rc, 0) << r.err;
    // The reserve is allocated again once there is room.
    EXPECT_TRUE(WaitFor([&] { return fs::exists(server.data_dir() / "reserve"); }, 10s));
  }
}

// Issue 30, "disk needed for slabs is checked like uploads": a job simplified in slabs keeps
// records of them on the data dir (to resume after the last one); when they cannot fit, CreateJob
// refuses it with the bytes needed and free, and queues nothing. The same volume in memory is
// taken. On a 48 MB tmpfs (root only; skipped otherwise).
TEST_F(HardeningE2E, AStreamedJobWhoseSlabRecordsCannotFitIsRefusedAtSubmit) {
  const fs::path mnt = scratch_ / "small-slabs";
  const std::optional<SmallDisk> disk = SmallDisk::Mount(mnt);
  if (!disk) GTEST_SKIP() << "cannot mount a 48 MB tmpfs here (needs root and CAP_SYS_ADMIN)";
  ServerProcess server(mnt / "data", {"--disk-reserve-mb", "4"});
  const fs::path big = scratch_ / "slabs.nii";
  WriteTinyNifti(big, 96, 96, 96);  // 1.8 MB; its slab records at 80 %: about 58 MB
  CliResult r = RunCli(server.address(),
                       {"submit", big.string(), "--stream-slab-voxels", "16", "--reduction", "0.8"},
                       60s * kSlowdown);
  EXPECT_NE(r.rc, 0);
  EXPECT_THAT(r.err, HasSubstr("RESOURCE_EXHAUSTED"));
  EXPECT_THAT(r.err, HasSubstr("in slabs (records of its slabs to resume from) needs"));
  EXPECT_THAT(r.err, HasSubstr("free"));
  v1::ListJobsResponse jobs;
  ASSERT_TRUE(v1::Jobs::NewStub(SharedChannel(server.address()))
                  ->ListJobs(Ctx().get(), v1::ListJobsRequest(), &jobs)
                  .ok());
  EXPECT_EQ(jobs.jobs_size(), 0) << "a refused job was queued";
  r = RunCli(server.address(), {"submit", big.string(), "--reduction", "0.8"}, 60s * kSlowdown);
  EXPECT_EQ(r.rc, 0) << r.err;
}

// Issue case 1: CreateVolume reads headers only (a 0.5 MB .nii.gz declaring 512 MB costs the
// server nothing), and the job that would need far more memory than allowed is refused when it
// is submitted, saying how much it needs: nothing is queued (issue 30).
TEST_F(HardeningE2E, DecompressionBombCostsTheServerNothingAndItsJobIsRefusedWithTheNeed) {
  ServerProcess server(scratch_ / "data", {"--worker-memory-mb", "2048"});
  const fs::path bomb = scratch_ / "bomb.nii.gz";
  WriteNiftiGzBomb(bomb, 1024, 1024, 512);
  ASSERT_LT(fs::file_size(bomb), 4u << 20);
  const int64_t before = PeakRss(server.pid());
  CliResult r =
      RunCli(server.address(), {"-q", "submit", bomb.string(), "--watch"}, 120s * kSlowdown);
  EXPECT_EQ(r.rc, 1) << r.err;  // refused: no job to fail
  EXPECT_THAT(r.err, HasSubstr("1024x1024x512 voxels) needs about"));
  EXPECT_THAT(r.err, HasSubstr("more than the job limit of 2.0 GB"));
  EXPECT_THAT(r.err, HasSubstr("--worker-memory-mb"));
  v1::ListJobsResponse jobs;
  ASSERT_TRUE(v1::Jobs::NewStub(SharedChannel(server.address()))
                  ->ListJobs(Ctx().get(), v1::ListJobsRequest(), &jobs)
                  .ok());
  EXPECT_EQ(jobs.jobs_size(), 0) << "a refused job was queued";
  const int64_t after = PeakRss(server.pid());
  ASSERT_GT(before, 0);
  EXPECT_LT(after - before, int64_t{64} << 20)
      << "the server's peak RSS grew by " << (after - before) << " bytes";
}

// Issue 30: a job that cannot fit is refused at submit from the file's header (CheckJobMemory),
// with CreateJob's message, before a byte is uploaded: no blob, no partial upload, no volume on
// the server. A job that fits on the same server uploads as before (the counts can move).
TEST_F(HardeningE2E, AJobOverTheMemoryLimitIsRefusedBeforeAnyByteIsUploaded) {
  ServerProcess server(scratch_ / "data", {"--worker-memory-mb", "2048"});
  const fs::path blobs = server.data_dir() / "blobs";
  const fs::path big = scratch_ / "big.nii.gz";
  WriteNiftiGzBomb(big, 1024, 1024, 512);
  CliResult r = RunCli(server.address(), {"submit", big.string()}, 120s * kSlowdown);
  EXPECT_EQ(r.rc, 1) << r.err;
  EXPECT_THAT(r.err, HasSubstr("big.nii.gz (1024x1024x512 voxels) needs about"));
  EXPECT_THAT(r.err, HasSubstr("more than the job limit of 2.0 GB"));
  EXPECT_THAT(r.err, HasSubstr("--worker-memory-mb"));
  EXPECT_THAT(r.err, Not(HasSubstr("upload")));  // no progress line: nothing was sent
  EXPECT_EQ(FileCount(blobs / "sha256"), 0u);
  EXPECT_EQ(FileCount(blobs / "partial"), 0u);
  EXPECT_TRUE(ListVolumes(server.address()).empty());
  r = RunCli(server.address(), {"-q", "submit", volume_.string()}, 60s * kSlowdown);
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(FileCount(blobs / "sha256"), 1u);
  EXPECT_EQ(ListVolumes(server.address()).size(), 1u);
}

// Issue case 4: a folder with two series is refused with the list, processed when one is
// chosen, and an unknown UID is refused at CreateVolume.
TEST_F(HardeningE2E, SeriesInstanceUidIsHonouredEndToEnd) {
  const fs::path folder = scratch_ / "two-series";
  fs::create_directories(folder);
  testing::SliceSpec a, b;
  a.rows = a.columns = b.rows = b.columns = 24;
  a.series_uid = "1.2.826.0.1.3680043.9.7777.31";
  b.series_uid = "1.2.826.0.1.3680043.9.7777.32";
  a.value = [](int i, int j) { return (i - 12) * (i - 12) + (j - 12) * (j - 12) < 40 ? 900 : 50; };
  b.value = [](int i, int) { return i < 12 ? 800 : 30; };
  testing::WriteSeries(folder, a, std::vector<double>(11, 1.0), {}, "a");
  testing::WriteSeries(folder, b, std::vector<double>(7, 2.0), {}, "b");
  ServerProcess server(scratch_ / "data");
  CliResult r = RunCli(server.address(), {"submit", folder.string()});
  EXPECT_EQ(r.rc, 1) << r.err;
  EXPECT_THAT(r.err, HasSubstr(a.series_uid));
  EXPECT_THAT(r.err, HasSubstr(b.series_uid));
  r = RunCli(server.address(), {"submit", folder.string(), "--series", "1.2.3.4.404"});
  EXPECT_NE(r.rc, 0);
  EXPECT_THAT(r.err, HasSubstr("1.2.3.4.404"));
  EXPECT_THAT(r.err, Not(HasSubstr(server.data_dir().string())));
  r = RunCli(server.address(),
             {"-q", "submit", folder.string(), "--series", b.series_uid, "--watch"},
             120s * kSlowdown);
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  const v1::Job job = GetJob(server.address(), FirstLine(r.out));
  EXPECT_EQ(job.state(), v1::SUCCEEDED);
  // The job read series b: 24 x 24 x 8 voxels.
  EXPECT_THAT(job.metrics_json(), HasSubstr("\"voxels\": 4608")) << job.metrics_json();
}

// Issue 35 part 3: what the DICOM receiver does for a sender was never audited. A series sent
// by DCMTK's storescu queues a job, and the audit log holds it under the sender's principal.
TEST_F(HardeningE2E, AJobQueuedFromAReceivedDicomSeriesIsAudited) {
  const fs::path storescu = "/usr/bin/storescu";
  if (!fs::exists(storescu)) GTEST_SKIP() << "storescu (Debian package dcmtk) is not installed";
  const fs::path folder = scratch_ / "series";
  fs::create_directories(folder);
  testing::SliceSpec s;
  s.rows = s.columns = 16;
  s.series_uid = "1.2.826.0.1.3680043.9.7777.35";
  const auto files = testing::WriteSeries(folder, s, std::vector<double>(5, 1.0));
  const int dicom_port = testing::FreePort();
  ASSERT_GT(dicom_port, 0);
  const fs::path audit = scratch_ / "audit.log";
  ServerProcess server(
      scratch_ / "data",
      {"--dicom-listen", "127.0.0.1:" + std::to_string(dicom_port), "--dicom-min-free-mb", "0",
       "--dicom-quiet-seconds", "0.2", "--audit-log", audit.string()});
  std::vector<std::string> argv = {
      storescu.string(),         "-aet", "SENDER", "-aec", "DECIMA", "127.0.0.1",
      std::to_string(dicom_port)};
  for (const auto& f : files) argv.push_back(f.string());
  CliResult sent = RunProgram(argv, 60s);
  ASSERT_EQ(sent.rc, 0) << sent.out << sent.err << server.Log();
  std::string line;
  WaitFor(
      [&] {
        std::ifstream in(audit);
        for (std::string l; std::getline(in, l);) {
          if (l.find("DicomCreateJob") != std::string::npos) line = l;
        }
        return !line.empty();
      },
      30s);
  ASSERT_FALSE(line.empty()) << server.Log();
  EXPECT_THAT(line, HasSubstr(R"({"principal":"dicom:SENDER","role":"system",)"
                              R"("rpc":"DicomCreateJob","resource":"jobs/)"));
  EXPECT_THAT(line, HasSubstr(R"("result":"OK"})"));
}

// Issue case 6: gRPC's SO_REUSEPORT let a second server share a busy port.
TEST_F(HardeningE2E, BusyPortIsRefusedAtStart) {
  ServerProcess first(scratch_ / "data1");
  CliResult second = RunProgram({ServerBinary().string(), "--listen", first.address(), "--data-dir",
                                 (scratch_ / "data2").string()},
                                30s);
  EXPECT_EQ(second.rc, 1) << second.out << second.err;
  EXPECT_THAT(second.out + second.err, HasSubstr("cannot bind"));
}

// Issue case 7: SIGTERM ends watch streams with UNAVAILABLE, the client reconnects to the
// restarted server and sees the job through; a job that ends within the drain time finishes.
TEST_F(HardeningE2E, WatchersSurviveAGracefulRestartAndShortJobsFinishInTheDrain) {
  const std::string listen = "127.0.0.1:" + std::to_string(decima::testing::FreePort());
  const fs::path data = scratch_ / "data";
  std::string requeued, finished;
  CliProcess watch;
  {
    // Long enough for the 2 s job to finish in it, short enough that the first server stops
    // within ServerProcess's 50 s bound under ThreadSanitizer.
    const std::string drain = std::to_string(5 * kSlowdown);
    ServerProcess server(
        data, {"--listen", listen, "--allow-faults", "--workers", "2", "--drain-seconds", drain});
    // The first job must outlast the drain (it is requeued and its watcher reconnects): its
    // pause scales with the drain, since watch streams of running jobs stay open through it.
    CliResult r = RunCli(
        listen, {"submit", volume_.string(), "--fault", "sleep:" + std::to_string(12 * kSlowdown)});
    ASSERT_EQ(r.rc, 0) << r.err;
    requeued = FirstLine(r.out);
    r = RunCli(listen, {"submit", volume_.string(), "--fault", "sleep:2"});
    ASSERT_EQ(r.rc, 0) << r.err;
    finished = FirstLine(r.out);
    ASSERT_TRUE(WaitFor([&] { return GetJob(listen, finished).state() == v1::RUNNING; }, 30s));
    ASSERT_TRUE(WaitFor([&] { return GetJob(listen, requeued).state() == v1::RUNNING; }, 30s));
    // The watcher must be on its stream before the drain starts (a CLI that only starts
    // during the drain meets a server that refuses new calls, which is not this case): under
    // load a fixed pause was too short.
    watch = StartCli(listen, {"watch", requeued});
    if (!WaitFor([&] { return ReadFile(watch.err).find("watching") != std::string::npos; },
                 30s * kSlowdown)) {
      kill(watch.pid, SIGKILL);
      WaitCli(watch, 10s);
      FAIL() << "the watcher never got its snapshot: " << ReadFile(watch.err);
    }
    server.Kill(SIGTERM);
  }
  ServerProcess restarted(data, {"--listen", listen, "--allow-faults", "--workers", "2"});
  const v1::Job done = GetJob(listen, finished);
  EXPECT_EQ(done.state(), v1::SUCCEEDED);
  EXPECT_EQ(done.attempts(), 1) << "a job that ends within the drain time is not re-run";
  CliResult w = WaitCli(watch, 180s * kSlowdown);
  EXPECT_EQ(w.rc, 0) << w.err;
  EXPECT_THAT(w.err, Not(HasSubstr("CANCELLED")));
  EXPECT_THAT(w.err, HasSubstr("reconnecting"));
  // A drain's requeue does not count as a failed attempt.
  EXPECT_EQ(GetJob(listen, requeued).state(), v1::SUCCEEDED);
}

// Issue case 8: a label map read by a queued job cannot be deleted; a refused submit leaves no
// volume; a cancelled job keeps no output; -q still says why a job failed.
TEST_F(HardeningE2E, LeftoversOfRefusedCancelledAndFailedWork) {
  ServerProcess server(scratch_ / "data", {"--allow-faults", "--workers", "1"});
  // The worker is busy, so the next job stays QUEUED.
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--fault", "sleep:60"});
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string busy = FirstLine(r.out);
  const fs::path labels = scratch_ / "labels.nii";
  WriteTinyNifti(labels, 24, 24, 16, 3);
  r = RunCli(server.address(), {"submit", volume_.string(), "--label-map", labels.string()});
  ASSERT_EQ(r.rc, 0) << r.err;
  const v1::Job queued = GetJob(server.address(), FirstLine(r.out));
  ASSERT_EQ(queued.state(), v1::QUEUED);
  grpc::Status d = DeleteVolume(server.address(), queued.spec().label_map());
  EXPECT_EQ(d.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << d.error_message();
  // Refused submit (bad option value caught by the server): no volume stays.
  const size_t volumes_before = ListVolumes(server.address()).size();
  r = RunCli(server.address(), {"submit", volume_.string(), "--transfer-function", "no-such"});
  EXPECT_NE(r.rc, 0);
  EXPECT_THAT(r.err, HasSubstr("INVALID_ARGUMENT"));
  EXPECT_EQ(ListVolumes(server.address()).size(), volumes_before);
  // Cancel the running job: its output folder goes.
  ASSERT_TRUE(WaitFor([&] { return GetJob(server.address(), busy).state() == v1::RUNNING; }, 30s));
  // Its first claim (lease epoch 1) writes under attempts/1/ (data_dir.h).
  const fs::path out = server.data_dir() / "jobs" / busy.substr(5) / "attempts" / "1" / "out";
  ASSERT_TRUE(fs::exists(out));
  r = RunCli(server.address(), {"cancel", busy});
  ASSERT_EQ(r.rc, 0) << r.err;
  ASSERT_TRUE(
      WaitFor([&] { return GetJob(server.address(), busy).state() == v1::CANCELLED; }, 30s));
  EXPECT_FALSE(fs::exists(out));
  // A failing job under -q still says why.
  r = RunCli(server.address(), {"-q", "submit", volume_.string(), "--fault", "crash", "--watch"},
             120s);
  EXPECT_EQ(r.rc, 3);
  EXPECT_THAT(r.err, HasSubstr("FAILED"));
  EXPECT_THAT(r.err, HasSubstr("signal"));
  // A job failing on its input (a DICOM series missing a slice: only the job's load stage
  // sees it) names the files relative to the data dir, not where the server keeps them.
  const fs::path gap = scratch_ / "gap";
  fs::create_directories(gap);
  testing::SliceSpec slice;
  slice.rows = slice.columns = 16;
  testing::WriteSeries(gap, slice, {1.0, 1.0, 2.0, 1.0});
  r = RunCli(server.address(), {"-q", "submit", gap.string(), "--watch"}, 120s * kSlowdown);
  EXPECT_EQ(r.rc, 3) << r.err;
  EXPECT_THAT(r.err, HasSubstr("missing slice"));
  EXPECT_THAT(r.err, Not(HasSubstr(server.data_dir().string())));
  const v1::Job failing = GetJob(server.address(), FirstLine(r.out));
  EXPECT_THAT(failing.error().message(), Not(HasSubstr(server.data_dir().string())));
}

}  // namespace
}  // namespace decima::e2e
