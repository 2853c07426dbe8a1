#include "tests/e2e/e2e_util.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstring>
#include <fstream>
#include <map>
#include <mutex>
#include <sstream>
#include <thread>

#include <grpcpp/grpcpp.h>
#include "decima/v1/jobs.grpc.pb.h"
#include "gtest/gtest.h"
#include "tests/testing/process.h"

namespace decima::e2e {
namespace fs = std::filesystem;

namespace {

std::string ReadAll(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

using testing::Spawn;

// Waits for a child the test started; a child still running after `timeout` is killed and
// fails the test.
int Reap(pid_t pid, std::chrono::seconds timeout) {
  std::string state;
  const int code = testing::WaitExit(pid, timeout, &state);
  if (code < 0) {
    ADD_FAILURE() << "process " << pid << " timed out after " << timeout.count() << " s (" << state
                  << ")";
  }
  return code;
}

}  // namespace

fs::path ServerBinary() { return DECIMA_SERVER_BIN; }
fs::path CliBinary() { return DECIMA_CLI_BIN; }

ServerProcess::ServerProcess(fs::path data_dir, std::vector<std::string> extra)
    : data_dir_(std::move(data_dir)) {
  fs::create_directories(data_dir_);
  static int counter = 0;
  std::string tag = std::to_string(getpid()) + "-" + std::to_string(++counter);
  fs::path port_file = data_dir_.parent_path() / ("port-" + tag);
  log_ = data_dir_.parent_path() / ("server-" + tag + ".log");
  fs::remove(port_file);
  std::vector<std::string> args = {ServerBinary().string(), "--data-dir", data_dir_.string(),
                                   "--port-file", port_file.string()};
  // A test may pin the address (a restart on the same port); else a free port.
  if (std::find(extra.begin(), extra.end(), "--listen") == extra.end()) {
    args.insert(args.end(), {"--listen", "127.0.0.1:0"});
  }
  args.insert(args.end(), extra.begin(), extra.end());
  pid_ = Spawn(args, log_, log_.string() + ".err", {});
  bool up = WaitFor(
      [&] {
        std::ifstream in(port_file);
        return static_cast<bool>(in >> port_);
      },
      std::chrono::seconds(30));
  if (!up) ADD_FAILURE() << "decima-server did not start: " << Log();
}

ServerProcess::~ServerProcess() {
  if (pid_ > 0) Kill(SIGKILL);
}

void ServerProcess::Kill(int sig) {
  if (pid_ <= 0) return;
  kill(pid_, sig);
  Reap(pid_, std::chrono::seconds(50));
  pid_ = -1;
}

void ServerProcess::Signal(int sig) {
  if (pid_ > 0) kill(pid_, sig);
}

std::string ServerProcess::Log() const { return ReadAll(log_) + ReadAll(log_.string() + ".err"); }

CliResult RunProgram(const std::vector<std::string>& argv, std::chrono::seconds timeout,
                     const std::map<std::string, std::string>& env) {
  static std::atomic<int> counter{0};
  fs::path dir = fs::temp_directory_path() / ("decima-run-" + std::to_string(getpid()));
  fs::create_directories(dir);
  std::string tag = std::to_string(++counter);
  fs::path out = dir / (tag + ".out"), err = dir / (tag + ".err");
  pid_t pid = Spawn(argv, out, err, env);
  CliResult r;
  r.rc = Reap(pid, timeout);
  r.out = ReadAll(out);
  r.err = ReadAll(err);
  fs::remove(out);
  fs::remove(err);
  return r;
}

CliProcess StartCli(const std::string& address, const std::vector<std::string>& args) {
  static std::atomic<int> counter{0};
  fs::path dir = fs::temp_directory_path() / ("decima-clip-" + std::to_string(getpid()));
  fs::create_directories(dir);
  const std::string tag = std::to_string(++counter);
  CliProcess p;
  p.out = dir / (tag + ".out");
  p.err = dir / (tag + ".err");
  std::vector<std::string> a = {CliBinary().string(), "--server", address};
  a.insert(a.end(), args.begin(), args.end());
  p.pid = Spawn(a, p.out, p.err, {});
  return p;
}

CliResult WaitCli(const CliProcess& p, std::chrono::seconds timeout) {
  CliResult r;
  r.rc = Reap(p.pid, timeout);
  r.out = ReadAll(p.out);
  r.err = ReadAll(p.err);
  fs::remove(p.out);
  fs::remove(p.err);
  return r;
}

std::string MakeTestPki(const fs::path& dir, const std::vector<std::string>& clients,
                        TestPki* pki) {
  std::string openssl;
  for (const char* p : {"/usr/bin/openssl", "/bin/openssl", "/usr/local/bin/openssl"}) {
    if (access(p, X_OK) == 0) {
      openssl = p;
      break;
    }
  }
  if (openssl.empty()) return "openssl not found";
  fs::create_directories(dir);
  pki->dir = dir;
  auto run = [&](std::vector<std::string> args) -> std::string {
    args.insert(args.begin(), openssl);
    CliResult r = RunProgram(args, std::chrono::seconds(60));
    if (r.rc == 0) return "";
    std::string cmd;
    for (const auto& a : args) cmd += a + " ";
    return cmd + "-> exit " + std::to_string(r.rc) + ": " + r.err;
  };
  const auto p = [&](const std::string& f) { return (dir / f).string(); };
  // P-256 keys: generated in milliseconds, unlike RSA.
  const std::vector<std::string> kNewKey = {"-newkey", "ec", "-pkeyopt",
                                            "ec_paramgen_curve:prime256v1", "-nodes"};
  auto self_signed = [&](const std::string& name, const std::string& cn) {
    std::vector<std::string> a = {"req", "-x509"};
    a.insert(a.end(), kNewKey.begin(), kNewKey.end());
    a.insert(a.end(), {"-keyout", p(name + ".key"), "-out", p(name + ".pem"), "-days", "2", "-subj",
                       "/CN=" + cn});
    return run(a);
  };
  auto signed_by = [&](const std::string& ca, const std::string& name, const std::string& cn,
                       const std::string& ext) {
    std::vector<std::string> a = {"req"};
    a.insert(a.end(), kNewKey.begin(), kNewKey.end());
    a.insert(a.end(),
             {"-keyout", p(name + ".key"), "-out", p(name + ".csr"), "-subj", "/CN=" + cn});
    if (auto e = run(a); !e.empty()) return e;
    std::ofstream(p(name + ".ext")) << ext << "\n";
    return run({"x509", "-req", "-in", p(name + ".csr"), "-CA", p(ca + ".pem"), "-CAkey",
                p(ca + ".key"), "-CAcreateserial", "-out", p(name + ".pem"), "-days", "2",
                "-extfile", p(name + ".ext")});
  };
  if (auto e = self_signed("ca", "decima-test-ca"); !e.empty()) return e;
  if (auto e = self_signed("other-ca", "some-other-ca"); !e.empty()) return e;
  if (auto e = signed_by("ca", "server", "localhost",
                         "subjectAltName=IP:127.0.0.1,DNS:localhost\nextendedKeyUsage=serverAuth");
      !e.empty()) {
    return e;
  }
  for (const auto& c : clients) {
    if (auto e = signed_by("ca", c, c, "extendedKeyUsage=clientAuth"); !e.empty()) return e;
  }
  if (auto e = signed_by("other-ca", "stranger", "stranger", "extendedKeyUsage=clientAuth");
      !e.empty()) {
    return e;
  }
  // An expired server certificate for server.key: `openssl ca` is the command that takes
  // explicit start and end dates.
  std::ofstream(p("ca.cnf")) << "[ca]\ndefault_ca=d\n[d]\ndatabase=" << p("index.txt")
                             << "\nnew_certs_dir=" << dir.string() << "\nserial=" << p("serial")
                             << "\ndefault_md=sha256\npolicy=p\n[p]\ncommonName=supplied\n";
  std::ofstream(p("index.txt")).flush();
  std::ofstream(p("serial")) << "1000\n";
  return run({"ca", "-batch", "-config", p("ca.cnf"), "-cert", p("ca.pem"), "-keyfile", p("ca.key"),
              "-in", p("server.csr"), "-out", p("expired.pem"), "-startdate", "20200101000000Z",
              "-enddate", "20200102000000Z", "-notext"});
}

CliResult RunCli(const std::string& address, const std::vector<std::string>& args,
                 std::chrono::seconds timeout, const std::map<std::string, std::string>& env) {
  std::vector<std::string> a = {CliBinary().string(), "--server", address};
  a.insert(a.end(), args.begin(), args.end());
  return RunProgram(a, timeout, env);
}

std::shared_ptr<grpc::Channel> SharedChannel(const std::string& address) {
  static std::mutex mu;
  static std::map<std::string, std::shared_ptr<grpc::Channel>> channels;
  std::lock_guard<std::mutex> lock(mu);
  auto& channel = channels[address];
  if (!channel) channel = grpc::CreateChannel(address, grpc::InsecureChannelCredentials());
  return channel;
}

v1::Job GetJob(const std::string& address, const std::string& name) {
  auto stub = v1::Jobs::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  v1::GetJobRequest req;
  req.set_name(name);
  v1::Job job;
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  grpc::Status s = stub->GetJob(&ctx, req, &job);
  EXPECT_TRUE(s.ok()) << name << ": " << s.error_message();
  return job;
}

std::vector<v1::JobEvent> WatchAll(const std::string& address, const std::string& name,
                                   int64_t after, int stop_after, grpc::Status* status,
                                   std::chrono::seconds deadline, std::atomic<int>* first_event) {
  auto stub = v1::Jobs::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + deadline);
  v1::WatchJobRequest req;
  req.set_name(name);
  req.set_after_sequence(after);
  auto reader = stub->WatchJob(&ctx, req);
  std::vector<v1::JobEvent> events;
  v1::JobEvent ev;
  while (reader->Read(&ev)) {
    if (events.empty() && first_event != nullptr) ++*first_event;
    events.push_back(ev);
    if (stop_after >= 0 && ev.has_progress() && --stop_after == 0) {
      ctx.TryCancel();
      break;
    }
  }
  grpc::Status s = reader->Finish();
  if (status != nullptr) *status = s;
  return events;
}

std::vector<int64_t> Sequences(const std::vector<v1::JobEvent>& events) {
  std::vector<int64_t> seqs;
  for (const auto& e : events) {
    if (!e.has_snapshot() && !e.has_heartbeat()) seqs.push_back(e.sequence());
  }
  return seqs;
}

std::string NiftiHeader(int nx, int ny, int nz, int16_t datatype, int16_t bitpix, float mm) {
  std::string hdr(352, '\0');
  auto put32 = [&](int off, int32_t v) { std::memcpy(&hdr[off], &v, 4); };
  auto put16 = [&](int off, int16_t v) { std::memcpy(&hdr[off], &v, 2); };
  auto putf = [&](int off, float v) { std::memcpy(&hdr[off], &v, 4); };
  put32(0, 348);
  put16(40, 3);
  put16(42, static_cast<int16_t>(nx));
  put16(44, static_cast<int16_t>(ny));
  put16(46, static_cast<int16_t>(nz));
  put16(48, 1);
  put16(50, 1);
  put16(52, 1);
  put16(54, 1);
  put16(70, datatype);
  put16(72, bitpix);
  putf(76, 1);  // qfac
  putf(80, mm);
  putf(84, mm);
  putf(88, mm);
  putf(108, 352);  // vox_offset
  putf(112, 1);    // scl_slope
  hdr[123] = 10;   // xyzt_units: mm, s
  put16(252, 1);   // qform_code scanner
  putf(256, 0);    // quatern b c d = identity
  std::memcpy(&hdr[344], "n+1", 4);
  return hdr;
}

void WriteTinyNifti(const fs::path& path, int nx, int ny, int nz, int seed) {
  const std::string hdr = NiftiHeader(nx, ny, nz, /*int16*/ 4, 16, 2.0f);
  std::vector<int16_t> v(static_cast<size_t>(nx) * ny * nz);
  double cx = nx / 2.0, cy = ny / 2.0, cz = nz / 2.0, r = std::min({nx, ny, nz}) / 3.0;
  for (int z = 0; z < nz; ++z) {
    for (int y = 0; y < ny; ++y) {
      for (int x = 0; x < nx; ++x) {
        double d2 = (x - cx) * (x - cx) + (y - cy) * (y - cy) + (z - cz) * (z - cz);
        v[(static_cast<size_t>(z) * ny + y) * nx + x] = d2 < r * r ? 1000 : 100;
      }
    }
  }
  v[0] = static_cast<int16_t>(seed);
  std::ofstream out(path, std::ios::binary);
  out.write(hdr.data(), static_cast<std::streamsize>(hdr.size()));
  out.write(reinterpret_cast<const char*>(v.data()), static_cast<std::streamsize>(v.size() * 2));
}

std::string FirstLine(const std::string& s) { return s.substr(0, s.find('\n')); }

}  // namespace decima::e2e
