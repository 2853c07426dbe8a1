// Real processes on loopback for the end-to-end tests: start decima-server on a free port with
// a scratch data dir, run the real `decima` binary, write tiny NIfTI volumes.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <grpcpp/grpcpp.h>

#include "decima/v1/jobs.pb.h"
#include "gtest/gtest.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {

struct CliResult {
  int rc = -1;  // exit code; 128+signal if killed
  std::string out, err;
};

class ServerProcess {
 public:
  // Starts decima-server with --data-dir `data_dir`, --listen 127.0.0.1:0 (unless `extra`
  // names --listen), `extra` flags;
  // waits until it wrote its port (fails the test after 30 s).
  ServerProcess(std::filesystem::path data_dir, std::vector<std::string> extra = {});
  ~ServerProcess();  // SIGKILL if still running

  std::string address() const { return "127.0.0.1:" + std::to_string(port_); }
  pid_t pid() const { return pid_; }
  void Kill(int sig);    // sends `sig` and reaps the process
  void Signal(int sig);  // sends `sig` only
  std::string Log() const;
  const std::filesystem::path& data_dir() const { return data_dir_; }

 private:
  std::filesystem::path data_dir_, log_;
  pid_t pid_ = -1;
  int port_ = 0;
};

// Runs `decima --server ADDR args...` and waits (killing it after `timeout`).
CliResult RunCli(const std::string& address, const std::vector<std::string>& args,
                 std::chrono::seconds timeout = std::chrono::seconds(60),
                 const std::map<std::string, std::string>& env = {});

// `decima --server ADDR args...` started without waiting (for signals while it runs); its
// stdout and stderr go to files that WaitCli reads.
struct CliProcess {
  pid_t pid = -1;
  std::filesystem::path out, err;
};
CliProcess StartCli(const std::string& address, const std::vector<std::string>& args);
CliResult WaitCli(const CliProcess& p, std::chrono::seconds timeout = std::chrono::seconds(60));

// How much slower the pipeline runs in this build: ThreadSanitizer instruments every access and
// runs the job processes on one thread (its libgomp is not instrumented). Timeouts and drain
// times that a job must meet are multiplied by it.
#ifdef __SANITIZE_THREAD__
inline constexpr int kSlowdown = 8;
#else
inline constexpr int kSlowdown = 1;
#endif

// Runs `argv` (argv[0] a path) to its end (killed after `timeout`), capturing its output.
CliResult RunProgram(const std::vector<std::string>& argv,
                     std::chrono::seconds timeout = std::chrono::seconds(60),
                     const std::map<std::string, std::string>& env = {});

// One plaintext channel per address for the whole process, as a client keeps its channel (and
// so follows a server restarted on the same address). A channel per call shuts gRPC down
// whenever the last one closes, and after an upload the server answered before the client had
// sent everything, that clean-up took 10 s in about 1 run of 100 on a loaded machine (traced:
// the time went between grpc_shutdown's start and the next call), which failed a timed test.
std::shared_ptr<grpc::Channel> SharedChannel(const std::string& address);

// GetJob over a fresh plaintext channel (fails the test on an error status).
v1::Job GetJob(const std::string& address, const std::string& name);

// The events of one WatchJob stream over a fresh plaintext channel, from `after` to the end of
// the stream, or until `stop_after` progress events were read (then the watch is cancelled).
// The stream's status goes to *status when given; *first_event (when given) is incremented
// once the first event (the snapshot) was read, so a test can wait for its watchers to be on.
std::vector<v1::JobEvent> WatchAll(const std::string& address, const std::string& name,
                                   int64_t after = 0, int stop_after = -1,
                                   grpc::Status* status = nullptr,
                                   std::chrono::seconds deadline = std::chrono::seconds(120),
                                   std::atomic<int>* first_event = nullptr);
// The sequence numbers of the events that are neither the snapshot nor heartbeats.
std::vector<int64_t> Sequences(const std::vector<v1::JobEvent>& events);

// A NIfTI-1 single-file header (352 bytes): dims, datatype code and bits, isotropic voxel size
// `mm`, identity qform.
std::string NiftiHeader(int nx, int ny, int nz, int16_t datatype, int16_t bitpix, float mm);

// A throwaway public-key infrastructure made with the `openssl` command in `dir`: a CA, a server
// certificate for 127.0.0.1/localhost, one client certificate per name (CN = the name), a
// client certificate from another CA, and an expired server certificate.
struct TestPki {
  std::filesystem::path dir;
  std::filesystem::path ca() const { return dir / "ca.pem"; }
  std::filesystem::path server_cert() const { return dir / "server.pem"; }
  std::filesystem::path server_key() const { return dir / "server.key"; }
  std::filesystem::path expired_cert() const { return dir / "expired.pem"; }  // key: server.key
  std::filesystem::path cert(const std::string& name) const { return dir / (name + ".pem"); }
  std::filesystem::path key(const std::string& name) const { return dir / (name + ".key"); }
  // A client certificate named "stranger", signed by another CA.
  std::filesystem::path stranger_cert() const { return dir / "stranger.pem"; }
  std::filesystem::path stranger_key() const { return dir / "stranger.key"; }
};
// "" on success, else what failed (the openssl command and its stderr). "openssl not found"
// when the command is absent (the caller skips).
std::string MakeTestPki(const std::filesystem::path& dir, const std::vector<std::string>& clients,
                        TestPki* pki);

// Polls `pred` every 20 ms until true or `timeout`; returns the last value.
template <typename Pred>
bool WaitFor(Pred pred, std::chrono::milliseconds timeout) {
  auto until = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    if (pred()) return true;
    if (std::chrono::steady_clock::now() > until) return false;
    struct timespec ts {
      0, 20 * 1000 * 1000
    };
    nanosleep(&ts, nullptr);
  }
}

// Writes a NIfTI-1 (.nii) int16 volume of `dims` with 2 mm voxels: a bright sphere in a darker
// box, plus `seed` added to one voxel so different seeds give different blobs.
void WriteTinyNifti(const std::filesystem::path& path, int nx, int ny, int nz, int seed = 0);

// The first line of `s` ("jobs/abc").
std::string FirstLine(const std::string& s);

// The SetUp the CLI's end-to-end suites share: a scratch folder of their own (removed at exit)
// and, unless `phantom` is false, the tiny volume `phantom.nii` in it that they submit.
class ScratchTest : public ::testing::Test {
 protected:
  // A phantom of nx x ny x nz voxels (none when nx is 0).
  explicit ScratchTest(std::string tag, bool phantom = true, int nx = 12, int ny = 10, int nz = 8)
      : tag_(std::move(tag)), dims_{phantom ? nx : 0, ny, nz} {}
  void SetUp() override {
    scratch_ = testing::MakeScratchDir(tag_);
    volume_ = scratch_ / "phantom.nii";
    if (dims_[0] > 0) WriteTinyNifti(volume_, dims_[0], dims_[1], dims_[2]);
  }
  std::filesystem::path scratch_, volume_;

 private:
  std::string tag_;
  int dims_[3];
};

std::filesystem::path ServerBinary();
std::filesystem::path CliBinary();

}  // namespace decima::e2e
