#include "server/dicom/dicom_receiver.h"
#include "server/dicom/receiver_parts.h"

// clang-format off
#include "dcmtk/config/osconfig.h"  // must come first
// clang-format on
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/dul.h"
#include "dcmtk/dcmnet/scpthrd.h"
#include "dcmtk/oflog/oflog.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <google/protobuf/util/time_util.h>

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "core/common/utf8.h"
#include "decima/v1/errors.pb.h"
#include "server/dicom/dicom_sender.h"
#include "server/files/volume_catalog.h"
#include "server/jobs/job_spec.h"
#include "server/util/ids.h"
#include "server/util/sha256.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace fs = std::filesystem;

int64_t WallMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

bool IsAeTitle(const std::string& ae) {
  if (ae.empty() || ae.size() > 16) return false;
  for (char c : ae) {
    if (c < 0x20 || c > 0x7E || c == '\\') return false;
  }
  return true;
}

namespace {

bool IsLoopbackHost(const std::string& host) {
  return host == "127.0.0.1" || host == "localhost" || host == "::1";
}

// Transfer syntaxes accepted for every storage SOP class: uncompressed, then the compressed
// ones GDCM (the job's reader) decodes. Not the deflated one: the job's reader refuses it
// (core/io/dicom_preflight.h), so its instances were acknowledged and then never processed, and
// reading their headers in the server inflated every element before the pixel data (a 0.5 MB
// instance grew the server by 512 MiB). A sender offered only explicit and implicit VR sends
// the same data set uncompressed.
const char* kTransferSyntaxes[] = {UID_LittleEndianExplicitTransferSyntax,
                                   UID_LittleEndianImplicitTransferSyntax,
                                   UID_BigEndianExplicitTransferSyntax,
                                   UID_JPEGProcess1TransferSyntax,
                                   UID_JPEGProcess2_4TransferSyntax,
                                   UID_JPEGProcess14SV1TransferSyntax,
                                   UID_JPEGProcess14TransferSyntax,
                                   UID_JPEGLSLosslessTransferSyntax,
                                   UID_JPEGLSLossyTransferSyntax,
                                   UID_JPEG2000LosslessOnlyTransferSyntax,
                                   UID_JPEG2000TransferSyntax,
                                   UID_RLELosslessTransferSyntax};

absl::Status CopyIntoBlobs(BlobStore* blobs, const fs::path& file, const std::string& sha,
                           int64_t size) {
  if (blobs->Has(sha)) return absl::OkStatus();
  const BlobStatus held = blobs->Status(sha, size);
  auto writer = blobs->OpenWriter(sha, size, held.committed_size);
  if (!writer.ok()) return writer.status();
  std::ifstream in(file, std::ios::binary);
  in.seekg(held.committed_size);
  std::vector<char> buf(1 << 20);
  while (in) {
    in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
    const std::streamsize n = in.gcount();
    if (n <= 0) break;
    if (auto st = (*writer)->Append(buf.data(), static_cast<size_t>(n)); !st.ok()) return st;
  }
  if (in.bad()) return absl::InternalError(absl::StrCat(file.string(), ": read failed"));
  return (*writer)->Commit();
}

}  // namespace

// DCMTK's network: the DUL state the associations share. Its listening socket is ours
// (DicomReceiver::listen_fd_): DCMTK 3.6.7 binds every interface and reads a connection's
// association request in the same call that accepts it, so one silent connection held the port.
class ScpNetwork {
 public:
  T_ASC_Network* net = nullptr;
  DcmSharedSCPConfig config;
  ~ScpNetwork() {
    if (net != nullptr) ASC_dropNetwork(&net);
  }
};

namespace {

// dcmExternalSocketHandle is DCMTK's one process-wide way to hand it an accepted socket; every
// use (set, ASC_receiveAssociation, reset) holds this.
std::mutex& ExternalSocketMutex() {
  static std::mutex mu;
  return mu;
}

// Waits until `fd` holds a whole A-ASSOCIATE-RQ PDU (PS3.8 9.3.2: type 01, a 4-byte big-endian
// length), so DCMTK's read of it does not block. A connection that sends anything else, a PDU
// over 1 MiB, or not all of it within the deadline is answered with an error.
absl::Status WaitForAssociateRequest(int fd, std::chrono::steady_clock::time_point deadline) {
  constexpr uint32_t kMaxRequestBytes = 1 << 20;
  unsigned char head[6];
  size_t want = sizeof(head);
  for (int round = 0; round < 100000; ++round) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) break;
    pollfd p{fd, POLLIN, 0};
    const int n = ::poll(&p, 1, static_cast<int>(std::min<int64_t>(left.count(), 1000)));
    if (n < 0 && errno != EINTR) return absl::UnavailableError(std::strerror(errno));
    if (n <= 0) continue;
    const ssize_t got = ::recv(fd, head, sizeof(head), MSG_PEEK);
    if (got <= 0) return absl::UnavailableError("closed before its association request");
    if (got < static_cast<ssize_t>(sizeof(head))) {
      // Part of the header: wait for more without spinning.
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
      continue;
    }
    if (head[0] != 0x01) {
      return absl::InvalidArgumentError(
          absl::StrFormat("first PDU has type %02X, expected an A-ASSOCIATE-RQ (01)", head[0]));
    }
    const uint32_t length = (uint32_t{head[2]} << 24) | (uint32_t{head[3]} << 16) |
                            (uint32_t{head[4]} << 8) | uint32_t{head[5]};
    if (length > kMaxRequestBytes) {
      return absl::InvalidArgumentError(
          absl::StrCat("A-ASSOCIATE-RQ of ", length, " bytes; at most ", kMaxRequestBytes));
    }
    want = sizeof(head) + length;
    int avail = 0;
    if (::ioctl(fd, FIONREAD, &avail) == 0 && static_cast<size_t>(avail) >= want) {
      return absl::OkStatus();
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return absl::DeadlineExceededError(want == sizeof(head) ? "no association request"
                                                          : "association request incomplete");
}

std::string PeerAddress(const sockaddr_storage& a) {
  char buf[INET6_ADDRSTRLEN] = {0};
  if (a.ss_family == AF_INET) {
    ::inet_ntop(AF_INET, &reinterpret_cast<const sockaddr_in&>(a).sin_addr, buf, sizeof(buf));
  } else if (a.ss_family == AF_INET6) {
    ::inet_ntop(AF_INET6, &reinterpret_cast<const sockaddr_in6&>(a).sin6_addr, buf, sizeof(buf));
  }
  return buf;
}

}  // namespace

// One association, on its connection's thread (DcmThreadSCP: the configuration is shared,
// read-only).
class StorageScp : public DcmThreadSCP {
 public:
  StorageScp(DicomReceiver* r, T_ASC_Association* assoc, int fd, std::string peer)
      : r_(r), assoc_(assoc), fd_(fd), peer_(std::move(peer)) {}

 protected:
  // Verification, then every storage SOP class in kTransferSyntaxes. Done here rather than by
  // DcmSCPConfig's profile, which holds at most 128 presentation contexts: DCMTK 3.6.7 knows
  // more storage SOP classes than that, so Verification, added last, was silently dropped and
  // echoscu was refused.
  OFCondition negotiateAssociation() override {
    const char* verification[] = {UID_VerificationSOPClass};
    const char* echo_syntaxes[] = {UID_LittleEndianExplicitTransferSyntax,
                                   UID_LittleEndianImplicitTransferSyntax};
    OFCondition c = ASC_acceptContextsWithPreferredTransferSyntaxes(assoc_->params, verification, 1,
                                                                    echo_syntaxes, 2);
    if (c.good()) {
      c = ASC_acceptContextsWithPreferredTransferSyntaxes(
          assoc_->params, dcmAllStorageSOPClassUIDs, numberOfDcmAllStorageSOPClassUIDs,
          kTransferSyntaxes, static_cast<int>(std::size(kTransferSyntaxes)));
    }
    if (c.bad()) spdlog::error("dicom: negotiating with {}: {}", peer_, c.text());
    return c;
  }
  // The peer's AE titles are text from the network: escaped in every log line, so that a line
  // break cannot forge log lines.
  OFBool checkCalledAETitleAccepted(const OFString& called) override {
    if (called == r_->options().aet.c_str()) return OFTrue;
    spdlog::warn("dicom: association refused: called AE title '{}' is not ours ('{}')",
                 absl::CHexEscape(called.c_str()), r_->options().aet);
    return OFFalse;
  }
  OFBool checkCallingAETitleAccepted(const OFString& calling) override {
    // Refused here, before any instance is sent: the title is what every instance of the
    // association would be recorded under (ListReceivedSeries, the owner "dicom:<AE>").
    if (!IsAeTitle(calling.c_str())) {
      spdlog::warn(
          "dicom: association refused: calling AE title '{}' is not printable ASCII "
          "of 1-16 characters",
          absl::CHexEscape(calling.c_str()));
      return OFFalse;
    }
    if (r_->options().routes.Match(calling.c_str(), r_->options().aet) != nullptr) return OFTrue;
    spdlog::warn("dicom: association refused: no route for calling AE title '{}'",
                 absl::CHexEscape(calling.c_str()));
    return OFFalse;
  }
  OFBool checkCallingHostAccepted(const OFString& /*host_or_ip*/) override {
    if (!IsLoopbackHost(r_->options().host)) return OFTrue;
    // The port is bound to the loopback host already; the peer's address is checked again.
    const bool ok = peer_ == "127.0.0.1" || peer_ == "::1" || peer_ == "::ffff:127.0.0.1" ||
                    peer_.rfind("127.", 0) == 0;
    if (!ok) spdlog::warn("dicom: association from '{}' refused: listening on loopback", peer_);
    return ok ? OFTrue : OFFalse;
  }
  void notifyAssociationRequest(const T_ASC_Parameters& params, DcmSCPActionType& action) override {
    std::string why;
    if (!r_->DiskSpaceAllows(&why)) {
      spdlog::warn("dicom: association from '{}' refused: {}",
                   absl::CHexEscape(params.DULparams.callingAPTitle), why);
      action = DCMSCP_ACTION_REFUSE_ASSOCIATION;
    }
  }
  void notifyAssociationAcknowledge() override {
    released_ = false;
    calling_ = getPeerAETitle().c_str();
    series_.clear();
    stored_ = 0;
    // Random, so ids stay unique across restarts and replicas without shared state.
    association_ = NewId();
    spdlog::info("dicom: association {} accepted from {}: calling AE '{}', called AE '{}'",
                 association_, peer_, absl::CHexEscape(calling_),
                 absl::CHexEscape(getCalledAETitle().c_str()));
  }
  void notifyReleaseRequest() override { released_ = true; }
  void notifyAssociationTermination() override {
    if (association_.empty()) return;  // refused before it was accepted: no id, nothing sent
    spdlog::info("dicom: association {} from {} ({}) {}: {} instance(s) stored", association_,
                 peer_, absl::CHexEscape(calling_), released_ ? "released" : "aborted", stored_);
    // Aborted or broken off: what it sent may be a part of what was due.
    if (!released_ && !series_.empty()) r_->MarkAborted(calling_, series_);
    series_.clear();
    r_->EndAssociation(association_);
    association_.clear();
  }
  // Called as a dataset arrives, with the bytes received so far. Past the limit the connection
  // stops reading: DCMTK's next read fails and it aborts the association, so neither the spool
  // nor the sender's time is spent on the rest.
  void notifyRECEIVEProgress(const unsigned long bytes) override {
    if (too_big_ || static_cast<int64_t>(bytes) <= r_->options().max_instance_bytes) return;
    too_big_ = true;
    spdlog::warn(
        "dicom: instance from {} refused: more than {} MiB (--max-upload-mb); aborting the "
        "association",
        absl::CHexEscape(getPeerAETitle().c_str()), r_->options().max_instance_bytes >> 20);
    ::shutdown(fd_, SHUT_RD);
  }
  OFCondition handleIncomingCommand(T_DIMSE_Message* msg,
                                    const DcmPresentationContextInfo& info) override {
    if (msg->CommandField != DIMSE_C_STORE_RQ) return DcmSCP::handleIncomingCommand(msg, info);
    T_DIMSE_C_StoreRQ& req = msg->msg.CStoreRQ;
    const fs::path tmp = r_->spool() / absl::StrCat(NewId(), ".dcm");
    OFCondition c = receiveSTORERequest(req, info.presentationContextID, OFString(tmp.c_str()));
    if (c.bad() || too_big_) {
      std::error_code ec;
      fs::remove(tmp, ec);
      return c.bad() ? c : DIMSE_READPDVFAILED;
    }
    std::string series;
    Uint16 status;
    {
      std::lock_guard<std::mutex> lock(r_->store_mu_);
      status = r_->StoreInstance(tmp, getPeerAETitle().c_str(), getCalledAETitle().c_str(), &series,
                                 association_);
    }
    if (!series.empty()) {
      series_.insert(series);
      ++stored_;
    }
    std::error_code ec;
    fs::remove(tmp, ec);
    return sendSTOREResponse(info.presentationContextID, req, status);
  }

 private:
  DicomReceiver* r_;
  T_ASC_Association* assoc_;
  int fd_;
  std::string peer_;
  bool released_ = false;
  bool too_big_ = false;
  std::string calling_;           // the current association's calling AE title
  std::set<std::string> series_;  // series of the current association
  std::string association_;       // the current association's id ("" before one is accepted)
  int stored_ = 0;                // instances it stored
};

DicomReceiver::DicomReceiver(DicomReceiverOptions options, const DataDir* data_dir, JobStore* store,
                             BlobStore* blobs, VolumeCatalog* catalog, WorkerPool* pool)
    : options_(std::move(options)),
      data_dir_(data_dir),
      store_(store),
      blobs_(blobs),
      catalog_(catalog),
      pool_(pool),
      started_ms_(WallMs()) {}

DicomReceiver::~DicomReceiver() { Stop(); }

fs::path DicomReceiver::spool() const { return data_dir_->dicom_spool(); }

bool DicomReceiver::DiskSpaceAllows(std::string* why) const {
  struct statvfs s {};
  if (::statvfs(data_dir_->root().c_str(), &s) != 0) {
    *why = absl::StrCat("statvfs ", data_dir_->root().string(), " failed");
    return false;
  }
  const int64_t free_mb =
      static_cast<int64_t>(s.f_bavail) * static_cast<int64_t>(s.f_frsize) / (1 << 20);
  if (free_mb >= options_.min_free_mb) return true;
  *why = absl::StrCat("only ", free_mb, " MiB free under ", data_dir_->root().string(),
                      " (--dicom-min-free-mb ", options_.min_free_mb, ")");
  return false;
}

absl::Status DicomReceiver::Start() {
  if (auto probe = store_->ListDicomInstances(); !probe.ok()) return probe.status();
  // DCMTK logs every C-STORE at INFO and every header-only read at WARN on stdout; our own
  // lines say what matters.
  OFLog::configure(OFLogger::ERROR_LOG_LEVEL);
  std::error_code ec;
  // What a previous process was receiving when it stopped was never acknowledged: the sender
  // sends it again.
  fs::remove_all(spool(), ec);
  fs::create_directories(spool(), ec);
  if (ec) return absl::InternalError(absl::StrCat(spool().string(), ": ", ec.message()));
  const std::string where = absl::StrCat("--dicom-listen ", options_.host, ":", options_.port);
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE;
  addrinfo* found = nullptr;
  const std::string port = std::to_string(options_.port);
  if (int e = ::getaddrinfo(options_.host.c_str(), port.c_str(), &hints, &found); e != 0) {
    return absl::UnavailableError(absl::StrCat(where, ": ", gai_strerror(e)));
  }
  std::string why = "no address";
  // IPv4 addresses first: "localhost" may resolve to ::1 first, and DICOM senders are
  // configured with IPv4 addresses.
  std::vector<addrinfo*> candidates;
  for (addrinfo* ai = found; ai != nullptr; ai = ai->ai_next) candidates.push_back(ai);
  std::stable_partition(candidates.begin(), candidates.end(),
                        [](const addrinfo* ai) { return ai->ai_family == AF_INET; });
  for (addrinfo* ai : candidates) {
    if (listen_fd_ >= 0) break;
    const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC, ai->ai_protocol);
    if (fd < 0) continue;
    const int one = 1;
    ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    if (::bind(fd, ai->ai_addr, ai->ai_addrlen) == 0 && ::listen(fd, 64) == 0) {
      listen_fd_ = fd;
    } else {
      why = std::strerror(errno);
      ::close(fd);
    }
  }
  ::freeaddrinfo(found);
  if (listen_fd_ < 0) return absl::UnavailableError(absl::StrCat(where, ": ", why));
  sockaddr_storage bound{};
  socklen_t len = sizeof(bound);
  ::getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&bound), &len);
  bound_port_ = ntohs(bound.ss_family == AF_INET6 ? reinterpret_cast<sockaddr_in6&>(bound).sin6_port
                                                  : reinterpret_cast<sockaddr_in&>(bound).sin_port);

  net_ = std::make_unique<ScpNetwork>();
  DcmSCPConfig& cfg = *net_->config;
  cfg.setAETitle(options_.aet.c_str());
  cfg.setHostLookupEnabled(OFFalse);
  cfg.setDIMSEBlockingMode(DIMSE_NONBLOCKING);
  cfg.setDIMSETimeout(static_cast<Uint32>(options_.timeout_seconds));
  cfg.setACSETimeout(static_cast<Uint32>(options_.timeout_seconds));
  cfg.setMaxReceivePDULength(ASC_MAXIMUMPDUSIZE);
  cfg.setProgressNotificationMode(OFTrue);
  OFCondition c;
  {
    // With an external socket set, DCMTK's acceptor network binds nothing of its own.
    std::lock_guard<std::mutex> lock(ExternalSocketMutex());
    dcmExternalSocketHandle.set(listen_fd_);
    c = ASC_initializeNetwork(NET_ACCEPTOR, bound_port_, options_.timeout_seconds, &net_->net);
    dcmExternalSocketHandle.set(-1);
  }
  if (c.bad()) {
    ::close(listen_fd_);
    listen_fd_ = -1;
    return absl::UnavailableError(absl::StrCat(where, ": ", c.text()));
  }
  // Logged before the threads start: the first spdlog call of a process builds spdlog's
  // registry, and the threads' own log calls must come after it (thread start orders them).
  spdlog::info(
      "dicom: storage SCP {} listening on {}:{} (quiet {} s, {} route(s), {} associations, {} "
      "per peer, timeout {} s)",
      options_.aet, options_.host, bound_port_, options_.quiet_seconds,
      options_.routes.routes.size(), options_.max_associations, options_.max_per_peer,
      options_.timeout_seconds);
  stop_ = false;
  accept_thread_ = std::thread([this] { AcceptLoop(); });
  settle_thread_ = std::thread([this] { SettleLoop(); });
  return absl::OkStatus();
}

void DicomReceiver::AcceptLoop() {
  while (!stop_) {
    {
      // Threads of finished connections are joined here, so they do not pile up.
      std::lock_guard<std::mutex> lock(conn_mu_);
      for (auto it = connections_.begin(); it != connections_.end();) {
        if (!it->done) {
          ++it;
          continue;
        }
        it->thread.join();
        it = connections_.erase(it);
      }
    }
    pollfd p{listen_fd_, POLLIN, 0};
    if (::poll(&p, 1, 200) <= 0) continue;  // 200 ms: Stop() is seen within that
    sockaddr_storage from{};
    socklen_t len = sizeof(from);
    const int fd = ::accept4(listen_fd_, reinterpret_cast<sockaddr*>(&from), &len, SOCK_CLOEXEC);
    if (fd < 0) continue;
    // Debian's DCMTK leaves Nagle's algorithm on: each C-STORE response would wait for the
    // delayed ACK (about 40 ms per instance).
    const int one = 1;
    ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
    const std::string peer = PeerAddress(from);
    std::lock_guard<std::mutex> lock(conn_mu_);
    int total = 0, from_peer = 0;
    for (const auto& conn : connections_) {
      if (conn.done) continue;
      ++total;
      from_peer += conn.peer == peer;
    }
    if (total >= options_.max_associations || from_peer >= options_.max_per_peer) {
      spdlog::warn(
          "dicom: connection from {} closed: {} open ({} from it; {} {})", peer, total, from_peer,
          total >= options_.max_associations ? "--dicom-max-associations" : "--dicom-max-per-peer",
          total >= options_.max_associations ? options_.max_associations : options_.max_per_peer);
      ::close(fd);
      continue;
    }
    Connection& conn = connections_.emplace_back();
    conn.fd = fd;
    conn.peer = peer;
    conn.thread = std::thread([this, fd, peer] { ServeConnection(fd, peer); });
  }
}

void DicomReceiver::ServeConnection(int fd, const std::string& peer) {
  auto finish = [&] {
    std::lock_guard<std::mutex> lock(conn_mu_);
    for (auto& conn : connections_) {
      if (conn.thread.get_id() == std::this_thread::get_id()) conn.done = true;
    }
  };
  // No longer shut down by Stop(): DCMTK closes the socket next, and the number may be reused.
  auto release_fd = [&] {
    std::lock_guard<std::mutex> lock(conn_mu_);
    for (auto& conn : connections_) {
      if (conn.fd == fd) conn.fd = -1;
    }
  };
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(options_.timeout_seconds);
  if (auto st = WaitForAssociateRequest(fd, deadline); !st.ok()) {
    if (!stop_) {
      spdlog::warn("dicom: connection from {} closed: {} within {} s (--dicom-timeout-seconds)",
                   peer, std::string(st.message()), options_.timeout_seconds);
    }
    release_fd();
    ::close(fd);
    return finish();
  }
  T_ASC_Association* assoc = nullptr;
  OFCondition c;
  {
    std::lock_guard<std::mutex> lock(ExternalSocketMutex());
    dcmExternalSocketHandle.set(fd);
    c = ASC_receiveAssociation(net_->net, &assoc, ASC_MAXIMUMPDUSIZE, nullptr, nullptr, OFFalse,
                               DUL_NOBLOCK, 1);
    dcmExternalSocketHandle.set(-1);
  }
  if (c.bad()) {
    spdlog::warn("dicom: association request from {}: {}", peer, c.text());
    release_fd();
    if (assoc != nullptr) {
      ASC_dropAssociation(assoc);
      ASC_destroyAssociation(&assoc);
    } else {
      ::close(fd);
    }
    return finish();
  }
  {
    StorageScp scp(this, assoc, fd, peer);
    scp.setSharedConfig(net_->config);
    scp.run(assoc);
    release_fd();
    // ~StorageScp drops the association and closes the socket.
  }
  finish();
}

void DicomReceiver::Stop() {
  stop_ = true;
  {
    std::lock_guard<std::mutex> lock(mu_);
    wake_ = true;
  }
  cv_.notify_all();
  if (accept_thread_.joinable()) accept_thread_.join();
  std::list<Connection> connections;
  {
    // Break off what is open: a silent association would otherwise keep Stop waiting for its
    // timeout.
    std::lock_guard<std::mutex> lock(conn_mu_);
    for (auto& conn : connections_) {
      if (conn.fd >= 0) ::shutdown(conn.fd, SHUT_RDWR);
    }
  }
  for (;;) {
    std::thread t;
    {
      std::lock_guard<std::mutex> lock(conn_mu_);
      for (auto& conn : connections_) {
        if (conn.thread.joinable()) {
          t = std::move(conn.thread);
          break;
        }
      }
    }
    if (!t.joinable()) break;
    t.join();
  }
  {
    std::lock_guard<std::mutex> lock(conn_mu_);
    connections_.clear();
  }
  if (settle_thread_.joinable()) settle_thread_.join();
  net_.reset();
  if (listen_fd_ >= 0) ::close(listen_fd_);
  listen_fd_ = -1;
}

void DicomReceiver::MarkAborted(const std::string& calling_ae,
                                const std::set<std::string>& series) {
  const int64_t now = WallMs();
  for (const auto& s : series) {
    spdlog::warn("dicom: the association from {} sending series {} was aborted",
                 absl::CHexEscape(calling_ae), s);
    // Unrecorded, a restart would judge the series by its geometry alone and might queue a
    // send cut short after a contiguous run of slices.
    if (auto st = store_->MarkDicomSeriesAborted(calling_ae, s, now); !st.ok()) {
      spdlog::error("dicom: recording the abort of series {}: {}", s, st.ToString());
    }
  }
}

namespace {

// C-STORE statuses DCMTK names only for other services: PS3.7 C.4 "Duplicate SOP instance".
constexpr uint16_t kDuplicateSopInstance = 0x0111;

// The SOP classes whose instances can be slices of the volume a job reads: the cross-sectional
// image storage classes GDCM reads as a stack. Everything else (a SEG or SC sent back by
// mistake, a report, a presentation state, a waveform, ...) can never complete a series, so it
// is refused when it arrives rather than waiting until it expires.
bool IsVolumeSliceClass(const std::string& uid) {
  static const char* const kSliceClasses[] = {UID_CTImageStorage,
                                              UID_EnhancedCTImageStorage,
                                              UID_LegacyConvertedEnhancedCTImageStorage,
                                              UID_MRImageStorage,
                                              UID_EnhancedMRImageStorage,
                                              UID_LegacyConvertedEnhancedMRImageStorage,
                                              UID_PositronEmissionTomographyImageStorage,
                                              UID_EnhancedPETImageStorage,
                                              UID_LegacyConvertedEnhancedPETImageStorage,
                                              UID_NuclearMedicineImageStorage};
  for (const char* c : kSliceClasses) {
    if (uid == c) return true;
  }
  return false;
}

// The SOP class's name for messages ("Segmentation Storage"), or its UID.
std::string SopClassName(const std::string& uid) {
  if (uid.empty()) return "no SOP Class UID";
  const char* name = dcmFindNameOfUID(uid.c_str(), nullptr);
  return name != nullptr ? absl::StrCat(name, " (", uid, ")") : uid;
}

}  // namespace

void DicomReceiver::RecordRefused(const std::string& kind, const std::string& series_uid,
                                  const std::string& calling_ae, const std::string& called_ae,
                                  const std::string& reason, const std::string& association_id) {
  Sha256 h;
  const std::string id = absl::StrCat(calling_ae, "\n", series_uid);
  h.Update(id.data(), id.size());
  DicomSeriesRecord rec;
  // Per association (each is a receive of its own); without one, per process start. The count
  // is kept in memory, not re-read per instance.
  rec.receive_key =
      absl::StrCat("refused-", kind, "-", h.HexDigest(), "@",
                   association_id.empty() ? absl::StrCat(started_ms_) : association_id);
  rec.association_id = association_id;
  const int64_t now = WallMs();
  {
    std::lock_guard<std::mutex> lock(mu_);
    Refused& r = refused_[rec.receive_key];
    if (r.count++ == 0) r.first_ms = now;
    rec.instance_count = r.count;
    rec.first_received_ms = r.first_ms;
  }
  rec.series_instance_uid = series_uid;
  rec.calling_ae = calling_ae;
  rec.called_ae = called_ae;
  const DicomRoute* route = options_.routes.Match(calling_ae, called_ae);
  rec.route = route != nullptr ? route->name : "";
  rec.state = v1::ReceivedSeries::REFUSED;
  rec.reason = ValidUtf8(reason);
  rec.last_received_ms = now;
  rec.update_ms = now;
  if (auto st = store_->PutDicomSeries(rec, {}); !st.ok()) {
    spdlog::error("dicom: recording a refused instance of series {}: {}", series_uid,
                  st.ToString());
  }
}

void DicomReceiver::EndAssociation(const std::string& association_id) {
  const std::string suffix = "@" + association_id;
  std::lock_guard<std::mutex> lock(mu_);
  std::erase_if(refused_, [&](const auto& entry) { return absl::EndsWith(entry.first, suffix); });
}

uint16_t DicomReceiver::StoreInstance(const fs::path& file, const std::string& calling_ae,
                                      const std::string& called_ae, std::string* series_uid,
                                      const std::string& association_id) {
  std::string why;
  if (!DiskSpaceAllows(&why)) {
    spdlog::warn("dicom: instance from {} refused: {}", absl::CHexEscape(calling_ae), why);
    return STATUS_STORE_Refused_OutOfResources;
  }
  // The AE titles go into ListReceivedSeries' answers too: printable ASCII (PS3.5 6.2, AE).
  auto header = ReadUids(file);
  if (header.ok() && !(IsAeTitle(calling_ae) && IsAeTitle(called_ae))) {
    header = absl::InvalidArgumentError("an AE title is not printable ASCII of 1-16 characters");
  }
  if (!header.ok()) {
    spdlog::warn("dicom: instance from {} refused: {}", absl::CHexEscape(calling_ae),
                 std::string(header.status().message()));
    return STATUS_STORE_Error_CannotUnderstand;
  }
  if (!IsVolumeSliceClass(header->sop_class_uid)) {
    const std::string reason =
        absl::StrCat(SopClassName(header->sop_class_uid),
                     " is not a slice of a volume: refused (C-STORE status 0122H)");
    spdlog::warn("dicom: instance {} of series {} from {} refused: {}", header->sop_uid,
                 header->series_uid, calling_ae, reason);
    RecordRefused("class", header->series_uid, calling_ae, called_ae, reason, association_id);
    return STATUS_STORE_Refused_SOPClassNotSupported;
  }
  auto sha = Sha256OfFile(file);
  std::error_code ec;
  const int64_t size = static_cast<int64_t>(fs::file_size(file, ec));
  if (options_.quota_mb > 0) {
    auto waiting = store_->DicomWaitingBytes(calling_ae);
    if (!waiting.ok()) {
      spdlog::error("dicom: instance {} from {}: {}", header->sop_uid, calling_ae,
                    waiting.status().ToString());
      return STATUS_STORE_Refused_OutOfResources;
    }
    if (*waiting + size > options_.quota_mb * (int64_t{1} << 20)) {
      spdlog::warn(
          "dicom: instance {} from {} refused: {} bytes of its instances already wait "
          "(--dicom-quota-mb {})",
          header->sop_uid, calling_ae, *waiting, options_.quota_mb);
      return STATUS_STORE_Refused_OutOfResources;
    }
  }
  absl::Status st = sha.ok() ? CopyIntoBlobs(blobs_, file, *sha, size) : sha.status();
  if (st.ok()) {
    // Held by its upload claim until the store row below holds it (BlobInUse counts received
    // instances), so the blob collector cannot take it in between.
    blobs_->Claim(*sha);
    st = store_->PutDicomInstance({header->series_uid, header->sop_uid, *sha, calling_ae, called_ae,
                                   WallMs(), 0, size, association_id});
  }
  if (st.code() == absl::StatusCode::kAlreadyExists) {
    // The first bytes stay: a job reads what the sender sent first, never a silent swap. The
    // new blob has no row and goes with the collector's next sweep.
    spdlog::error("dicom: instance of series {} refused: {}", header->series_uid,
                  std::string(st.message()));
    RecordRefused("bytes", header->series_uid, calling_ae, called_ae,
                  absl::StrCat(st.message(), ": refused (C-STORE status 0111H), the first kept"),
                  association_id);
    return kDuplicateSopInstance;
  }
  if (!st.ok()) {
    spdlog::error("dicom: storing instance {}: {}", header->sop_uid, st.ToString());
    return STATUS_STORE_Refused_OutOfResources;
  }
  *series_uid = header->series_uid;
  return STATUS_Success;
}

}  // namespace decima::server
