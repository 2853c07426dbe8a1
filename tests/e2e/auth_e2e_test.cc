// End-to-end security (issue 16): TLS and mutual TLS with a throwaway PKI made by `openssl`,
// identities from a tokens file, ownership of jobs and volumes (every RPC x every role), and the
// audit log of a scripted session. Real decima-server and decima processes on loopback.
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

#include "decima/v1/artifacts.grpc.pb.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "gmock/gmock.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "gtest/gtest.h"
#include "server/util/sha256.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/postgres_server.h"
#include "tests/testing/process.h"
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

std::string Sha256Hex(const std::string& s) {
  server::Sha256 h;
  h.Update(s.data(), s.size());
  return h.HexDigest();
}

class AuthE2E : public ScratchTest {
 protected:
  AuthE2E() : ScratchTest("auth_e2e") {}
  // Skips the test when openssl is absent.
  bool MakePki() {
    std::string err = MakeTestPki(scratch_ / "pki", {"alice", "rita"}, &pki_);
    if (err == "openssl not found") return false;
    EXPECT_EQ(err, "");
    return err.empty();
  }
  std::shared_ptr<grpc::Channel> TlsChannel(const std::string& address,
                                            const std::string& client = "") {
    grpc::SslCredentialsOptions o;
    o.pem_root_certs = ReadFile(pki_.ca());
    if (!client.empty()) {
      o.pem_cert_chain = ReadFile(pki_.cert(client));
      o.pem_private_key = ReadFile(pki_.key(client));
    }
    return grpc::CreateChannel(address, grpc::SslCredentials(o));
  }
  TestPki pki_;
};

TEST_F(AuthE2E, JobOverTlsAndOverMutualTlsAndClientsWithoutAGoodCertificateAreRefused) {
  if (!MakePki()) GTEST_SKIP() << "openssl not installed";
  const std::vector<std::string> tls = {"--ca-cert", pki_.ca().string()};
  {
    ServerProcess server(scratch_ / "data-tls", {"--tls-cert", pki_.server_cert().string(),
                                                 "--tls-key", pki_.server_key().string()});
    // The CT head when the shared data is there, the phantom otherwise.
    fs::path input = volume_;
    if (auto ct = testing::SharedDataFile("ct-head-128x128x53.nii.gz")) input = *ct;
    std::vector<std::string> args = tls;
    args.insert(args.end(), {"submit", input.string(), "--out", (scratch_ / "out-tls").string(),
                             "--image-size", "64"});
    CliResult r = RunCli(server.address(), args, 600s);
    ASSERT_EQ(r.rc, 0) << r.err << server.Log();
    EXPECT_THAT(r.err, HasSubstr("SUCCEEDED"));
    EXPECT_TRUE(fs::exists(scratch_ / "out-tls" / "mesh.vtu"));
    // Plaintext against a TLS port does not get through.
    r = RunCli(server.address(), {"--timeout", "3", "list"});
    EXPECT_EQ(r.rc, 8) << r.out << r.err;
  }
  ServerProcess server(scratch_ / "data-mtls",
                       {"--tls-cert", pki_.server_cert().string(), "--tls-key",
                        pki_.server_key().string(), "--tls-client-ca", pki_.ca().string()});
  std::vector<std::string> alice = tls;
  alice.insert(alice.end(), {"--tls-cert", pki_.cert("alice").string(), "--tls-key",
                             pki_.key("alice").string()});
  std::vector<std::string> args = alice;
  args.insert(args.end(), {"submit", volume_.string(), "--out", (scratch_ / "out-mtls").string(),
                           "--image-size", "32"});
  CliResult r = RunCli(server.address(), args, 300s);
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  EXPECT_TRUE(fs::exists(scratch_ / "out-mtls" / "mesh.vtu"));
  const std::string job = FirstLine(r.out);
  // The job belongs to the certificate's CN.
  args = alice;
  args.insert(args.end(), {"--json", "status", job});
  r = RunCli(server.address(), args);
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("\"creator\":\"alice\""));

  // No client certificate: the handshake is refused; exit 8 with the hint what to check.
  args = tls;
  args.insert(args.end(), {"--timeout", "3", "list"});
  r = RunCli(server.address(), args);
  EXPECT_EQ(r.rc, 8) << r.out << r.err;
  EXPECT_THAT(r.err, HasSubstr("--tls-cert"));
  // A certificate from another CA: refused too.
  args = tls;
  args.insert(args.end(), {"--timeout", "3", "--tls-cert", pki_.stranger_cert().string(),
                           "--tls-key", pki_.stranger_key().string(), "list"});
  r = RunCli(server.address(), args);
  EXPECT_EQ(r.rc, 8) << r.out << r.err;
  // Another client (rita, a submitter by default) does not see alice's job: exit code 7.
  args = tls;
  args.insert(args.end(), {"--tls-cert", pki_.cert("rita").string(), "--tls-key",
                           pki_.key("rita").string(), "status", job});
  r = RunCli(server.address(), args);
  EXPECT_EQ(r.rc, 7) << r.out << r.err;
  EXPECT_THAT(r.err, HasSubstr("PERMISSION_DENIED"));
  // Under mutual TLS the handshake itself needs a certificate; health then needs nothing more.
  args = alice;
  args.push_back("health");
  r = RunCli(server.address(), args);
  EXPECT_EQ(r.rc, 0) << r.err;
}

TEST_F(AuthE2E, WrongOrExpiredCertificatesAndBadTokensFilesStopTheServerWithTheReason) {
  if (!MakePki()) GTEST_SKIP() << "openssl not installed";
  fs::path garbage = scratch_ / "garbage.pem";
  std::ofstream(garbage) << "not a certificate\n";
  fs::path tokens = scratch_ / "tokens";
  std::ofstream(tokens) << "token " << Sha256Hex("t") << " alice superuser\n";
  struct Case {
    std::vector<std::string> flags;
    std::string expect;
  };
  const std::vector<Case> cases = {
      {{"--tls-cert", pki_.expired_cert().string(), "--tls-key", pki_.server_key().string()},
       "has expired"},
      {{"--tls-cert", pki_.server_cert().string(), "--tls-key", pki_.key("alice").string()},
       "does not belong to the certificate"},
      {{"--tls-cert", garbage.string(), "--tls-key", pki_.server_key().string()},
       "not a PEM certificate"},
      {{"--tls-cert", pki_.server_cert().string(), "--tls-key", pki_.server_key().string(),
        "--tls-client-ca", garbage.string()},
       "--tls-client-ca"},
      {{"--tokens-file", tokens.string()}, "line 1: role 'superuser'"},
  };
  int n = 0;
  for (const auto& c : cases) {
    std::vector<std::string> argv = {ServerBinary().string(), "--listen", "127.0.0.1:0",
                                     "--data-dir",
                                     (scratch_ / ("data" + std::to_string(n++))).string()};
    argv.insert(argv.end(), c.flags.begin(), c.flags.end());
    CliResult r = RunProgram(argv, 30s);
    EXPECT_EQ(r.rc, 1) << c.expect << ": " << r.err;
    // spdlog writes to stdout.
    EXPECT_THAT(r.out + r.err, HasSubstr(c.expect));
  }
}

TEST_F(AuthE2E, RenewedCertificateFilesServeNewConnectionsWithoutDroppingAnOpenStream) {
  if (!MakePki()) GTEST_SKIP() << "openssl not installed";
  // The server reads copies, so the test can replace them.
  fs::path cert = scratch_ / "live.pem", key = scratch_ / "live.key";
  fs::copy_file(pki_.server_cert(), cert);
  fs::copy_file(pki_.server_key(), key);
  ServerProcess server(scratch_ / "data", {"--tls-cert", cert.string(), "--tls-key", key.string(),
                                           "--tls-reload-seconds", "1", "--allow-faults"});
  auto channel = TlsChannel(server.address());
  auto jobs = v1::Jobs::NewStub(channel);
  // A job that runs for a few seconds, watched over the first connection.
  CliResult r =
      RunCli(server.address(), {"--ca-cert", pki_.ca().string(), "submit", volume_.string(),
                                "--fault", "sleep:4", "--image-size", "32"});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  const std::string job = FirstLine(r.out);
  grpc::ClientContext watch_ctx;
  watch_ctx.set_deadline(std::chrono::system_clock::now() + 120s);
  v1::WatchJobRequest wr;
  wr.set_name(job);
  auto reader = jobs->WatchJob(&watch_ctx, wr);
  v1::JobEvent ev;
  ASSERT_TRUE(reader->Read(&ev));

  // Renew: a certificate from another CA for the same key, swapped in atomically.
  fs::path renewed = scratch_ / "renewed.pem";
  CliResult s =
      RunProgram({"/usr/bin/openssl", "x509", "-req", "-in", (pki_.dir / "server.csr").string(),
                  "-CA", (pki_.dir / "other-ca.pem").string(), "-CAkey",
                  (pki_.dir / "other-ca.key").string(), "-CAcreateserial", "-out", renewed.string(),
                  "-days", "2", "-extfile", (pki_.dir / "server.ext").string()});
  ASSERT_EQ(s.rc, 0) << s.err;
  fs::rename(renewed, cert);
  // New connections trust the new CA within a few reload periods.
  bool renewed_served = WaitFor(
      [&] {
        CliResult h = RunCli(server.address(), {"--ca-cert", (pki_.dir / "other-ca.pem").string(),
                                                "--timeout", "2", "health"});
        return h.rc == 0;
      },
      30s);
  EXPECT_TRUE(renewed_served) << server.Log();
  // The stream opened before the swap runs to the job's end.
  v1::JobState last = v1::JOB_STATE_UNSPECIFIED;
  while (reader->Read(&ev)) {
    if (ev.has_state_change()) last = ev.state_change().state();
  }
  grpc::Status st = reader->Finish();
  EXPECT_TRUE(st.ok()) << st.error_message();
  EXPECT_EQ(last, v1::SUCCEEDED);
}

// Issue 35 part 4: an empty key or certificate renamed into place aborted the server within one
// reload period (an assertion in gRPC), and a broken non-empty pair made every new handshake
// fail. Now the server checks each changed set before gRPC sees it: while a client keeps
// opening new connections, an empty key, an empty certificate, a file that is no PEM and a
// certificate of another key are each renamed into place for three reload periods; the server
// stays up, every handshake succeeds with the last good pair, and a good renewal is still
// taken afterwards.
TEST_F(AuthE2E, BrokenOrEmptyTlsFilesRenamedIntoPlaceKeepTheLastGoodPairServing) {
  if (!MakePki()) GTEST_SKIP() << "openssl not installed";
  fs::path cert = scratch_ / "live.pem", key = scratch_ / "live.key";
  fs::copy_file(pki_.server_cert(), cert);
  fs::copy_file(pki_.server_key(), key);
  ServerProcess server(scratch_ / "data", {"--tls-cert", cert.string(), "--tls-key", key.string(),
                                           "--tls-reload-seconds", "1"});
  const std::string ca = ReadFile(pki_.ca());
  std::atomic<bool> stop{false};
  std::atomic<int> ok{0}, failed{0};
  // New connections all the time: a channel of its own subchannel pool each.
  std::thread client([&] {
    for (int i = 0; i < 100000 && !stop; ++i) {
      grpc::SslCredentialsOptions o;
      o.pem_root_certs = ca;
      grpc::ChannelArguments args;
      args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
      auto ch = grpc::CreateCustomChannel(server.address(), grpc::SslCredentials(o), args);
      if (ch->WaitForConnected(std::chrono::system_clock::now() + 5s)) {
        ++ok;
      } else {
        ++failed;
      }
      std::this_thread::sleep_for(50ms);
    }
  });
  auto swap_in = [&](const fs::path& target, const std::string& content) {
    fs::path tmp = target.string() + ".new";
    std::ofstream(tmp, std::ios::binary) << content;
    fs::rename(tmp, target);
    std::this_thread::sleep_for(3500ms);  // three reload periods and a half
  };
  const std::string good_cert = ReadFile(cert), good_key = ReadFile(key);
  swap_in(key, "");
  swap_in(key, good_key);
  swap_in(cert, "");
  swap_in(cert, "-----BEGIN CERTIFICATE-----\nnot base64 at all\n-----END CERTIFICATE-----\n");
  swap_in(cert, ReadFile(pki_.stranger_cert()));  // a good certificate of another key
  EXPECT_EQ(kill(server.pid(), 0), 0) << "the server died\n" << server.Log();
  // A good renewal (another CA, same key) is still taken.
  CliResult s = RunProgram(
      {"/usr/bin/openssl", "x509", "-req", "-in", (pki_.dir / "server.csr").string(), "-CA",
       (pki_.dir / "other-ca.pem").string(), "-CAkey", (pki_.dir / "other-ca.key").string(),
       "-CAcreateserial", "-out", (scratch_ / "renewed.pem").string(), "-days", "2", "-extfile",
       (pki_.dir / "server.ext").string()});
  ASSERT_EQ(s.rc, 0) << s.err;
  stop = true;
  client.join();
  fs::rename(scratch_ / "renewed.pem", cert);
  bool renewed_served = WaitFor(
      [&] {
        CliResult h = RunCli(server.address(), {"--ca-cert", (pki_.dir / "other-ca.pem").string(),
                                                "--timeout", "2", "health"});
        return h.rc == 0;
      },
      30s);
  EXPECT_TRUE(renewed_served) << server.Log();
  EXPECT_GT(ok.load(), 50);
  EXPECT_EQ(failed.load(), 0) << server.Log();
  const std::string log = server.Log();
  EXPECT_THAT(log, HasSubstr("TLS reload refused"));
  EXPECT_THAT(log, HasSubstr("does not belong to the certificate"));
  std::printf("handshakes during the broken swaps: %d ok, %d failed\n", ok.load(), failed.load());
}

// Issue 35 part 7: a plaintext client against a TLS server was told "is the server running
// there?" with no hint of TLS. Now, when something accepts TCP at the address, the hint says
// the server may serve TLS and names --tls / --ca-cert; a closed port keeps the old hint.
TEST_F(AuthE2E, APlaintextClientAgainstATlsServerIsToldAboutTls) {
  if (!MakePki()) GTEST_SKIP() << "openssl not installed";
  ServerProcess server(scratch_ / "data", {"--tls-cert", pki_.server_cert().string(), "--tls-key",
                                           pki_.server_key().string()});
  CliResult r = RunCli(server.address(), {"--timeout", "3", "list"});
  EXPECT_EQ(r.rc, 8) << r.err;
  EXPECT_THAT(r.err, HasSubstr("may serve TLS"));
  EXPECT_THAT(r.err, HasSubstr("--ca-cert"));
  EXPECT_THAT(r.err, ::testing::Not(HasSubstr("is the server running")));
  CliResult ok = RunCli(server.address(), {"--ca-cert", pki_.ca().string(), "list"});
  EXPECT_EQ(ok.rc, 0) << ok.err;
  // Nothing listens on a fresh free port: the old hint.
  const std::string closed = "127.0.0.1:" + std::to_string(testing::FreePort());
  CliResult none = RunCli(closed, {"--timeout", "3", "list"});
  EXPECT_EQ(none.rc, 8) << none.err;
  EXPECT_THAT(none.err, HasSubstr("is the server running"));
  EXPECT_THAT(none.err, ::testing::Not(HasSubstr("may serve TLS")));
}

// --- Who may do what -------------------------------------------------------------------------

struct Caller {
  std::string label;  // column of the table
  std::string token;  // "" = no credentials
};

class OwnershipE2E : public AuthE2E {
 protected:
  void SetUp() override {
    AuthE2E::SetUp();
    fs::path tokens = scratch_ / "tokens";
    std::ofstream(tokens) << "# principals of the test\n"
                          << "token " << Sha256Hex("alice-token") << " alice submitter\n"
                          << "token " << Sha256Hex("bob-token") << " bob submitter\n"
                          << "token " << Sha256Hex("rita-token") << " rita reader\n"
                          << "token " << Sha256Hex("root-token") << " root admin\n";
    audit_ = scratch_ / "audit" / "audit.log";
    fs::create_directories(audit_.parent_path());
    server_ = std::make_unique<ServerProcess>(
        scratch_ / "data",
        std::vector<std::string>{"--tokens-file", tokens.string(), "--audit-log", audit_.string()});
    auto ch = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
    uploads_ = v1::Uploads::NewStub(ch);
    volumes_ = v1::Volumes::NewStub(ch);
    jobs_ = v1::Jobs::NewStub(ch);
    artifacts_ = v1::Artifacts::NewStub(ch);
    health_ = ch;
  }
  std::unique_ptr<grpc::ClientContext> Ctx(const std::string& token) {
    auto ctx = std::make_unique<grpc::ClientContext>();
    ctx->set_deadline(std::chrono::system_clock::now() + 30s);
    if (!token.empty()) ctx->AddMetadata("authorization", "Bearer " + token);
    return ctx;
  }
  grpc::StatusCode Upload(const std::string& token, const std::string& bytes,
                          std::string* sha = nullptr) {
    v1::UploadRequest req;
    req.set_sha256(Sha256Hex(bytes));
    req.set_size_bytes(static_cast<int64_t>(bytes.size()));
    req.set_data(bytes);
    if (sha) *sha = req.sha256();
    v1::Blob blob;
    auto ctx = Ctx(token);
    auto w = uploads_->Upload(ctx.get(), &blob);
    w->Write(req);
    w->WritesDone();
    return w->Finish().error_code();
  }
  // `path` names the file: the same principal's create of the same name and bytes answers its
  // volume of them, so a volume a case deletes needs a name of its own.
  grpc::StatusCode CreateVolume(const std::string& token, const std::string& sha,
                                std::string* name = nullptr,
                                const std::string& path = "phantom.nii") {
    v1::CreateVolumeRequest req;
    auto* f = req.mutable_volume()->add_files();
    f->set_path(path);
    f->set_blob("blobs/" + sha);
    v1::Volume v;
    auto s = volumes_->CreateVolume(Ctx(token).get(), req, &v);
    if (name) *name = v.name();
    return s.error_code();
  }
  grpc::StatusCode CreateJob(const std::string& token, const std::string& volume,
                             std::string* name = nullptr) {
    v1::CreateJobRequest req;
    req.mutable_spec()->set_volume(volume);
    req.mutable_spec()->set_image_size(32);
    v1::Job j;
    auto s = jobs_->CreateJob(Ctx(token).get(), req, &j);
    if (name) *name = j.name();
    return s.error_code();
  }
  v1::Job WaitFinal(const std::string& name) {
    v1::Job j;
    WaitFor(
        [&] {
          v1::GetJobRequest g;
          g.set_name(name);
          jobs_->GetJob(Ctx("root-token").get(), g, &j);
          return j.state() == v1::SUCCEEDED || j.state() == v1::FAILED ||
                 j.state() == v1::CANCELLED;
        },
        120s);
    return j;
  }
  // A final (cancelled or finished) job of alice's, for one DeleteJob.
  std::string FinalJobOfAlice() {
    std::string name;
    EXPECT_EQ(CreateJob("alice-token", volume_name_, &name), grpc::StatusCode::OK);
    v1::CancelJobRequest c;
    c.set_name(name);
    v1::Job j;
    jobs_->CancelJob(Ctx("alice-token").get(), c, &j);
    WaitFinal(name);
    return name;
  }

  fs::path audit_;
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<v1::Uploads::Stub> uploads_;
  std::unique_ptr<v1::Volumes::Stub> volumes_;
  std::unique_ptr<v1::Jobs::Stub> jobs_;
  std::unique_ptr<v1::Artifacts::Stub> artifacts_;
  std::shared_ptr<grpc::Channel> health_;
  std::string phantom_sha_, volume_name_;
};

TEST_F(OwnershipE2E, EveryRpcByEveryRoleGetsTheExpectedCode) {
  using C = grpc::StatusCode;
  const std::string phantom = ReadFile(volume_);
  // alice (a submitter) owns a volume and a succeeded job.
  ASSERT_EQ(Upload("alice-token", phantom, &phantom_sha_), C::OK);
  ASSERT_EQ(CreateVolume("alice-token", phantom_sha_, &volume_name_), C::OK);
  std::string job;
  ASSERT_EQ(CreateJob("alice-token", volume_name_, &job), C::OK);
  v1::Job done = WaitFinal(job);
  ASSERT_EQ(done.state(), v1::SUCCEEDED) << server_->Log();
  ASSERT_EQ(done.creator(), "alice");
  ASSERT_GT(done.artifacts_size(), 0);
  const std::string artifact = done.artifacts(0).name();

  // Columns: the owner, another submitter, a reader, an admin, no credentials.
  const std::vector<Caller> callers = {{"owner alice", "alice-token"},
                                       {"submitter bob", "bob-token"},
                                       {"reader rita", "rita-token"},
                                       {"admin root", "root-token"},
                                       {"anonymous", ""}};
  constexpr C OK = C::OK, PD = C::PERMISSION_DENIED, UA = C::UNAUTHENTICATED,
              FP = C::FAILED_PRECONDITION, NF = C::NOT_FOUND;
  struct Row {
    const char* rpc;
    std::vector<C> expected;  // one per caller
    std::function<C(const std::string& token)> call;
  };
  int uploads = 0;
  const std::vector<Row> table = {
      {"Uploads.Upload",
       {OK, OK, PD, OK, UA},
       [&](const std::string& t) { return Upload(t, "bytes " + std::to_string(++uploads)); }},
      {"Uploads.GetUploadStatus",
       {OK, OK, OK, OK, UA},
       [&](const std::string& t) {
         v1::GetUploadStatusRequest r;
         r.set_sha256(phantom_sha_);
         r.set_size_bytes(static_cast<int64_t>(phantom.size()));
         v1::UploadStatus s;
         return uploads_->GetUploadStatus(Ctx(t).get(), r, &s).error_code();
       }},
      {"Volumes.CreateVolume",
       {OK, OK, PD, OK, UA},
       [&](const std::string& t) { return CreateVolume(t, phantom_sha_); }},
      {"Volumes.GetVolume",
       {OK, PD, OK, OK, UA},
       [&](const std::string& t) {
         v1::GetVolumeRequest r;
         r.set_name(volume_name_);
         v1::Volume v;
         return volumes_->GetVolume(Ctx(t).get(), r, &v).error_code();
       }},
      {"Volumes.ListVolumes",
       {OK, OK, OK, OK, UA},
       [&](const std::string& t) {
         v1::ListVolumesResponse resp;
         auto s = volumes_->ListVolumes(Ctx(t).get(), {}, &resp);
         // A submitter lists only its own volumes; reader and admin see alice's too.
         bool sees_alices = false;
         for (const auto& v : resp.volumes()) {
           if (v.name() == volume_name_) sees_alices = true;
           if (t == "bob-token") {
             EXPECT_EQ(v.creator(), "bob");
           }
         }
         if (s.ok()) {
           EXPECT_EQ(sees_alices, t != "bob-token") << t;
         }
         return s.error_code();
       }},
      {"Volumes.ListReceivedSeries",
       {OK, OK, OK, OK, UA},
       [&](const std::string& t) {
         v1::ListReceivedSeriesResponse resp;
         auto s = volumes_->ListReceivedSeries(Ctx(t).get(), {}, &resp);
         if (s.ok()) {
           EXPECT_EQ(resp.received_series_size(), 0);  // no DICOM receiver in this server
         }
         return s.error_code();
       }},
      {"Volumes.DeleteReceivedSeries (nothing waits)",
       {NF, NF, PD, NF, UA},
       [&](const std::string& t) {
         v1::DeleteReceivedSeriesRequest r;
         r.set_series_instance_uid("1.2.3");
         v1::DeleteReceivedSeriesResponse resp;
         return volumes_->DeleteReceivedSeries(Ctx(t).get(), r, &resp).error_code();
       }},
      {"Volumes.DeleteVolume",
       {OK, PD, PD, OK, UA},
       [&](const std::string& t) {
         std::string victim;
         EXPECT_EQ(CreateVolume("alice-token", phantom_sha_, &victim, "victim.nii"), OK);
         v1::DeleteVolumeRequest r;
         r.set_name(victim);
         v1::DeleteVolumeResponse resp;
         return volumes_->DeleteVolume(Ctx(t).get(), r, &resp).error_code();
       }},
      {"Jobs.CreateJob (on alice's volume)",
       {OK, PD, PD, OK, UA},
       [&](const std::string& t) {
         std::string name;
         C c = CreateJob(t, volume_name_, &name);
         if (c == OK) WaitFinal(name);
         return c;
       }},
      {"Jobs.CheckJobMemory (a role that may submit may ask)",
       {OK, OK, PD, OK, UA},
       [&](const std::string& t) {
         v1::CheckJobMemoryRequest r;
         r.set_display_name("phantom.nii");
         for (int64_t d : {24, 24, 16}) r.add_dims(d);
         r.set_size_bytes(static_cast<int64_t>(phantom.size()));
         v1::CheckJobMemoryResponse resp;
         auto s = jobs_->CheckJobMemory(Ctx(t).get(), r, &resp);
         if (s.ok()) {
           EXPECT_TRUE(resp.fits());
         }
         return s.error_code();
       }},
      {"Jobs.GetJob",
       {OK, PD, OK, OK, UA},
       [&](const std::string& t) {
         v1::GetJobRequest r;
         r.set_name(job);
         v1::Job j;
         return jobs_->GetJob(Ctx(t).get(), r, &j).error_code();
       }},
      {"Jobs.ListJobs",
       {OK, OK, OK, OK, UA},
       [&](const std::string& t) {
         v1::ListJobsResponse resp;
         auto s = jobs_->ListJobs(Ctx(t).get(), {}, &resp);
         bool sees_alices = false;
         for (const auto& j : resp.jobs()) sees_alices |= j.name() == job;
         if (s.ok()) {
           EXPECT_EQ(sees_alices, t != "bob-token") << t;
         }
         return s.error_code();
       }},
      {"Jobs.CancelJob (a succeeded job: unchanged)",
       {OK, PD, PD, OK, UA},
       [&](const std::string& t) {
         v1::CancelJobRequest r;
         r.set_name(job);
         v1::Job j;
         return jobs_->CancelJob(Ctx(t).get(), r, &j).error_code();
       }},
      {"Jobs.RetryJob (a succeeded job)",
       {FP, PD, PD, FP, UA},
       [&](const std::string& t) {
         v1::RetryJobRequest r;
         r.set_name(job);
         v1::Job j;
         return jobs_->RetryJob(Ctx(t).get(), r, &j).error_code();
       }},
      {"Jobs.DeleteJob",
       {OK, PD, PD, OK, UA},
       [&](const std::string& t) {
         v1::DeleteJobRequest r;
         r.set_name(FinalJobOfAlice());
         v1::DeleteJobResponse resp;
         return jobs_->DeleteJob(Ctx(t).get(), r, &resp).error_code();
       }},
      {"Jobs.WatchJob",
       {OK, PD, OK, OK, UA},
       [&](const std::string& t) {
         v1::WatchJobRequest r;
         r.set_name(job);
         auto ctx = Ctx(t);
         auto reader = jobs_->WatchJob(ctx.get(), r);
         v1::JobEvent ev;
         int n = 0;
         while (reader->Read(&ev)) ++n;
         C c = reader->Finish().error_code();
         if (c == OK) {
           EXPECT_GT(n, 0);
         }
         return c;
       }},
      {"Artifacts.ReadArtifact",
       {OK, PD, OK, OK, UA},
       [&](const std::string& t) {
         v1::ReadArtifactRequest r;
         r.set_name(artifact);
         auto ctx = Ctx(t);
         auto reader = artifacts_->ReadArtifact(ctx.get(), r);
         v1::ReadArtifactResponse chunk;
         int64_t bytes = 0;
         while (reader->Read(&chunk)) bytes += static_cast<int64_t>(chunk.data().size());
         C c = reader->Finish().error_code();
         if (c == OK) {
           EXPECT_EQ(bytes, done.artifacts(0).size_bytes());
         }
         return c;
       }},
      {"ServerReflection.ServerReflectionInfo (list_services)",
       {OK, OK, OK, OK, UA},
       [&](const std::string& t) {
         namespace rv = ::grpc::reflection::v1alpha;
         auto stub = rv::ServerReflection::NewStub(health_);
         auto ctx = Ctx(t);
         auto stream = stub->ServerReflectionInfo(ctx.get());
         rv::ServerReflectionRequest req;
         req.set_list_services("");
         rv::ServerReflectionResponse resp;
         const bool answered = stream->Write(req) && stream->Read(&resp);
         stream->WritesDone();
         C c = stream->Finish().error_code();
         if (c == OK) {
           EXPECT_TRUE(answered);
           EXPECT_GE(resp.list_services_response().service_size(), 4);
         }
         return c;
       }},
  };
  int checked = 0;
  for (const auto& row : table) {
    for (size_t i = 0; i < callers.size(); ++i) {
      C got = row.call(callers[i].token);
      EXPECT_EQ(got, row.expected[i]) << row.rpc << " by " << callers[i].label;
      ++checked;
    }
  }
  EXPECT_EQ(checked, 18 * 5);
  // Health stays open without credentials.
  CliResult h = RunCli(server_->address(), {"health"});
  EXPECT_EQ(h.rc, 0) << h.err;
  // The CLI's exit code for PERMISSION_DENIED is 7, with the reason.
  CliResult r = RunCli(server_->address(), {"--token", "bob-token", "status", job});
  EXPECT_EQ(r.rc, 7) << r.out << r.err;
  EXPECT_THAT(r.err, HasSubstr("PERMISSION_DENIED"));
  EXPECT_THAT(r.err, HasSubstr("bob (submitter)"));
  // No token ever reaches the audit log.
  const std::string audit = ReadFile(audit_);
  for (const char* t : {"alice-token", "bob-token", "rita-token", "root-token"}) {
    EXPECT_EQ(audit.find(t), std::string::npos) << t;
  }
}

TEST_F(OwnershipE2E, AuditLogHoldsExactlyOneLinePerStateChangingCallOfAScriptedSession) {
  using C = grpc::StatusCode;
  const std::string phantom = ReadFile(volume_);
  ASSERT_EQ(Upload("alice-token", phantom, &phantom_sha_), C::OK);
  ASSERT_EQ(CreateVolume("alice-token", phantom_sha_, &volume_name_), C::OK);
  std::string job;
  ASSERT_EQ(CreateJob("alice-token", volume_name_, &job), C::OK);
  // Reads are not audited.
  v1::GetJobRequest g;
  g.set_name(job);
  v1::Job j;
  ASSERT_TRUE(jobs_->GetJob(Ctx("rita-token").get(), g, &j).ok());
  v1::CancelJobRequest c;
  c.set_name(job);
  EXPECT_EQ(jobs_->CancelJob(Ctx("bob-token").get(), c, &j).error_code(), C::PERMISSION_DENIED);
  EXPECT_EQ(jobs_->CancelJob(Ctx("wrong-token").get(), c, &j).error_code(), C::UNAUTHENTICATED);
  EXPECT_EQ(jobs_->CancelJob(Ctx("alice-token").get(), c, &j).error_code(), C::OK);
  WaitFinal(job);
  v1::DeleteJobRequest d;
  d.set_name(job);
  v1::DeleteJobResponse dr;
  EXPECT_EQ(jobs_->DeleteJob(Ctx("rita-token").get(), d, &dr).error_code(), C::PERMISSION_DENIED);
  EXPECT_EQ(jobs_->DeleteJob(Ctx("root-token").get(), d, &dr).error_code(), C::OK);
  v1::DeleteVolumeRequest dv;
  dv.set_name(volume_name_);
  v1::DeleteVolumeResponse dvr;
  EXPECT_EQ(volumes_->DeleteVolume(Ctx("alice-token").get(), dv, &dvr).error_code(), C::OK);

  const std::vector<std::string> expected = {
      R"({"principal":"alice","role":"submitter","rpc":"Upload","resource":"blobs/)" +
          phantom_sha_ + R"(","result":"OK"})",
      R"({"principal":"alice","role":"submitter","rpc":"CreateVolume","resource":")" +
          volume_name_ + R"(","result":"OK"})",
      R"({"principal":"alice","role":"submitter","rpc":"CreateJob","resource":")" + job +
          R"(","result":"OK"})",
      R"({"principal":"bob","role":"submitter","rpc":"CancelJob","resource":")" + job +
          R"(","result":"PERMISSION_DENIED"})",
      // Refused before anyone was identified: nothing the caller sent is written.
      R"({"principal":"","role":"","rpc":"CancelJob","resource":"","result":"UNAUTHENTICATED"})",
      R"({"principal":"alice","role":"submitter","rpc":"CancelJob","resource":")" + job +
          R"(","result":"OK"})",
      R"({"principal":"rita","role":"reader","rpc":"DeleteJob","resource":")" + job +
          R"(","result":"PERMISSION_DENIED"})",
      R"({"principal":"root","role":"admin","rpc":"DeleteJob","resource":")" + job +
          R"(","result":"OK"})",
      R"({"principal":"alice","role":"submitter","rpc":"DeleteVolume","resource":")" +
          volume_name_ + R"(","result":"OK"})",
  };
  std::vector<std::string> lines;
  std::istringstream in(ReadFile(audit_));
  for (std::string line; std::getline(in, line);) {
    // "<UTC time>Z {json}": the time, then the object.
    auto space = line.find(' ');
    ASSERT_NE(space, std::string::npos) << line;
    EXPECT_EQ(line[space - 1], 'Z') << line;
    auto obj = nlohmann::json::parse(line.substr(space + 1), nullptr, false);
    EXPECT_TRUE(obj.is_object()) << line;
    lines.push_back(line.substr(space + 1));
  }
  EXPECT_EQ(lines, expected);
}

// The lines of the audit file `path` and its rotated siblings (audit.1.log, ...), each checked
// to be "<time>Z {json}" with a JSON object; the objects are returned.
std::vector<nlohmann::json> AuditRecords(const fs::path& path, uintmax_t* bytes = nullptr) {
  std::vector<nlohmann::json> out;
  if (bytes) *bytes = 0;
  const std::string stem = path.stem().string(), ext = path.extension().string();
  for (const auto& e : fs::directory_iterator(path.parent_path())) {
    const std::string name = e.path().filename().string();
    if (name.rfind(stem, 0) != 0 || name.size() < ext.size() ||
        name.compare(name.size() - ext.size(), ext.size(), ext) != 0) {
      continue;
    }
    if (bytes) *bytes += fs::file_size(e.path());
    std::istringstream in(ReadFile(e.path()));
    for (std::string line; std::getline(in, line);) {
      auto space = line.find(' ');
      EXPECT_NE(space, std::string::npos) << line.substr(0, 200);
      if (space == std::string::npos) continue;
      auto obj = nlohmann::json::parse(line.substr(space + 1), nullptr, false);
      EXPECT_TRUE(obj.is_object()) << line.substr(0, 200);
      if (obj.is_object()) out.push_back(obj);
    }
  }
  return out;
}

// Issue 35 part 3: oversized requests (near gRPC's 4 MB limit) without credentials rotated every
// real record out of the files. Now an unidentified caller's lines hold nothing it sent and are
// rate-limited, and an identified caller's oversized, escape-laden name is cut and escaped: the
// authenticated records survive any number of such calls, in a 1 MiB x 2 file budget.
TEST_F(AuthE2E, OversizedCallsWithoutCredentialsKeepEveryAuthenticatedAuditRecord) {
  fs::path tokens = scratch_ / "tokens";
  std::ofstream(tokens) << "token " << Sha256Hex("alice-token") << " alice submitter\n";
  const fs::path audit = scratch_ / "audit" / "audit.log";
  fs::create_directories(audit.parent_path());
  ServerProcess server(scratch_ / "data",
                       {"--tokens-file", tokens.string(), "--audit-log", audit.string(),
                        "--audit-max-mb", "1", "--audit-files", "1"});
  auto ch = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto jobs = v1::Jobs::NewStub(ch);
  auto call = [&](const std::string& token, const std::string& name) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + 30s);
    if (!token.empty()) ctx.AddMetadata("authorization", "Bearer " + token);
    v1::DeleteJobRequest d;
    d.set_name(name);
    v1::DeleteJobResponse r;
    return jobs->DeleteJob(&ctx, d, &r).error_code();
  };
  // Authenticated records before and after the flood.
  ASSERT_EQ(call("alice-token", "jobs/first-real-record"), grpc::StatusCode::NOT_FOUND);
  // 1 MB names with a terminal escape, a line break and a character that is not ASCII.
  std::string huge = "jobs/\x1b[2J\n\xc3\xa9";
  huge.resize(1'000'000, 'x');
  constexpr int kFlood = 12;  // 12 MB of names: 6x the files' budget if written verbatim
  for (int i = 0; i < kFlood; ++i) ASSERT_EQ(call("", huge), grpc::StatusCode::UNAUTHENTICATED);
  // An identified caller's long name (short enough for the status message quoting it to fit
  // the client's 8 KiB metadata limit).
  const std::string long_name = huge.substr(0, 4000);
  ASSERT_EQ(call("alice-token", long_name), grpc::StatusCode::INVALID_ARGUMENT);
  ASSERT_EQ(call("alice-token", "jobs/last-real-record"), grpc::StatusCode::NOT_FOUND);

  uintmax_t bytes = 0;
  auto records = AuditRecords(audit, &bytes);
  EXPECT_LT(bytes, 16u << 10) << "the files grew with the callers' names";
  int unidentified = 0;
  std::vector<std::string> alice;
  for (const auto& r : records) {
    if (r["principal"] == "") {
      ++unidentified;
      EXPECT_EQ(r["resource"], "") << r.dump();
      EXPECT_EQ(r["result"], "UNAUTHENTICATED") << r.dump();
    } else {
      alice.push_back(r["resource"].get<std::string>());
    }
  }
  // At most kUnidentifiedPerSecond (10) a second.
  EXPECT_GE(unidentified, 1);
  EXPECT_LE(unidentified, kFlood);
  ASSERT_EQ(alice.size(), 3u);
  EXPECT_EQ(alice[0], "jobs/first-real-record");
  // Cut to 256 bytes of the name, escaped, and saying how much was left out.
  EXPECT_EQ(alice[1].substr(0, 9), "jobs/\x1b[2J");
  EXPECT_NE(alice[1].find("...(+" + std::to_string(long_name.size() - 256) + " bytes)"),
            std::string::npos);
  EXPECT_EQ(alice[2], "jobs/last-real-record");
  std::printf(
      "%d oversized unauthenticated calls: %d lines written, audit files %ju bytes, "
      "%zu of 3 authenticated records kept\n",
      kFlood, unidentified, bytes, alice.size());
  // Raw: every byte that is not printable ASCII as \u00XX; no control character but the line
  // ends.
  EXPECT_THAT(ReadFile(audit), HasSubstr(R"("jobs/\u001b[2J\u000a\u00c3\u00a9xxx)"));
  for (const auto& e : fs::directory_iterator(audit.parent_path())) {
    if (e.path().extension() != ".log") continue;
    for (unsigned char c : ReadFile(e.path())) {
      EXPECT_TRUE(c == '\n' || (c >= 0x20 && c < 0x7f)) << "byte " << int(c) << " in " << e.path();
      if (!(c == '\n' || (c >= 0x20 && c < 0x7f))) break;
    }
  }
}

// One writer per audit file: spdlog rotates by renaming, so two processes on one file lose each
// other's records. A second server pointed at a file another one writes refuses to start, and
// a server on the default name writes a file named for its host (replicas sharing a data dir
// each write their own).
TEST_F(AuthE2E, ASecondServerOnTheSameAuditFileRefusesToStartAndTheDefaultIsPerHost) {
  const fs::path audit = scratch_ / "shared-audit.log";
  ServerProcess first(scratch_ / "data1", {"--audit-log", audit.string()});
  CliResult second =
      RunProgram({ServerBinary().string(), "--data-dir", (scratch_ / "data2").string(), "--listen",
                  "127.0.0.1:0", "--audit-log", audit.string()},
                 20s);
  EXPECT_EQ(second.rc, 1) << second.err;
  EXPECT_THAT(second.out + second.err, HasSubstr("written by another process"));
  EXPECT_THAT(second.out + second.err, HasSubstr(audit.string()));

  ServerProcess third(scratch_ / "data3");
  char host[256] = {};
  ASSERT_EQ(gethostname(host, sizeof host - 1), 0);
  EXPECT_TRUE(fs::exists(scratch_ / "data3" / ("audit-" + std::string(host) + ".log")))
      << third.Log();
  EXPECT_FALSE(fs::exists(scratch_ / "data3" / "audit.log"));
}

// A record that cannot be written (here every write fails: the file is /dev/full) stops
// mutations with UNAVAILABLE instead of letting them go unaudited, and the server says so.
TEST_F(AuthE2E, MutationsAreRefusedWhileTheAuditLogCannotBeWritten) {
  if (!fs::exists("/dev/full")) GTEST_SKIP() << "no /dev/full";
  const fs::path audit = scratch_ / "audit.log";
  fs::create_symlink("/dev/full", audit);
  ServerProcess server(scratch_ / "data", {"--audit-log", audit.string()});
  auto ch = grpc::CreateChannel(server.address(), grpc::InsecureChannelCredentials());
  auto jobs = v1::Jobs::NewStub(ch);
  auto del = [&] {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + 30s);
    v1::DeleteJobRequest d;
    d.set_name("jobs/nonexistent");
    v1::DeleteJobResponse r;
    return jobs->DeleteJob(&ctx, d, &r);
  };
  // The first call is made (the log could not know), its record fails, auditing stops.
  EXPECT_EQ(del().error_code(), grpc::StatusCode::NOT_FOUND);
  for (int i = 0; i < 3; ++i) {
    grpc::Status st = del();
    EXPECT_EQ(st.error_code(), grpc::StatusCode::UNAVAILABLE);
    EXPECT_THAT(st.error_message(), HasSubstr("audit log cannot be written"));
  }
  // Reads go on.
  CliResult h = RunCli(server.address(), {"list"});
  EXPECT_EQ(h.rc, 0) << h.err;
  EXPECT_THAT(server.Log(), HasSubstr("AUDIT LOG STOPPED"));
}

testing::PostgresServer* SharedPostgres() {
  static testing::PostgresServer* pg = [] {
    auto* p = new testing::PostgresServer();
    std::atexit([] { delete SharedPostgres(); });
    return p;
  }();
  return pg;
}

// Issue 35 part 7: every submit of the same file made a new volume record. Now a principal's
// submit of a file it already has as a live volume reuses that volume (the CLI says so), another
// principal's identical bytes are a record of its own, and a deleted volume is not reused. In
// both job stores (the volume rows live there), with the real server and CLI.
class VolumeReuseE2E : public ScratchTest, public ::testing::WithParamInterface<std::string> {
 protected:
  VolumeReuseE2E() : ScratchTest("volume_reuse_e2e") {}
  void SetUp() override {
    ScratchTest::SetUp();
    tokens_ = scratch_ / "tokens";
    std::ofstream(tokens_) << "token " << Sha256Hex("alice-token") << " alice submitter\n"
                           << "token " << Sha256Hex("bob-token") << " bob submitter\n";
    if (GetParam() == "postgresql") {
      if (!testing::PostgresServer::BinDir()) GTEST_SKIP() << testing::PostgresServer::WhyAbsent();
      ASSERT_EQ(SharedPostgres()->error(), "") << "PostgreSQL did not start";
      const std::string db = "reuse" + std::to_string(::getpid());
      ASSERT_EQ(SharedPostgres()->CreateDatabase(db), "");
      store_ = {"--store", SharedPostgres()->Dsn(db)};
    }
  }
  // `decima --token TOKEN submit phantom.nii --watch`: the job's name and the CLI's stderr.
  std::pair<std::string, std::string> Submit(const std::string& address, const std::string& token) {
    CliResult r = RunCli(address, {"--token", token, "submit", volume_.string(), "--image-size",
                                   "32", "--reduction", "0.3", "--watch"});
    EXPECT_EQ(r.rc, 0) << r.err;
    return {FirstLine(r.out), r.err};
  }
  std::string VolumeOf(const std::string& address, const std::string& token,
                       const std::string& job) {
    CliResult r = RunCli(address, {"--token", token, "status", job, "-o", "json"});
    auto j = nlohmann::json::parse(r.out, nullptr, false);
    EXPECT_TRUE(j.is_object()) << r.out << r.err;
    return j.is_object() ? j["spec"]["volume"].get<std::string>() : "";
  }
  std::vector<std::string> Volumes(const std::string& address, const std::string& token) {
    auto stub = v1::Volumes::NewStub(SharedChannel(address));
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + 30s);
    ctx.AddMetadata("authorization", "Bearer " + token);
    v1::ListVolumesResponse resp;
    grpc::Status st = stub->ListVolumes(&ctx, {}, &resp);
    EXPECT_TRUE(st.ok()) << st.error_message();
    std::vector<std::string> names;
    for (const auto& v : resp.volumes()) names.push_back(v.name());
    return names;
  }

  fs::path tokens_;
  std::vector<std::string> store_;
};

TEST_P(VolumeReuseE2E, TheSameFileIsOneVolumePerPrincipalUntilDeleted) {
  std::vector<std::string> flags = {"--tokens-file", tokens_.string()};
  flags.insert(flags.end(), store_.begin(), store_.end());
  ServerProcess server(scratch_ / "data", flags);
  const std::string addr = server.address();

  const auto [job1, err1] = Submit(addr, "alice-token");
  const std::string alices = VolumeOf(addr, "alice-token", job1);
  ASSERT_FALSE(alices.empty());
  EXPECT_THAT(err1, HasSubstr("uploaded"));
  EXPECT_THAT(err1, ::testing::Not(HasSubstr("reusing")));
  const auto [job2, err2] = Submit(addr, "alice-token");
  EXPECT_NE(job2, job1);
  EXPECT_EQ(VolumeOf(addr, "alice-token", job2), alices);
  EXPECT_THAT(err2, HasSubstr("reusing " + alices));
  EXPECT_THAT(err2, ::testing::Not(HasSubstr("uploaded")));
  EXPECT_EQ(Volumes(addr, "alice-token"), std::vector<std::string>{alices});

  // Bob's identical bytes: a record of his own, which alice's listing does not show.
  const auto [job3, err3] = Submit(addr, "bob-token");
  const std::string bobs = VolumeOf(addr, "bob-token", job3);
  EXPECT_NE(bobs, alices);
  EXPECT_THAT(err3, ::testing::Not(HasSubstr("reusing")));
  EXPECT_EQ(Volumes(addr, "bob-token"), std::vector<std::string>{bobs});
  EXPECT_EQ(Volumes(addr, "alice-token"), std::vector<std::string>{alices});
  const auto [job4, err4] = Submit(addr, "bob-token");
  EXPECT_THAT(err4, HasSubstr("reusing " + bobs));

  // Deleted (with both jobs that read it), then submitted again: a new record.
  CliResult del = RunCli(addr, {"--token", "alice-token", "delete", job1, job2, "--volume"});
  ASSERT_EQ(del.rc, 0) << del.err;
  EXPECT_THAT(del.out, HasSubstr("deleted " + alices));
  const auto [job5, err5] = Submit(addr, "alice-token");
  const std::string fresh = VolumeOf(addr, "alice-token", job5);
  EXPECT_NE(fresh, alices);
  EXPECT_THAT(err5, ::testing::Not(HasSubstr("reusing")));
  EXPECT_EQ(Volumes(addr, "alice-token"), std::vector<std::string>{fresh});
  EXPECT_EQ(Volumes(addr, "bob-token"), std::vector<std::string>{bobs});

  // A refused job on a reused volume leaves that volume alone: it was alice's before the call
  // (the CLI deletes only a volume its own call created), even when no job reads it any more.
  ASSERT_EQ(RunCli(addr, {"--token", "alice-token", "delete", job5}).rc, 0);
  CliResult refused = RunCli(addr, {"--token", "alice-token", "submit", volume_.string(),
                                    "--transfer-function", "no-such"});
  EXPECT_NE(refused.rc, 0);
  EXPECT_THAT(refused.err, HasSubstr("reusing " + fresh));
  EXPECT_THAT(refused.err, HasSubstr("INVALID_ARGUMENT"));
  EXPECT_EQ(Volumes(addr, "alice-token"), std::vector<std::string>{fresh});
  // A volume the refused submit made itself is deleted again.
  const fs::path other = scratch_ / "other.nii";
  WriteTinyNifti(other, 12, 10, 8, 5);
  refused = RunCli(
      addr, {"--token", "alice-token", "submit", other.string(), "--transfer-function", "no-such"});
  EXPECT_NE(refused.rc, 0);
  EXPECT_THAT(refused.err, ::testing::Not(HasSubstr("reusing")));
  EXPECT_EQ(Volumes(addr, "alice-token"), std::vector<std::string>{fresh});
}

INSTANTIATE_TEST_SUITE_P(Stores, VolumeReuseE2E, ::testing::Values("sqlite", "postgresql"),
                         [](const auto& info) { return info.param; });

}  // namespace
}  // namespace decima::e2e
