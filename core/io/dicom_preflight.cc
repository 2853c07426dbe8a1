// Element-tree walk of DICOM Part 5 §7 (data elements), §7.5 (sequences and items) and §A.4
// (encapsulated pixel data). Values are skipped, never read, so the walk costs one pass over the
// headers and allocates nothing.
#include "core/io/dicom_preflight.h"

#include <cstdint>
#include <cstring>
#include <optional>
#include <string>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace decima::dicom_internal {
namespace {

constexpr uint32_t kUndefinedLength = 0xFFFFFFFFu;
constexpr uint16_t kItemGroup = 0xFFFE;
constexpr uint16_t kItem = 0xE000;
constexpr uint16_t kItemDelimitation = 0xE00D;
constexpr uint16_t kSequenceDelimitation = 0xE0DD;

// VRs of Part 5 Table 7.1-1; the first group uses a 2-byte reserved field and a 4-byte length.
constexpr const char* kLongVrs[] = {"OB", "OD", "OF", "OL", "OV", "OW", "SQ",
                                    "SV", "UC", "UN", "UR", "UT", "UV"};
constexpr const char* kShortVrs[] = {"AE", "AS", "AT", "CS", "DA", "DS", "DT",
                                     "FD", "FL", "IS", "LO", "LT", "PN", "SH",
                                     "SL", "SS", "ST", "TM", "UI", "UL", "US"};

bool VrIn(const char* vr, const auto& list) {
  for (const char* v : list) {
    if (vr[0] == v[0] && vr[1] == v[1]) return true;
  }
  return false;
}

class Walker {
 public:
  Walker(absl::string_view bytes, bool big_endian) : bytes_(bytes), big_endian_(big_endian) {}

  // Walks data set elements from `pos` up to `end`. A `delimited` data set (an undefined-length
  // item) must end with an item delimitation tag, which is consumed.
  absl::Status DataSet(size_t& pos, size_t end, int depth, bool delimited, bool explicit_vr) {
    while (pos < end) {
      if (end - pos < 8) return Error(pos, "element header is truncated");
      const uint16_t group = U16(pos), element = U16(pos + 2);
      if (group == kItemGroup) {
        if (delimited && element == kItemDelimitation) {
          pos += 8;
          return absl::OkStatus();
        }
        return Error(pos, absl::StrFormat("unexpected item tag (%04X,%04X)", group, element));
      }
      char vr[2] = {'?', '?'};
      uint32_t length;
      size_t header;
      if (explicit_vr) {
        vr[0] = bytes_[pos + 4];
        vr[1] = bytes_[pos + 5];
        if (VrIn(vr, kLongVrs)) {
          if (end - pos < 12) return Error(pos, "element header is truncated");
          length = U32(pos + 8);
          header = 12;
        } else if (VrIn(vr, kShortVrs)) {
          length = U16(pos + 6);
          header = 8;
        } else {
          return Error(pos,
                       absl::StrFormat("element (%04X,%04X) has an invalid VR", group, element));
        }
      } else {
        length = U32(pos + 4);
        header = 8;
      }
      const size_t start = pos;
      pos += header;
      const bool is_sq = vr[0] == 'S' && vr[1] == 'Q';
      const bool is_un = vr[0] == 'U' && vr[1] == 'N';
      if (length == kUndefinedLength) {
        absl::Status s;
        if (depth == 0 && group == 0x7FE0 && element == 0x0010) {
          s = Fragments(pos, end);
        } else if (!explicit_vr || is_sq || is_un) {
          // CP-246: an undefined-length UN holds an implicit VR little endian sequence.
          s = Sequence(pos, end, depth + 1, /*delimited=*/true, explicit_vr && !is_un);
        } else {
          s = Error(start,
                    absl::StrFormat("element (%04X,%04X) has an undefined length", group, element));
        }
        if (!s.ok()) return s;
        continue;
      }
      if (length > end - pos) {
        return Error(start, absl::StrFormat("element (%04X,%04X) claims %u bytes but %u remain "
                                            "(truncated or corrupt file)",
                                            group, element, length, end - pos));
      }
      if (explicit_vr && is_sq) {
        // GDCM parses explicit defined-length sequences eagerly, so they are walked too.
        size_t p = pos;
        absl::Status s = Sequence(p, pos + length, depth + 1, /*delimited=*/false, true);
        if (!s.ok()) return s;
      }
      pos += length;
    }
    if (delimited) return Error(pos, "item is not closed by a delimiter (truncated file)");
    return absl::OkStatus();
  }

 private:
  absl::Status Sequence(size_t& pos, size_t end, int depth, bool delimited, bool explicit_vr) {
    if (depth > kMaxSequenceDepth) {
      return Error(pos, absl::StrCat("sequences nested deeper than ", kMaxSequenceDepth));
    }
    while (pos < end) {
      if (end - pos < 8) return Error(pos, "item header is truncated");
      const uint16_t group = U16(pos), element = U16(pos + 2);
      const uint32_t length = U32(pos + 4);
      if (group == kItemGroup && element == kSequenceDelimitation) {
        pos += 8;
        return absl::OkStatus();
      }
      if (group != kItemGroup || element != kItem) {
        return Error(pos, absl::StrFormat("expected an item tag in a sequence, found (%04X,%04X)",
                                          group, element));
      }
      pos += 8;
      if (length == kUndefinedLength) {
        absl::Status s = DataSet(pos, end, depth, /*delimited=*/true, explicit_vr);
        if (!s.ok()) return s;
      } else {
        if (length > end - pos) {
          return Error(pos - 8,
                       absl::StrFormat("item claims %u bytes but %u remain", length, end - pos));
        }
        size_t p = pos;
        absl::Status s = DataSet(p, pos + length, depth, /*delimited=*/false, explicit_vr);
        if (!s.ok()) return s;
        pos += length;
      }
    }
    if (delimited) return Error(pos, "sequence is not closed by a delimiter (truncated file)");
    return absl::OkStatus();
  }

  // Encapsulated pixel data: items of defined length (offset table, fragments), then a
  // sequence delimiter.
  absl::Status Fragments(size_t& pos, size_t end) {
    while (pos < end) {
      if (end - pos < 8) return Error(pos, "pixel data fragment header is truncated");
      const uint16_t group = U16(pos), element = U16(pos + 2);
      const uint32_t length = U32(pos + 4);
      pos += 8;
      if (group == kItemGroup && element == kSequenceDelimitation) return absl::OkStatus();
      if (group != kItemGroup || element != kItem || length == kUndefinedLength) {
        return Error(pos - 8, "invalid fragment in encapsulated pixel data");
      }
      if (length > end - pos) {
        return Error(pos - 8, absl::StrFormat("pixel data fragment claims %u bytes but %u remain "
                                              "(truncated file)",
                                              length, end - pos));
      }
      pos += length;
    }
    return Error(pos, "encapsulated pixel data is not closed by a delimiter (truncated file)");
  }

  uint16_t U16(size_t at) const {
    uint16_t v;
    std::memcpy(&v, bytes_.data() + at, 2);
    return big_endian_ ? static_cast<uint16_t>((v >> 8) | (v << 8)) : v;
  }
  uint32_t U32(size_t at) const {
    uint32_t v;
    std::memcpy(&v, bytes_.data() + at, 4);
    return big_endian_ ? __builtin_bswap32(v) : v;
  }
  static absl::Status Error(size_t at, absl::string_view what) {
    return absl::InvalidArgumentError(absl::StrCat("at byte ", at, ": ", what));
  }

  absl::string_view bytes_;
  bool big_endian_;
};

}  // namespace

absl::Status CheckDicomStructure(absl::string_view bytes) {
  if (bytes.size() < 132 || bytes.substr(128, 4) != "DICM") {
    return absl::InvalidArgumentError("no DICM marker at byte 128 (not a DICOM Part 10 file)");
  }
  // File meta information: group 0002, always explicit VR little endian.
  size_t pos = 132;
  std::string transfer_syntax;
  std::optional<uint64_t> meta_end;  // from (0002,0000) FileMetaInformationGroupLength
  while (bytes.size() - pos >= 8) {
    uint16_t group, element;
    std::memcpy(&group, bytes.data() + pos, 2);
    std::memcpy(&element, bytes.data() + pos + 2, 2);
    if (group != 0x0002) break;
    const char vr[2] = {bytes[pos + 4], bytes[pos + 5]};
    uint32_t length;
    size_t header;
    if (VrIn(vr, kLongVrs)) {
      if (bytes.size() - pos < 12) break;  // reported as truncated below
      std::memcpy(&length, bytes.data() + pos + 8, 4);
      header = 12;
    } else if (VrIn(vr, kShortVrs)) {
      uint16_t short_length;
      std::memcpy(&short_length, bytes.data() + pos + 6, 2);
      length = short_length;
      header = 8;
    } else {
      return absl::InvalidArgumentError(absl::StrFormat(
          "at byte %u: file meta element (0002,%04X) has an invalid VR", pos, element));
    }
    if (length == kUndefinedLength || length > bytes.size() - pos - header) {
      return absl::InvalidArgumentError(
          absl::StrFormat("at byte %u: file meta element (0002,%04X) is truncated", pos, element));
    }
    if (element == 0x0010) transfer_syntax = std::string(bytes.substr(pos + header, length));
    if (element == 0x0000 && length == 4) {
      uint32_t group_length;
      std::memcpy(&group_length, bytes.data() + pos + header, 4);
      meta_end = pos + header + 4 + uint64_t{group_length};  // counts the bytes after itself
    }
    pos += header + length;
  }
  // GDCM reads the meta group up to the end its group length announces, past the end of the
  // file if need be (and then asserts), so the announced end must be where the elements end.
  if (meta_end && *meta_end != pos) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "file meta information group length ends at byte %u but its elements end at byte %u "
        "(truncated or corrupt file)",
        *meta_end, pos));
  }
  // (GDCM also asserts on a file that ends right after its meta information.)
  if (pos >= bytes.size()) {
    return absl::InvalidArgumentError("file ends after the file meta information (no data set)");
  }
  while (!transfer_syntax.empty() &&
         (transfer_syntax.back() == '\0' || transfer_syntax.back() == ' ')) {
    transfer_syntax.pop_back();
  }
  if (transfer_syntax.empty()) {
    return absl::InvalidArgumentError("file meta information has no TransferSyntaxUID (0002,0010)");
  }
  if (transfer_syntax == "1.2.840.10008.1.2.1.99") {
    return absl::InvalidArgumentError(
        "transfer syntax Deflated Explicit VR Little Endian is not supported");
  }
  const bool implicit_vr = transfer_syntax == "1.2.840.10008.1.2";
  const bool big_endian = transfer_syntax == "1.2.840.10008.1.2.2";
  Walker walker(bytes, big_endian);
  return walker.DataSet(pos, bytes.size(), 0, /*delimited=*/false, !implicit_vr);
}

}  // namespace decima::dicom_internal
