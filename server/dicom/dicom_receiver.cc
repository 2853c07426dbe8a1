#include "server/dicom/dicom_receiver.h"

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
using google::protobuf::util::TimeUtil;
namespace {

int64_t WallMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

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

struct Header {
  std::string series_uid, sop_uid, sop_class_uid;
};

// A UID as PS3.5 9.1 defines it: digits and dots, at most 64 characters. What the receiver
// keeps of an instance goes into ListReceivedSeries' answers (protobuf strings).
bool IsDicomUid(const std::string& uid) {
  return !uid.empty() && uid.size() <= 64 &&
         uid.find_first_not_of("0123456789.") == std::string::npos;
}

// What the receiver reads of an instance lies before the pixel data: the UIDs in groups 0008
// and 0020, the geometry in 0020 and 0028. Only the file's first kHeaderBytes are parsed (real
// headers keep these attributes within a few KiB; vendors' large private blocks come after, in
// groups 0029 and up), and no value longer than kMaxValueBytes is read, so neither a long run of
// tiny elements nor a declared length of 4 GiB costs more than a bounded tree. A header that
// fits in kHeaderBytes must parse whole up to the pixel data, as before.
constexpr size_t kHeaderBytes = 64 << 10;
constexpr Uint32 kMaxValueBytes = 1024;

// Sequences and items nested deeper than this are refused before DCMTK reads them: DCMTK
// parses nesting recursively, about 1.5 KiB of stack a level, so the 3,000 levels that fit in
// kHeaderBytes overflowed a thread's stack. Real headers nest a handful of levels.
constexpr size_t kMaxNesting = 32;  // sequences + items, so 16 levels of sequences

uint32_t ReadU32(absl::string_view b, size_t pos, bool big_endian) {
  const auto* u = reinterpret_cast<const unsigned char*>(b.data() + pos);
  return big_endian
             ? (uint32_t{u[0]} << 24) | (uint32_t{u[1]} << 16) | (uint32_t{u[2]} << 8) | u[3]
             : (uint32_t{u[3]} << 24) | (uint32_t{u[2]} << 16) | (uint32_t{u[1]} << 8) | u[0];
}
uint16_t ReadU16(absl::string_view b, size_t pos, bool big_endian) {
  const auto* u = reinterpret_cast<const unsigned char*>(b.data() + pos);
  return static_cast<uint16_t>(big_endian ? (u[0] << 8) | u[1] : (u[1] << 8) | u[0]);
}

// Walks the element headers of a data set (PS3.5 7.1, 7.5) from `pos` to the end of `b` or the
// top-level pixel data, skipping values, and answers whether sequences and items nest deeper
// than kMaxNesting. Undefined-length UN holds implicit VR (PS3.5 6.2.2). Stops quietly where
// the bytes stop making sense: DCMTK then reports the parse error.
bool NestsTooDeep(absl::string_view b, size_t pos, bool explicit_vr, bool big_endian) {
  constexpr uint32_t kUndefined = 0xFFFFFFFF;
  constexpr size_t kOpen = SIZE_MAX;
  struct Container {
    size_t end;  // kOpen: ends at its delimitation item
    bool explicit_vr;
  };
  std::vector<Container> open;
  for (size_t steps = 0; pos + 8 <= b.size() && steps < b.size(); ++steps) {
    while (!open.empty() && open.back().end != kOpen && pos >= open.back().end) open.pop_back();
    const bool ex = open.empty() ? explicit_vr : open.back().explicit_vr;
    const uint16_t group = ReadU16(b, pos, big_endian), element = ReadU16(b, pos + 2, big_endian);
    if (group == 0xFFFE) {
      const uint32_t length = ReadU32(b, pos + 4, big_endian);
      pos += 8;
      if (element == 0xE000) {
        open.push_back({length == kUndefined ? kOpen : pos + length, ex});
      } else if ((element == 0xE00D || element == 0xE0DD) && !open.empty()) {
        open.pop_back();
      }
      if (open.size() > kMaxNesting) return true;
      continue;
    }
    if (open.empty() && group == 0x7FE0 && element == 0x0010) return false;
    uint32_t length;
    bool sequence, un = false;
    if (ex) {
      const std::string vr = std::string(b.substr(pos + 4, 2));
      static const std::set<std::string> kLong = {"OB", "OD", "OF", "OL", "OV", "OW", "SQ",
                                                  "SV", "UC", "UN", "UR", "UT", "UV"};
      if (kLong.count(vr) > 0) {
        if (pos + 12 > b.size()) return false;
        length = ReadU32(b, pos + 8, big_endian);
        pos += 12;
      } else {
        length = ReadU16(b, pos + 6, big_endian);
        pos += 8;
      }
      un = vr == "UN";
      sequence = vr == "SQ" || (un && length == kUndefined);
    } else {
      length = ReadU32(b, pos + 4, big_endian);
      pos += 8;
      sequence = length == kUndefined;
    }
    if (sequence) {
      open.push_back({length == kUndefined ? kOpen : pos + length, ex && !un});
      if (open.size() > kMaxNesting) return true;
      continue;
    }
    if (length == kUndefined) return false;  // encapsulated data outside the pixel data
    pos += length;
  }
  return false;
}

// The header of `file` parsed by DCMTK from a copy of its first kHeaderBytes (a memfd, so DCMTK
// can never seek past them). INVALID_ARGUMENT naming the file for a deflated transfer syntax
// (never accepted, see kTransferSyntaxes) or a header DCMTK cannot parse.
absl::Status LoadBoundedHeader(const fs::path& file, DcmFileFormat* ff) {
  std::ifstream in(file, std::ios::binary);
  if (!in) return absl::InvalidArgumentError(absl::StrCat(file.string(), ": cannot open"));
  std::string head(kHeaderBytes, '\0');
  in.read(head.data(), static_cast<std::streamsize>(head.size()));
  head.resize(static_cast<size_t>(in.gcount()));
  const bool truncated = head.size() == kHeaderBytes && in.peek() != EOF;
  // Files the receiver writes always have the Part 10 header; without it DCMTK would guess the
  // transfer syntax, and so would the nesting walk.
  if (head.size() < 132 || head.compare(128, 4, "DICM") != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(file.string(), ": not a DICOM Part 10 file (no DICM marker at byte 128)"));
  }
  // The meta group (explicit VR little endian, PS3.10 7.1) is walked here first: DCMTK loads the
  // values it looks at (the transfer syntax) whatever length they declare. It ends at the first
  // element of another group, as DCMTK's reading of it does.
  size_t meta_end = 132;
  std::string ts;
  while (meta_end + 8 <= head.size() && ReadU16(head, meta_end, false) == 0x0002) {
    const size_t pos = meta_end;
    const std::string vr = head.substr(pos + 4, 2);
    const bool long_vr = vr == "OB" || vr == "UN" || vr == "UT" || vr == "UC" || vr == "UR" ||
                         vr == "OW" || vr == "SQ";
    const uint32_t length = long_vr && pos + 12 <= head.size() ? ReadU32(head, pos + 8, false)
                            : long_vr                          ? kHeaderBytes
                                                               : ReadU16(head, pos + 6, false);
    const size_t value = pos + (long_vr ? 12 : 8);
    if (length > kMaxValueBytes || value + length > head.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat(file.string(), ": meta header element at byte ", pos, " declares ", length,
                       " bytes; expected at most ", kMaxValueBytes));
    }
    if (ReadU16(head, pos + 2, false) == 0x0010) {
      ts = head.substr(value, length);
      while (!ts.empty() && (ts.back() == '\0' || ts.back() == ' ')) ts.pop_back();
    }
    meta_end = value + length;
  }
  if (ts == UID_DeflatedExplicitVRLittleEndianTransferSyntax) {
    return absl::InvalidArgumentError(absl::StrCat(
        file.string(), ": transfer syntax Deflated Explicit VR Little Endian is not accepted"));
  }
  const int fd = ::memfd_create("decima-dicom-header", MFD_CLOEXEC);
  if (fd < 0) return absl::InternalError(absl::StrCat("memfd_create: ", std::strerror(errno)));
  size_t written = 0;
  while (written < head.size()) {
    const ssize_t n = ::write(fd, head.data() + written, head.size() - written);
    if (n <= 0) break;
    written += static_cast<size_t>(n);
  }
  const std::string name = absl::StrCat("/proc/self/fd/", fd);
  OFCondition c = written == head.size() ? EC_Normal : EC_InvalidStream;
  if (c.good()) {
    const bool big_endian = ts == UID_BigEndianExplicitTransferSyntax;
    const bool explicit_vr = ts != UID_LittleEndianImplicitTransferSyntax;
    if (meta_end < head.size() && NestsTooDeep(head, meta_end, explicit_vr, big_endian)) {
      ::close(fd);
      return absl::InvalidArgumentError(absl::StrCat(
          file.string(), ": sequences nested deeper than ", kMaxNesting / 2, " levels"));
    }
    c = ff->loadFileUntilTag(name.c_str(), EXS_Unknown, EGL_noChange, kMaxValueBytes,
                             ERM_autoDetect, DCM_PixelData);
  }
  ::close(fd);
  // A header cut at kHeaderBytes ends in a parse error; the elements before the cut are read.
  if (c.bad() && !truncated) {
    return absl::InvalidArgumentError(absl::StrCat(file.string(), ": ", c.text()));
  }
  return absl::OkStatus();
}

// `tag`'s value as a string, empty when absent or longer than kMaxValueBytes (such a value was
// not read and is no UID, position or size anyway).
std::string SmallString(DcmItem& d, const DcmTagKey& tag, bool all_values = false) {
  DcmElement* e = nullptr;
  if (d.findAndGetElement(tag, e).bad() || e == nullptr || e->getLengthField() > kMaxValueBytes) {
    return "";
  }
  OFString v;
  if ((all_values ? e->getOFStringArray(v) : e->getOFString(v, 0)).bad()) return "";
  return v.c_str();
}

Uint16 SmallUint16(DcmItem& d, const DcmTagKey& tag) {
  DcmElement* e = nullptr;
  Uint16 v = 0;
  if (d.findAndGetElement(tag, e).bad() || e == nullptr || e->getLengthField() > kMaxValueBytes ||
      e->getUint16(v).bad()) {
    return 0;
  }
  return v;
}

absl::StatusOr<Header> ReadUids(const fs::path& file) {
  DcmFileFormat ff;
  if (auto st = LoadBoundedHeader(file, &ff); !st.ok()) return st;
  Header h{SmallString(*ff.getDataset(), DCM_SeriesInstanceUID),
           SmallString(*ff.getDataset(), DCM_SOPInstanceUID),
           SmallString(*ff.getDataset(), DCM_SOPClassUID)};
  if (h.series_uid.empty() || h.sop_uid.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "no SeriesInstanceUID or SOPInstanceUID within the first ", kHeaderBytes >> 10, " KiB"));
  }
  if (!IsDicomUid(h.series_uid) || !IsDicomUid(h.sop_uid)) {
    return absl::InvalidArgumentError("SeriesInstanceUID or SOPInstanceUID is not a DICOM UID");
  }
  return h;
}

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

bool IsAeTitle(const std::string& ae) {
  if (ae.empty() || ae.size() > 16) return false;
  for (char c : ae) {
    if (c < 0x20 || c > 0x7E || c == '\\') return false;
  }
  return true;
}

// The key of one sender's set of instances: the sender is part of it, so the request id made
// from it ("dicom-<key>") is another for the same SOP Instance UIDs from another sender.
std::string InstanceSetKey(const std::string& calling_ae, std::vector<std::string> sop_uids) {
  std::sort(sop_uids.begin(), sop_uids.end());
  Sha256 h;
  h.Update(calling_ae.data(), calling_ae.size());
  h.Update("\n", 1);
  for (const auto& u : sop_uids) {
    h.Update(u.data(), u.size());
    h.Update("\n", 1);
  }
  return h.HexDigest();
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

absl::Status CheckSeriesComplete(const std::vector<fs::path>& files) {
  struct Slice {
    fs::path file;
    Eigen::Vector3d position;
    double z = 0;
  };
  std::vector<Slice> slices;
  std::string orientation, spacing;
  long rows = -1, cols = -1;
  Eigen::Vector3d normal(0, 0, 1);
  for (const auto& f : files) {
    DcmFileFormat ff;
    if (auto st = LoadBoundedHeader(f, &ff); !st.ok()) return st;
    DcmDataset& d = *ff.getDataset();
    const OFString ipp = SmallString(d, DCM_ImagePositionPatient, true).c_str();
    const OFString iop = SmallString(d, DCM_ImageOrientationPatient, true).c_str();
    const OFString ps = SmallString(d, DCM_PixelSpacing, true).c_str();
    const Uint16 r = SmallUint16(d, DCM_Rows), co = SmallUint16(d, DCM_Columns);
    const OFString frames = SmallString(d, DCM_NumberOfFrames).c_str();
    const OFString images_in_acquisition = SmallString(d, DCM_ImagesInAcquisition).c_str();
    long expected = 0;
    if (!images_in_acquisition.empty() &&
        absl::SimpleAtoi(images_in_acquisition.c_str(), &expected) && expected > 0 &&
        static_cast<size_t>(expected) > files.size()) {
      return absl::InvalidArgumentError(absl::StrCat(files.size(), " of ", expected,
                                                     " instances (ImagesInAcquisition of ",
                                                     f.filename().string(), ")"));
    }
    auto name = f.filename().string();
    if (ipp.empty() || iop.empty() || ps.empty() || r == 0 || co == 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("instance ", name,
                       " lacks ImagePositionPatient, ImageOrientationPatient, PixelSpacing, "
                       "Rows or Columns: not a slice of a volume"));
    }
    if (!frames.empty() && frames != "1") {
      return absl::InvalidArgumentError(
          absl::StrCat("instance ", name, " has ", frames.c_str(), " frames; expected 1"));
    }
    std::vector<double> p, o;
    for (absl::string_view s : absl::StrSplit(ipp.c_str(), '\\')) {
      double v = 0;
      if (absl::SimpleAtod(s, &v)) p.push_back(v);
    }
    for (absl::string_view s : absl::StrSplit(iop.c_str(), '\\')) {
      double v = 0;
      if (absl::SimpleAtod(s, &v)) o.push_back(v);
    }
    if (p.size() != 3 || o.size() != 6) {
      return absl::InvalidArgumentError(
          absl::StrCat("instance ", name, ": malformed ImagePositionPatient or orientation"));
    }
    if (slices.empty()) {
      orientation = iop.c_str();
      spacing = ps.c_str();
      rows = r;
      cols = co;
      normal = Eigen::Vector3d(o[0], o[1], o[2]).cross(Eigen::Vector3d(o[3], o[4], o[5]));
      if (normal.norm() < 1e-6) {
        return absl::InvalidArgumentError(
            absl::StrCat("instance ", name, ": degenerate orientation"));
      }
      normal.normalize();
    } else if (orientation != iop.c_str()) {
      return absl::InvalidArgumentError(absl::StrCat("more than one orientation: ", orientation,
                                                     " and ", iop.c_str(), " (", name, ")"));
    } else if (rows != r || cols != co || spacing != ps.c_str()) {
      return absl::InvalidArgumentError(absl::StrCat("inconsistent size: ", cols, "x", rows,
                                                     " spacing ", spacing, " and ", co, "x", r,
                                                     " spacing ", ps.c_str(), " (", name, ")"));
    }
    Slice s{f, Eigen::Vector3d(p[0], p[1], p[2]), 0};
    s.z = s.position.dot(normal);
    slices.push_back(std::move(s));
  }
  if (slices.size() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(slices.size(), " slice(s): a volume needs 2 or more"));
  }
  std::sort(slices.begin(), slices.end(), [](const Slice& a, const Slice& b) { return a.z < b.z; });
  double min_gap = INFINITY;
  for (size_t i = 1; i < slices.size(); ++i) {
    const double gap = slices[i].z - slices[i - 1].z;
    if (gap < 1e-3) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "two instances at the same position z=%g mm (%s, %s)", slices[i].z,
          slices[i - 1].file.filename().string(), slices[i].file.filename().string()));
    }
    min_gap = std::min(min_gap, gap);
    // Every slice on the line through the first along the normal (no gantry tilt, no shift).
    const Eigen::Vector3d off = slices[i].position - slices[0].position;
    if ((off - off.dot(normal) * normal).norm() > 0.01 + 0.01 * min_gap) {
      return absl::InvalidArgumentError(absl::StrCat("slices not stacked along their normal (",
                                                     slices[i].file.filename().string(),
                                                     "): tilted or shifted series"));
    }
  }
  for (size_t i = 1; i < slices.size(); ++i) {
    const double gap = slices[i].z - slices[i - 1].z;
    if (std::abs(gap - min_gap) > 0.01 * min_gap + 0.01) {
      const long missing = std::lround(gap / min_gap) - 1;
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s between z=%g and z=%g mm (gap %g mm, expected %g mm); %d instances received",
          missing >= 1 ? absl::StrCat(missing, " slice(s) missing") : std::string("uneven spacing"),
          slices[i - 1].z, slices[i].z, gap, min_gap, slices.size()));
    }
  }
  return absl::OkStatus();
}

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

// A check's receive: the set at its newest arrival (the same set re-checked after a restart is
// the same receive; sent again later, a new one).
std::string ReceiveKey(const std::string& instance_set, int64_t newest_ms) {
  return absl::StrCat(instance_set, "@", newest_ms);
}

std::string FormatMs(int64_t ms) {
  return TimeUtil::ToString(TimeUtil::MillisecondsToTimestamp(ms));
}

// Earlier INCOMPLETE receives of the sender's series whose instances a later receive consumed or
// removed: they take the outcome (`state`, `job`, `reason`) instead of waiting for ever in the
// history. Bounded by the newest 1000 rows.
void CloseEarlierReceives(JobStore* store, const std::string& calling_ae,
                          const std::string& series_uid, const std::string& except_key,
                          v1::ReceivedSeries::State state, const std::string& job,
                          const std::string& reason) {
  auto rows = store->ListDicomSeries(/*pending_only=*/false, 1000);
  if (!rows.ok()) {
    spdlog::error("dicom: {}", rows.status().ToString());
    return;
  }
  for (DicomSeriesRecord r : *rows) {
    if (r.calling_ae != calling_ae || r.series_instance_uid != series_uid ||
        r.receive_key == except_key || r.state != v1::ReceivedSeries::INCOMPLETE) {
      continue;
    }
    r.state = state;
    r.job = job;
    r.reason = reason;
    r.update_ms = WallMs();
    if (auto st = store->PutDicomSeries(r, {}); !st.ok()) {
      spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
    }
  }
}

// Removes the waiting instances of a sender's series (expired or deleted), records the outcome
// as the receive of that set (`state`, `reason`), closes the sender's earlier INCOMPLETE
// receives of it, and frees the blobs nothing else holds.
absl::StatusOr<RemovedSeries> RemoveWaiting(JobStore* store, BlobStore* blobs,
                                            const std::string& calling_ae,
                                            const std::string& series_uid,
                                            v1::ReceivedSeries::State state,
                                            const std::string& reason) {
  auto removed = store->RemoveDicomInstances(calling_ae, series_uid);
  if (!removed.ok()) return removed.status();
  RemovedSeries out;
  if (removed->empty()) return out;
  out.instances = static_cast<int>(removed->size());
  std::vector<std::string> uids, shas;
  int64_t first = INT64_MAX, newest = 0;
  for (const auto& i : *removed) {
    uids.push_back(i.sop_instance_uid);
    shas.push_back(i.sha256);
    first = std::min(first, i.received_ms);
    newest = std::max(newest, i.received_ms);
  }
  const std::string set = InstanceSetKey(calling_ae, uids);
  DicomSeriesRecord rec;
  rec.receive_key = ReceiveKey(set, newest);
  // The row of this set's check, when it was checked: its route and counts stay.
  if (auto rows = store->ListDicomSeries(false, 1000); rows.ok()) {
    for (const auto& r : *rows) {
      if (r.receive_key == rec.receive_key) rec = r;
    }
  }
  rec.instance_set = set;
  rec.series_instance_uid = series_uid;
  rec.calling_ae = calling_ae;
  rec.called_ae = removed->back().called_ae;
  rec.association_id = removed->back().association_id;
  rec.instance_count = out.instances;
  rec.first_received_ms = first;
  rec.last_received_ms = newest;
  rec.state = state;
  rec.reason = reason;
  rec.job.clear();
  rec.results_pending = false;
  rec.update_ms = WallMs();
  if (auto st = store->PutDicomSeries(rec, {}); !st.ok()) {
    spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
  }
  CloseEarlierReceives(store, calling_ae, series_uid, rec.receive_key, state, "", reason);
  std::sort(shas.begin(), shas.end());
  shas.erase(std::unique(shas.begin(), shas.end()), shas.end());
  BlobSweepPolicy now;
  now.grace = std::chrono::seconds(0);
  // A blob another sender's instance or a volume holds stays (identical bytes are one blob).
  const BlobSweepStats swept = blobs->Sweep(
      now,
      [store](const std::string& sha) {
        auto used = store->BlobInUse(sha);
        return !used.ok() || *used;
      },
      &shas);
  out.freed_bytes = swept.bytes_freed;
  spdlog::info("dicom: series {} from {}: {} instances removed ({} bytes freed): {}", series_uid,
               absl::CHexEscape(calling_ae), out.instances, out.freed_bytes, reason);
  return out;
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

void DicomReceiver::SettleLoop() {
  const auto period = std::chrono::milliseconds(
      std::max<int64_t>(10, static_cast<int64_t>(options_.poll_seconds * 1000)));
  while (!stop_) {
    {
      std::unique_lock<std::mutex> lock(mu_);
      cv_.wait_for(lock, period, [this] { return wake_; });
      wake_ = false;
    }
    if (stop_) break;
    auto instances = store_->ListDicomInstances();
    if (!instances.ok()) {
      spdlog::error("dicom: {}", instances.status().ToString());
      continue;
    }
    // A series per sender: another sender's instances of the same SeriesInstanceUID are
    // another series (they never complete or replace these).
    std::map<std::pair<std::string, std::string>, std::vector<DicomInstanceRecord>> by_series;
    for (auto& i : *instances) {
      by_series[{i.calling_ae, i.series_instance_uid}].push_back(std::move(i));
    }
    const int64_t now = WallMs();
    const auto quiet_ms = static_cast<int64_t>(options_.quiet_seconds * 1000);
    const auto expiry_ms = static_cast<int64_t>(options_.incomplete_expiry_seconds * 1000);
    std::set<std::string> pending_keys;
    for (const auto& [sender_series, list] : by_series) {
      const auto& [calling_ae, series] = sender_series;
      int64_t newest = 0;
      std::vector<std::string> uids;
      for (const auto& i : list) {
        newest = std::max(newest, i.received_ms);
        uids.push_back(i.sop_instance_uid);
      }
      if (expiry_ms > 0 && now - newest >= expiry_ms) {
        auto removed = RemoveWaiting(
            store_, blobs_, calling_ae, series, v1::ReceivedSeries::EXPIRED,
            absl::StrCat("expired: no instance came for ", (now - newest) / 1000,
                         " s (--dicom-incomplete-expiry ", options_.incomplete_expiry_seconds,
                         " s); its ", list.size(), " waiting instances were removed"));
        if (!removed.ok()) spdlog::error("dicom: {}", removed.status().ToString());
        continue;
      }
      const std::string key = InstanceSetKey(calling_ae, uids);
      pending_keys.insert(key);
      // Once per set and newest arrival: the same set sent again (a retry after an abort, which
      // lifts the abort mark) is checked again.
      auto seen = checked_.find(key);
      if (now - newest < quiet_ms || (seen != checked_.end() && seen->second == newest)) continue;
      checked_[key] = newest;
      SettleSeries(series, list, key);
    }
    for (auto it = checked_.begin(); it != checked_.end();) {
      it = pending_keys.count(it->first) > 0 ? std::next(it) : checked_.erase(it);
    }
    FollowReceives();
  }
}

void DicomReceiver::SettleSeries(const std::string& series_uid,
                                 const std::vector<DicomInstanceRecord>& instances,
                                 const std::string& key) {
  const DicomInstanceRecord& last = instances.back();
  const DicomRoute* route = options_.routes.Match(last.calling_ae, last.called_ae);
  DicomSeriesRecord rec;
  rec.instance_set = key;
  rec.series_instance_uid = series_uid;
  rec.route = route != nullptr ? route->name : "";
  rec.update_ms = WallMs();
  rec.calling_ae = last.calling_ae;
  rec.called_ae = last.called_ae;
  rec.association_id = last.association_id;
  rec.instance_count = static_cast<int>(instances.size());
  rec.first_received_ms = INT64_MAX;
  int64_t newest = 0, aborted = 0;
  for (const auto& i : instances) {
    rec.first_received_ms = std::min(rec.first_received_ms, i.received_ms);
    newest = std::max(newest, i.received_ms);
    aborted = std::max(aborted, i.aborted_ms);
  }
  rec.last_received_ms = newest;
  rec.receive_key = ReceiveKey(key, newest);
  const std::string owner = DicomOwner(last.calling_ae);
  auto not_queued = [&](v1::ReceivedSeries::State state, const std::string& reason) {
    rec.state = state;
    // The reason may quote the instances' own text (NumberOfFrames, ...): kept as valid UTF-8,
    // which PostgreSQL's TEXT and the answer's protobuf string both require.
    rec.reason = ValidUtf8(reason);
    spdlog::warn("dicom: series {} ({} instances from {}) not queued: {}", series_uid,
                 instances.size(), last.calling_ae, rec.reason);
    if (auto st = store_->PutDicomSeries(rec, {}); !st.ok()) {
      spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
    }
  };
  constexpr auto kIncomplete = v1::ReceivedSeries::INCOMPLETE;
  constexpr auto kNotQueued = v1::ReceivedSeries::NOT_QUEUED;
  if (route == nullptr) return not_queued(kNotQueued, "no route for its AE titles any more");
  // An aborted association may have cut a series short anywhere, also after a contiguous run
  // of slices that the geometry check cannot tell from a whole series: wait for more.
  if (aborted >= newest) {
    return not_queued(kIncomplete,
                      absl::StrCat("the association that sent it was aborted after ",
                                   instances.size(), " instances; waiting for the rest"));
  }
  std::vector<fs::path> files;
  v1::CreateVolumeRequest vreq;
  std::vector<std::string> uids;
  for (const auto& i : instances) {
    auto path = blobs_->LocalPath(i.sha256);
    if (!path.ok())
      return not_queued(
          kNotQueued, absl::StrCat("instance ", i.sop_instance_uid, ": ", path.status().message()));
    files.push_back(*path);
    uids.push_back(i.sop_instance_uid);
    auto* f = vreq.mutable_volume()->add_files();
    f->set_path(absl::StrCat(i.sop_instance_uid, ".dcm"));
    f->set_blob(absl::StrCat("blobs/", i.sha256));
  }
  if (auto st = CheckSeriesComplete(files); !st.ok()) {
    return not_queued(kIncomplete, absl::StrCat("incomplete: ", st.message()));
  }
  const std::string request_id = absl::StrCat("dicom-", key);
  vreq.set_request_id(request_id);
  vreq.mutable_volume()->set_display_name(absl::StrCat("DICOM series ", series_uid));
  v1::ErrorDetail detail;
  // Created by the sender's principal, so that a submitter token of that name sees them and
  // readers and admins see them as any other.
  auto volume = catalog_->Create(vreq, owner, &detail);
  if (!volume.ok()) {
    return not_queued(kNotQueued, absl::StrCat("volume: ", volume.status().message()));
  }
  // The request id is the receiver's (CreateVolume and CreateJob refuse the prefix to callers),
  // but a store from before that rule may hold another principal's: never reuse it.
  if (volume->creator() != owner) {
    spdlog::error("dicom: series {} from {}: request id {} names {}, created by '{}', not {}",
                  series_uid, last.calling_ae, request_id, volume->name(), volume->creator(),
                  owner);
    return not_queued(kNotQueued, absl::StrCat("request id ", request_id, " is held by ",
                                               volume->name(), " of another creator"));
  }
  v1::JobSpec spec = route->spec;
  spec.set_volume(volume->name());
  auto normalized = NormalizeJobSpec(spec);
  if (!normalized.ok()) {
    return not_queued(kNotQueued, absl::StrCat("spec: ", normalized.status().message()));
  }
  bool created = false;
  const std::string id = NewId();
  auto job = store_->CreateJob(id, *normalized, request_id, options_.max_queued, owner, &created);
  if (!created) data_dir_->RemoveJob(id);
  if (options_.audit)
    options_.audit->RecordSystem(owner, "DicomCreateJob", job.ok() ? job->name() : "", job.status(),
                                 rec.association_id);
  if (!job.ok()) return not_queued(kNotQueued, absl::StrCat("job: ", job.status().ToString()));
  if (job->creator() != owner) {
    spdlog::error("dicom: series {} from {}: request id {} names {}, created by '{}', not {}",
                  series_uid, last.calling_ae, request_id, job->name(), job->creator(), owner);
    return not_queued(kNotQueued, absl::StrCat("request id ", request_id, " is held by ",
                                               job->name(), " of another creator"));
  }
  // Complete and queued (or the job of the same set reused): FollowReceives advances it with
  // its job and sends the results to this receive's route.
  rec.state = v1::ReceivedSeries::QUEUED;
  rec.job = job->name();
  rec.reason.clear();
  rec.results_pending = true;
  if (!created) {
    spdlog::info(
        "dicom: series {} re-sent by {} ({} instances): same set as {}, no new job; its results "
        "go to route {} too",
        series_uid, last.calling_ae, instances.size(), job->name(), route->name);
  } else {
    spdlog::info(
        "job {} QUEUED from DICOM series {} ({} instances from {}, newest by association {}, "
        "route {})",
        id, series_uid, instances.size(), last.calling_ae, rec.association_id, route->name);
  }
  if (auto st = store_->PutDicomSeries(rec, uids); !st.ok()) {
    spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
    return;
  }
  CloseEarlierReceives(store_, last.calling_ae, series_uid, rec.receive_key,
                       v1::ReceivedSeries::COMPLETE, job->name(),
                       absl::StrCat("completed by the receive of ", FormatMs(newest)));
  if (created) pool_->Notify();
}

void DicomReceiver::FollowReceives() {
  auto pending = store_->ListDicomSeries(/*pending_only=*/true, 100);
  if (!pending.ok()) {
    spdlog::error("dicom: {}", pending.status().ToString());
    return;
  }
  const int64_t now = WallMs();
  for (DicomSeriesRecord rec : *pending) {
    if (stop_) return;
    const DicomSeriesRecord before = rec;
    auto id = ParseName(rec.job, "jobs", "job");
    if (!id.ok()) {
      rec.results_pending = false;  // nothing to follow
    } else if (auto job = store_->GetJob(*id); !job.ok()) {
      if (job.status().code() != absl::StatusCode::kNotFound) continue;  // retried next period
      rec.state = v1::ReceivedSeries::FAILED;
      rec.reason = absl::StrCat(rec.job, " was deleted before it finished");
      rec.results_pending = false;
    } else if (job->state() == v1::QUEUED || job->state() == v1::RUNNING) {
      rec.state =
          job->state() == v1::QUEUED ? v1::ReceivedSeries::QUEUED : v1::ReceivedSeries::RUNNING;
    } else if (job->state() != v1::SUCCEEDED) {
      rec.state = v1::ReceivedSeries::FAILED;
      rec.reason =
          absl::StrCat("job ", v1::JobState_Name(job->state()), ": ", job->error().message());
      rec.send_status = "nothing sent: the job did not succeed";
      rec.results_pending = false;
    } else {
      rec.state = v1::ReceivedSeries::SUCCEEDED;
      const DicomRoute* route = options_.routes.Find(rec.route);
      std::vector<fs::path> files;
      for (const auto& a : job->artifacts()) {
        const std::string& n = a.file_name();
        if (n.size() > 4 && n.compare(n.size() - 4, 4, ".dcm") == 0) {
          files.push_back(data_dir_->ArtifactsDir(*id) / n);
        }
      }
      if (route == nullptr || !route->destination.configured()) {
        rec.send_status = absl::StrCat("nothing sent: route '", rec.route, "' has no destination");
        rec.results_pending = false;
      } else if (files.empty()) {
        rec.send_status = "nothing sent: the job has no DICOM artifact";
        rec.results_pending = false;
      } else if (next_send_ms_.count(rec.receive_key) == 0 ||
                 now >= next_send_ms_[rec.receive_key]) {
        DicomDestination dest = route->destination;
        dest.calling_aet = options_.aet;
        const auto t0 = std::chrono::steady_clock::now();
        auto sent = SendDicomFiles(dest, files);
        if (options_.audit)
          options_.audit->RecordSystem(job->creator(), "DicomSendResults", rec.job, sent.status(),
                                       rec.association_id);
        const double secs =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (sent.ok()) {
          rec.state = v1::ReceivedSeries::SENT;
          rec.send_status = absl::StrCat("sent: ", *sent);
          rec.results_pending = false;
          spdlog::info("dicom: results of {} {} (route {}) in {:.3f} s", rec.job, *sent, rec.route,
                       secs);
        } else {
          const int attempts = ++send_attempts_[rec.receive_key];
          rec.send_status =
              absl::StrCat("attempt ", attempts, " failed: ", sent.status().ToString());
          spdlog::warn("dicom: results of {} (route {}): {}", rec.job, rec.route, rec.send_status);
          if (attempts < 3) {
            next_send_ms_[rec.receive_key] = now + 5000;
          } else {
            rec.state = v1::ReceivedSeries::SEND_FAILED;
            rec.results_pending = false;
          }
        }
      }
    }
    if (!rec.results_pending) {
      send_attempts_.erase(rec.receive_key);
      next_send_ms_.erase(rec.receive_key);
    }
    if (rec.state == before.state && rec.results_pending == before.results_pending &&
        rec.send_status == before.send_status && rec.reason == before.reason) {
      continue;  // nothing new: no write every period
    }
    rec.update_ms = now;
    if (auto st = store_->PutDicomSeries(rec, {}); !st.ok()) {
      spdlog::error("dicom: recording the outcome of {}: {}", rec.job, st.ToString());
    }
  }
}

std::string DicomOwner(const std::string& calling_ae) { return absl::StrCat("dicom:", calling_ae); }

absl::Status RefuseReceiverRequestId(const std::string& request_id) {
  if (!absl::StartsWith(request_id, "dicom-")) return absl::OkStatus();
  // Otherwise a submitter who computes a series' id before it arrives has the receiver reuse
  // its job and send that job's results as the sender's.
  return absl::InvalidArgumentError(absl::StrCat(
      "request_id: '", request_id, "': the prefix 'dicom-' is reserved for the DICOM receiver"));
}

absl::StatusOr<RemovedSeries> DeleteReceivedSeries(
    JobStore* store, BlobStore* blobs, const std::string& series_uid, const std::string& calling_ae,
    const std::string& deleted_by,
    const std::function<absl::Status(const std::string& owner)>& may_delete) {
  if (!IsDicomUid(series_uid)) {
    return absl::InvalidArgumentError(
        absl::StrCat("series_instance_uid: '", absl::CHexEscape(series_uid),
                     "' is not a DICOM UID (digits and dots, at most 64 characters)"));
  }
  if (!calling_ae.empty() && !IsAeTitle(calling_ae)) {
    return absl::InvalidArgumentError(absl::StrCat("calling_ae: '", absl::CHexEscape(calling_ae),
                                                   "' is not an AE title (printable ASCII, 1-16 "
                                                   "characters)"));
  }
  auto instances = store->ListDicomInstances();
  if (!instances.ok()) return instances.status();
  std::set<std::string> senders;
  for (const auto& i : *instances) {
    if (i.series_instance_uid == series_uid && (calling_ae.empty() || i.calling_ae == calling_ae)) {
      senders.insert(i.calling_ae);
    }
  }
  if (senders.empty()) {
    return absl::NotFoundError(
        absl::StrCat("no instance of series ", series_uid,
                     calling_ae.empty() ? "" : absl::StrCat(" from ", calling_ae), " waits"));
  }
  RemovedSeries total;
  absl::Status refused;
  int allowed = 0;
  for (const auto& sender : senders) {
    if (absl::Status may = may_delete(DicomOwner(sender)); !may.ok()) {
      refused = may;
      continue;
    }
    ++allowed;
    auto removed = RemoveWaiting(store, blobs, sender, series_uid, v1::ReceivedSeries::DELETED,
                                 absl::StrCat("deleted by ", deleted_by));
    if (!removed.ok()) return removed.status();
    total.instances += removed->instances;
    total.freed_bytes += removed->freed_bytes;
  }
  if (allowed == 0) return refused;
  return total;
}

namespace {

v1::ReceivedSeries ToProto(const DicomSeriesRecord& r) {
  v1::ReceivedSeries out;
  out.set_series_instance_uid(r.series_instance_uid);
  out.set_calling_ae(r.calling_ae);
  out.set_called_ae(r.called_ae);
  out.set_instance_count(r.instance_count);
  // Rows written before the state column: derived from what they hold.
  out.set_state(r.state != v1::ReceivedSeries::STATE_UNSPECIFIED ? r.state
                : r.job.empty()                                  ? v1::ReceivedSeries::NOT_QUEUED
                                                                 : v1::ReceivedSeries::QUEUED);
  out.set_job(r.job);
  out.set_reason(ValidUtf8(r.reason));  // also rows stored before reasons were made valid
  out.set_route(r.route);
  out.set_owner(r.calling_ae.empty() ? "" : DicomOwner(r.calling_ae));
  *out.mutable_first_receive_time() = TimeUtil::MillisecondsToTimestamp(r.first_received_ms);
  *out.mutable_last_receive_time() = TimeUtil::MillisecondsToTimestamp(r.last_received_ms);
  out.set_send_status(ValidUtf8(r.send_status));
  out.set_association_id(r.association_id);
  return out;
}

}  // namespace

absl::StatusOr<ReceivedSeriesPage> ListReceivedSeries(JobStore* store, const std::string& owner,
                                                      int page_size,
                                                      const std::string& page_token) {
  size_t offset = 0;
  if (!page_token.empty() &&
      (page_token[0] != 'r' || !absl::SimpleAtoi(page_token.substr(1), &offset))) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_token '", page_token, "' is not a token this server returned"));
  }
  const size_t size = page_size <= 0 ? 50 : std::min(page_size, 1000);
  auto instances = store->ListDicomInstances();
  if (!instances.ok()) return instances.status();
  auto rows = store->ListDicomSeries(/*pending_only=*/false, 1000);
  if (!rows.ok()) return rows.status();
  std::set<std::string> recorded;
  for (const auto& r : *rows) recorded.insert(r.receive_key);

  // Each sender's waiting instances not checked as they are now: a RECEIVING entry (their
  // earlier checks, if any, are rows of their own).
  std::map<std::pair<std::string, std::string>, std::vector<const DicomInstanceRecord*>> waiting;
  for (const auto& i : *instances) waiting[{i.calling_ae, i.series_instance_uid}].push_back(&i);
  std::vector<v1::ReceivedSeries> all;
  for (const auto& [sender_series, list] : waiting) {
    std::vector<std::string> sops;
    int64_t first = INT64_MAX, last = 0;
    for (const auto* i : list) {
      sops.push_back(i->sop_instance_uid);
      first = std::min(first, i->received_ms);
      last = std::max(last, i->received_ms);
    }
    if (recorded.count(ReceiveKey(InstanceSetKey(sender_series.first, sops), last)) > 0) continue;
    DicomSeriesRecord r;
    r.state = v1::ReceivedSeries::RECEIVING;
    r.first_received_ms = first;
    r.last_received_ms = last;
    r.series_instance_uid = sender_series.second;
    r.calling_ae = sender_series.first;
    r.called_ae = list.back()->called_ae;
    r.association_id = list.back()->association_id;
    r.instance_count = static_cast<int>(list.size());
    all.push_back(ToProto(r));
  }
  for (const auto& r : *rows) all.push_back(ToProto(r));
  std::stable_sort(all.begin(), all.end(), [](const auto& a, const auto& b) {
    return TimeUtil::TimestampToMilliseconds(a.last_receive_time()) >
           TimeUtil::TimestampToMilliseconds(b.last_receive_time());
  });
  if (!owner.empty()) {
    std::erase_if(all, [&](const v1::ReceivedSeries& r) { return r.owner() != owner; });
  }
  // A token past the end (the list shrank, or it was made up) is an empty last page; compared
  // without offset + size, which a made-up offset near SIZE_MAX wraps around.
  ReceivedSeriesPage page;
  if (offset >= all.size()) return page;
  const size_t end = all.size() - offset > size ? offset + size : all.size();
  for (size_t k = offset; k < end; ++k) page.series.push_back(std::move(all[k]));
  if (end < all.size()) page.next_page_token = absl::StrCat("r", end);
  return page;
}

}  // namespace decima::server
