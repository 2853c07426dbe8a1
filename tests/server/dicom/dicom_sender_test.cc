// SendDicomFiles by C-STORE on loopback: a peer nobody listens on and a peer that never answers
// fail UNAVAILABLE with the reason, in bounded time; DCMTK's storescp, started as a process on a
// free port, stores every file. Then the receiver's sending of a finished job's results: a
// refusing peer is tried 3 times and the receive ends SEND_FAILED with the reason.
#include "server/dicom/dicom_sender.h"

#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <optional>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/dicom/dicom_receiver.h"
#include "server/files/blob_store.h"
#include "server/files/data_dir.h"
#include "server/store/job_store.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/process.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono_literals;
using ::testing::HasSubstr;
using Clock = std::chrono::steady_clock;

const fs::path kStorescp = "/usr/bin/storescp";

class DicomSenderTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeScratchDir("dicom_sender");
    fs::create_directories(dir_ / "series");
    testing::SliceSpec s;
    files_ = testing::WriteSeries(dir_ / "series", s, {2.0, 2.0});
    ASSERT_EQ(files_.size(), 3u);
  }
  DicomDestination Peer(int port) const {
    DicomDestination d;
    d.host = "127.0.0.1";
    d.port = port;
    d.aet = "STORESCP";
    d.calling_aet = "DECIMA";
    d.timeout_seconds = 2;
    return d;
  }
  fs::path dir_;
  std::vector<fs::path> files_;
};

TEST_F(DicomSenderTest, APortNobodyListensOnFailsUnavailableNamingThePeer) {
  const int port = testing::FreePort();
  ASSERT_GT(port, 0);
  const auto t0 = Clock::now();
  auto sent = SendDicomFiles(Peer(port), files_);
  EXPECT_LT(Clock::now() - t0, 15s);
  ASSERT_FALSE(sent.ok());
  EXPECT_EQ(sent.status().code(), absl::StatusCode::kUnavailable) << sent.status();
  EXPECT_THAT(std::string(sent.status().message()),
              HasSubstr("C-STORE STORESCP@127.0.0.1:" + std::to_string(port) + ": association"));
}

TEST_F(DicomSenderTest, APeerThatNeverAnswersFailsWithinItsTimeout) {
  // Accepts TCP (the kernel completes the handshake from the backlog) but never speaks DICOM.
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  ASSERT_GE(fd, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  addr.sin_port = 0;
  ASSERT_EQ(::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
  ASSERT_EQ(::listen(fd, 4), 0);
  socklen_t len = sizeof addr;
  ASSERT_EQ(::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len), 0);
  const int port = ntohs(addr.sin_port);
  DicomDestination d = Peer(port);
  d.timeout_seconds = 1;
  const auto t0 = Clock::now();
  auto sent = SendDicomFiles(d, files_);
  const double took = std::chrono::duration<double>(Clock::now() - t0).count();
  ::close(fd);
  ASSERT_FALSE(sent.ok());
  EXPECT_EQ(sent.status().code(), absl::StatusCode::kUnavailable) << sent.status();
  EXPECT_THAT(std::string(sent.status().message()), HasSubstr("association"));
  EXPECT_LT(took, 8.0) << "a silent peer holds the sender for its timeout, not for ever";
}

TEST_F(DicomSenderTest, AFileThatIsNotDicomIsRefusedBeforeAnyConnection) {
  const fs::path junk = dir_ / "junk.dcm";
  std::ofstream(junk) << "not a DICOM file";
  auto sent = SendDicomFiles(Peer(testing::FreePort()), {junk});
  ASSERT_FALSE(sent.ok());
  EXPECT_EQ(sent.status().code(), absl::StatusCode::kInvalidArgument) << sent.status();
  EXPECT_THAT(std::string(sent.status().message()), HasSubstr("junk.dcm"));
}

TEST_F(DicomSenderTest, StorescpOnLoopbackStoresEveryFile) {
  if (!fs::exists(kStorescp)) GTEST_SKIP() << "storescp (Debian package dcmtk) is not installed";
  const fs::path received = dir_ / "received";
  fs::create_directories(received);
  const int port = testing::FreePort();
  ASSERT_GT(port, 0);
  const pid_t pid = testing::Spawn(
      {kStorescp.string(), "-aet", "STORESCP", "-od", received.string(), std::to_string(port)},
      (dir_ / "storescp.log").string());
  ASSERT_GT(pid, 0);
  // storescp has no readiness signal: try until it listens (connection refused until then), for
  // at most 30 s (10 s was once too short on a loaded machine).
  absl::StatusOr<std::string> sent = absl::UnavailableError("not tried");
  for (int i = 0; i < 300 && absl::IsUnavailable(sent.status()); ++i) {
    std::this_thread::sleep_for(100ms);
    sent = SendDicomFiles(Peer(port), files_);
  }
  ::kill(pid, SIGTERM);
  testing::WaitExit(pid, 10s);
  ASSERT_TRUE(sent.ok()) << sent.status();
  EXPECT_THAT(*sent, HasSubstr("3 instances stored by C-STORE at STORESCP@127.0.0.1:"));
  size_t stored = 0;
  for (const auto& e : fs::directory_iterator(received)) stored += e.is_regular_file();
  EXPECT_EQ(stored, files_.size());
}

// A loopback listener that accepts and at once closes every connection, counting them: a PACS
// that refuses to talk.
class ClosingPeer {
 public:
  ClosingPeer() {
    fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (fd_ < 0 || ::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 ||
        ::listen(fd_, 8) != 0) {
      return;
    }
    socklen_t len = sizeof addr;
    ::getsockname(fd_, reinterpret_cast<sockaddr*>(&addr), &len);
    port_ = ntohs(addr.sin_port);
    thread_ = std::thread([this] {
      for (;;) {
        const int c = ::accept(fd_, nullptr, nullptr);
        if (c < 0) return;  // shut down
        ++accepted_;
        ::close(c);
      }
    });
  }
  ~ClosingPeer() {
    ::shutdown(fd_, SHUT_RDWR);
    if (thread_.joinable()) thread_.join();
    ::close(fd_);
  }
  int port() const { return port_; }
  int accepted() const { return accepted_.load(); }

 private:
  int fd_ = -1;
  int port_ = 0;
  std::atomic<int> accepted_{0};
  std::thread thread_;
};

// A receive whose job SUCCEEDED with one DICOM artifact, stored as the receiver leaves it.
class DicomResultsSendTest : public DicomSenderTest {
 protected:
  void SetUp() override {
    DicomSenderTest::SetUp();
    auto store = OpenSqliteJobStore((dir_ / "jobs.sqlite").string());
    ASSERT_TRUE(store.ok()) << store.status();
    store_ = *std::move(store);
    auto blobs = LocalBlobStore::Open(dir_ / "blobs", false);
    ASSERT_TRUE(blobs.ok()) << blobs.status();
    blobs_ = *std::move(blobs);
    data_.emplace(dir_);
    v1::JobSpec spec;
    spec.set_volume("volumes/v");
    bool created = false;
    ASSERT_TRUE(store_->CreateJob("j", spec, "", 10, "dicom:CT1", &created).ok());
    auto claim = store_->ClaimNext("test", 60000);
    ASSERT_TRUE(claim.ok() && claim->has_value());
    ASSERT_TRUE(data_->ResetJobOut("j", (*claim)->lease.epoch).ok());
    fs::copy_file(files_[0], data_->ArtifactsDir("j") / "segmentation.dcm");
    v1::Job outcome;
    outcome.add_artifacts()->set_file_name("segmentation.dcm");
    ASSERT_TRUE(store_->Finish((*claim)->lease, v1::SUCCEEDED, outcome).ok());
    DicomSeriesRecord rec;
    rec.receive_key = "set@1";
    rec.instance_set = "set";
    rec.series_instance_uid = "1.2.3";
    rec.job = "jobs/j";
    rec.route = "to-pacs";
    rec.results_pending = true;
    rec.state = v1::ReceivedSeries::QUEUED;
    rec.calling_ae = "CT1";
    rec.called_ae = "DECIMA";
    rec.instance_count = 3;
    ASSERT_TRUE(store_->PutDicomSeries(rec, {}).ok());
  }
  void TearDown() override {
    if (receiver_) receiver_->Stop();
  }
  void StartReceiver(const DicomDestination& dest) {
    DicomReceiverOptions o;
    o.port = 0;
    o.min_free_mb = 0;
    o.poll_seconds = 0.05;
    DicomRoute route;
    route.name = "to-pacs";
    route.destination = dest;
    o.routes.routes.push_back(route);
    receiver_ =
        std::make_unique<DicomReceiver>(o, &*data_, store_.get(), blobs_.get(), nullptr, nullptr);
    ASSERT_TRUE(receiver_->Start().ok());
  }
  // The receive once it is no longer followed, within `limit`; nullopt otherwise.
  std::optional<v1::ReceivedSeries> Settled(std::chrono::seconds limit) {
    const auto end = Clock::now() + limit;
    while (Clock::now() < end) {
      auto page = ListReceivedSeries(store_.get(), "", 100, "");
      if (page.ok()) {
        for (const auto& r : page->series) {
          if (r.state() == v1::ReceivedSeries::SENT ||
              r.state() == v1::ReceivedSeries::SEND_FAILED) {
            return r;
          }
        }
      }
      std::this_thread::sleep_for(50ms);
    }
    return std::nullopt;
  }

  std::unique_ptr<JobStore> store_;
  std::unique_ptr<LocalBlobStore> blobs_;
  std::optional<DataDir> data_;
  std::unique_ptr<DicomReceiver> receiver_;
};

TEST_F(DicomResultsSendTest, ARefusingPeerIsTriedThreeTimesThenTheReceiveIsSendFailed) {
  ClosingPeer peer;
  ASSERT_GT(peer.port(), 0);
  StartReceiver(Peer(peer.port()));
  // Three attempts 5 s apart.
  auto rec = Settled(30s);
  ASSERT_TRUE(rec.has_value()) << "the receive did not settle";
  EXPECT_EQ(rec->state(), v1::ReceivedSeries::SEND_FAILED);
  EXPECT_THAT(rec->send_status(), HasSubstr("attempt 3 failed: UNAVAILABLE"));
  EXPECT_THAT(rec->send_status(), HasSubstr("STORESCP@127.0.0.1:" + std::to_string(peer.port())));
  EXPECT_EQ(peer.accepted(), 3);
  std::this_thread::sleep_for(6s);  // past the next attempt's time had there been one
  EXPECT_EQ(peer.accepted(), 3) << "no attempt after the third";
}

TEST_F(DicomResultsSendTest, StorescpReceivesTheResultsAndTheReceiveIsSent) {
  if (!fs::exists(kStorescp)) GTEST_SKIP() << "storescp (Debian package dcmtk) is not installed";
  const fs::path received = dir_ / "received";
  fs::create_directories(received);
  const int port = testing::FreePort();
  ASSERT_GT(port, 0);
  const pid_t pid = testing::Spawn(
      {kStorescp.string(), "-aet", "STORESCP", "-od", received.string(), std::to_string(port)},
      (dir_ / "storescp.log").string());
  ASSERT_GT(pid, 0);
  // Listening before the receiver's first attempt: a refused first attempt would wait 5 s.
  for (int i = 0; i < 100; ++i) {
    const int c = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    addr.sin_port = htons(static_cast<uint16_t>(port));
    const bool up = ::connect(c, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0;
    ::close(c);
    if (up) break;
    std::this_thread::sleep_for(100ms);
  }
  StartReceiver(Peer(port));
  auto rec = Settled(30s);
  ::kill(pid, SIGTERM);
  testing::WaitExit(pid, 10s);
  ASSERT_TRUE(rec.has_value()) << "the receive did not settle";
  EXPECT_EQ(rec->state(), v1::ReceivedSeries::SENT) << rec->send_status();
  EXPECT_THAT(rec->send_status(), HasSubstr("sent: 1 instances stored by C-STORE"));
  size_t stored = 0;
  for (const auto& e : fs::directory_iterator(received)) stored += e.is_regular_file();
  EXPECT_EQ(stored, 1u);
}

}  // namespace
}  // namespace decima::server
