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

namespace {

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

}  // namespace

// A UID as PS3.5 9.1 defines it: digits and dots, at most 64 characters. What the receiver
// keeps of an instance goes into ListReceivedSeries' answers (protobuf strings).
bool IsDicomUid(const std::string& uid) {
  return !uid.empty() && uid.size() <= 64 &&
         uid.find_first_not_of("0123456789.") == std::string::npos;
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
std::string SmallString(DcmItem& d, const DcmTagKey& tag, bool all_values) {
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

absl::StatusOr<InstanceHeader> ReadUids(const fs::path& file) {
  DcmFileFormat ff;
  if (auto st = LoadBoundedHeader(file, &ff); !st.ok()) return st;
  InstanceHeader h{SmallString(*ff.getDataset(), DCM_SeriesInstanceUID),
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

}  // namespace decima::server
