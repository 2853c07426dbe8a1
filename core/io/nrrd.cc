// NRRD (.nrrd attached / .nhdr detached) reader, after the NRRD0005 format definition
// (teem.sourceforge.net/nrrd/format.html): "field: value" lines up to a blank line, data after.
//
// Interpretations: "space directions" columns are the axis vectors including spacing, so
// spacing = |column| and direction = column / |column|; "scanner-xyz", "3D-right-handed" and a
// bare "space dimension: 3" are taken as LPS (DICOM scanner coordinates are LPS). A 4D file is
// accepted only if its first or last axis has size 1 (that axis is dropped).
#include <charconv>
#include <cmath>
#include <optional>

#include <map>
#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "core/common/status.h"
#include "core/io/io_util.h"
#include "core/io/volume_io.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;
using internal::Invalid;
using internal::Unsupported;

constexpr size_t kMaxNrrdHeaderBytes = 1 << 20;

struct NrrdHeader {
  std::map<std::string, std::string> fields;  // lower-cased field name -> value
  int64_t data_offset = 0;                    // end of header in the .nrrd file
  bool ended_with_blank_line = false;
};

absl::StatusOr<NrrdHeader> ParseNrrdHeader(const fs::path& path) {
  DECIMA_ASSIGN_OR_RETURN(const std::string head,
                          internal::ReadFileHead(path, kMaxNrrdHeaderBytes));
  if (head.empty()) return Invalid(path, "empty file, expected a NRRD header");
  if (head.size() < 8 || head.compare(0, 7, "NRRD000") != 0) {
    return Invalid(path, "missing the NRRD magic 'NRRD000x' on the first line");
  }
  NrrdHeader h;
  size_t pos = head.find('\n');
  if (pos == std::string::npos) return Invalid(path, "truncated: header has only a magic line");
  ++pos;
  while (pos < head.size()) {
    size_t eol = head.find('\n', pos);
    if (eol == std::string::npos) {
      if (head.size() >= kMaxNrrdHeaderBytes) {
        return Invalid(path, "header longer than ", kMaxNrrdHeaderBytes, " bytes");
      }
      eol = head.size();
    }
    absl::string_view line(head.data() + pos, eol - pos);
    pos = std::min(eol + 1, head.size());
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    if (line.empty()) {
      h.ended_with_blank_line = true;
      break;
    }
    if (line[0] == '#') continue;
    if (line.find(":=") != absl::string_view::npos) continue;  // key/value pair, not a field
    const size_t colon = line.find(": ");
    if (colon == absl::string_view::npos) {
      return Invalid(path, "header line '", line.substr(0, 60), "' is not 'field: value'");
    }
    std::string key = absl::AsciiStrToLower(line.substr(0, colon));
    h.fields[key] = std::string(absl::StripAsciiWhitespace(line.substr(colon + 2)));
  }
  h.data_offset = static_cast<int64_t>(pos);
  return h;
}

const std::string* Field(const NrrdHeader& h, std::initializer_list<const char*> keys) {
  for (const char* k : keys) {
    auto it = h.fields.find(k);
    if (it != h.fields.end()) return &it->second;
  }
  return nullptr;
}

std::vector<std::string> Tokens(const std::string& v) {
  return absl::StrSplit(v, absl::ByAnyChar(" \t"), absl::SkipEmpty());
}

absl::StatusOr<VoxelType> ParseType(const fs::path& path, const std::string& value) {
  const std::string t = absl::AsciiStrToLower(value);
  static const std::pair<const char*, VoxelType> kNames[] = {
      {"signed char", VoxelType::kInt8},
      {"int8", VoxelType::kInt8},
      {"int8_t", VoxelType::kInt8},
      {"uchar", VoxelType::kUInt8},
      {"unsigned char", VoxelType::kUInt8},
      {"uint8", VoxelType::kUInt8},
      {"uint8_t", VoxelType::kUInt8},
      {"short", VoxelType::kInt16},
      {"short int", VoxelType::kInt16},
      {"signed short", VoxelType::kInt16},
      {"signed short int", VoxelType::kInt16},
      {"int16", VoxelType::kInt16},
      {"int16_t", VoxelType::kInt16},
      {"ushort", VoxelType::kUInt16},
      {"unsigned short", VoxelType::kUInt16},
      {"unsigned short int", VoxelType::kUInt16},
      {"uint16", VoxelType::kUInt16},
      {"uint16_t", VoxelType::kUInt16},
      {"int", VoxelType::kInt32},
      {"signed int", VoxelType::kInt32},
      {"int32", VoxelType::kInt32},
      {"int32_t", VoxelType::kInt32},
      {"uint", VoxelType::kUInt32},
      {"unsigned int", VoxelType::kUInt32},
      {"uint32", VoxelType::kUInt32},
      {"uint32_t", VoxelType::kUInt32},
      {"float", VoxelType::kFloat32},
      {"double", VoxelType::kFloat64},
  };
  for (const auto& [name, type] : kNames) {
    if (t == name) return type;
  }
  if (t.find("long") != std::string::npos || t.find("64") != std::string::npos || t == "block") {
    return Unsupported(path, "type '", value, "' (64-bit integer or block) is not supported");
  }
  return Invalid(path, "unknown type '", value, "'");
}

absl::StatusOr<Eigen::Vector3d> ParseVector(const fs::path& path, absl::string_view field,
                                            absl::string_view tok) {
  if (tok.size() < 2 || tok.front() != '(' || tok.back() != ')') {
    return Invalid(path, field, " entry '", tok, "' is not a vector '(x,y,z)'");
  }
  std::vector<absl::string_view> parts = absl::StrSplit(tok.substr(1, tok.size() - 2), ',');
  if (parts.size() != 3) {
    return Invalid(path, field, " entry '", tok, "' has ", parts.size(),
                   " components, expected 3 (a 3D space)");
  }
  Eigen::Vector3d v;
  for (int i = 0; i < 3; ++i) {
    if (!absl::SimpleAtod(absl::StripAsciiWhitespace(parts[i]), &v[i]) || !std::isfinite(v[i])) {
      return Invalid(path, field, " entry '", tok, "' has a non-finite or non-numeric component");
    }
  }
  return v;
}

// "(a,b,c) (d,e,f)" may contain spaces inside the parentheses; group tokens by parentheses.
std::vector<std::string> VectorTokens(const std::string& v) {
  std::vector<std::string> out;
  std::string cur;
  int depth = 0;
  for (char ch : v) {
    if (ch == '(') ++depth;
    if (ch == ')') --depth;
    if ((ch == ' ' || ch == '\t') && depth == 0) {
      if (!cur.empty()) out.push_back(cur);
      cur.clear();
    } else if (ch != ' ' && ch != '\t') {
      cur += ch;
    }
  }
  if (!cur.empty()) out.push_back(cur);
  return out;
}

// Sign flips taking coordinates of `space` to LPS.
absl::StatusOr<Eigen::Vector3d> SpaceToLps(const fs::path& path, const std::string& space) {
  const std::string s = absl::AsciiStrToLower(space);
  if (s == "left-posterior-superior" || s == "lps") return Eigen::Vector3d(1, 1, 1);
  if (s == "right-anterior-superior" || s == "ras") return Eigen::Vector3d(-1, -1, 1);
  if (s == "left-anterior-superior" || s == "las") return Eigen::Vector3d(1, -1, 1);
  if (s == "scanner-xyz" || s == "3d-right-handed") return Eigen::Vector3d(1, 1, 1);
  return Unsupported(path, "space '", space,
                     "' is not supported (expected left-posterior-superior, "
                     "right-anterior-superior, left-anterior-superior, scanner-xyz or "
                     "3D-right-handed)");
}

template <typename T>
absl::Status ParseAscii(const fs::path& path, absl::string_view text, int64_t n, uint8_t* out) {
  const char* p = text.data();
  const char* end = text.data() + text.size();
  for (int64_t i = 0; i < n; ++i) {
    while (p < end && (absl::ascii_isspace(static_cast<unsigned char>(*p)) || *p == ',')) ++p;
    if (p == end) {
      return Invalid(path, "truncated: ascii data has ", i, " values, expected ", n);
    }
    double d = 0;
    auto r = std::from_chars(p, end, d);
    if (r.ec != std::errc()) {
      return Invalid(path, "ascii data value ", i, " is not a number");
    }
    p = r.ptr;
    T value = static_cast<T>(0);
    if constexpr (std::is_integral_v<T>) {
      if (!(d >= static_cast<double>(std::numeric_limits<T>::min()) &&
            d <= static_cast<double>(std::numeric_limits<T>::max())) ||
          d != std::floor(d)) {
        return Invalid(path, "ascii data value ", i, " = ", d, " does not fit the type");
      }
    }
    value = static_cast<T>(d);
    std::memcpy(out + i * sizeof(T), &value, sizeof(T));
  }
  while (p < end && (absl::ascii_isspace(static_cast<unsigned char>(*p)) || *p == ',')) ++p;
  if (p != end) return Invalid(path, "ascii data: more values than the header implies");
  return absl::OkStatus();
}

absl::Status ParseAsciiTyped(const fs::path& path, absl::string_view text, Volume& v) {
  const int64_t n = v.voxel_count();
  uint8_t* out = v.bytes.data();
  switch (v.type) {
    case VoxelType::kUInt8:
      return ParseAscii<uint8_t>(path, text, n, out);
    case VoxelType::kInt8:
      return ParseAscii<int8_t>(path, text, n, out);
    case VoxelType::kUInt16:
      return ParseAscii<uint16_t>(path, text, n, out);
    case VoxelType::kInt16:
      return ParseAscii<int16_t>(path, text, n, out);
    case VoxelType::kUInt32:
      return ParseAscii<uint32_t>(path, text, n, out);
    case VoxelType::kInt32:
      return ParseAscii<int32_t>(path, text, n, out);
    case VoxelType::kFloat32:
      return ParseAscii<float>(path, text, n, out);
    case VoxelType::kFloat64:
      return ParseAscii<double>(path, text, n, out);
  }
  return absl::OkStatus();
}

// Byte offset in `data_path` after skipping `lines` newline-terminated lines from `offset`.
absl::StatusOr<int64_t> SkipLines(const fs::path& data_path, int64_t offset, int64_t lines) {
  if (lines == 0) return offset;
  DECIMA_ASSIGN_OR_RETURN(
      auto in,
      internal::InputStream::Open(data_path, offset, internal::InputStream::Compression::kNone));
  for (int64_t l = 0; l < lines; ++l) {
    char ch = 0;
    do {
      DECIMA_RETURN_IF_ERROR(in.ReadExact(&ch, 1, "line skip"));
      ++offset;
    } while (ch != '\n');
  }
  return offset;
}

}  // namespace

namespace internal {

absl::StatusOr<Volume> ReadNrrd(const fs::path& path, ReadMode mode) {
  DECIMA_ASSIGN_OR_RETURN(const NrrdHeader h, ParseNrrdHeader(path));

  const std::string* dim_s = Field(h, {"dimension"});
  if (dim_s == nullptr) return Invalid(path, "header has no 'dimension' field");
  int ndim = 0;
  if (!absl::SimpleAtoi(*dim_s, &ndim) || ndim < 1) {
    return Invalid(path, "dimension = '", *dim_s, "', expected a positive integer");
  }
  if (ndim == 2) return Invalid(path, "2D image: Decima needs a 3D volume (dimension: 2)");
  if (ndim != 3 && ndim != 4) {
    return Unsupported(path, "dimension ", ndim, ": only 3D volumes are supported");
  }
  const std::string* sizes_s = Field(h, {"sizes"});
  if (sizes_s == nullptr) return Invalid(path, "header has no 'sizes' field");
  const std::vector<std::string> size_tok = Tokens(*sizes_s);
  if (static_cast<int>(size_tok.size()) != ndim) {
    return Invalid(path, "sizes has ", size_tok.size(), " values, dimension is ", ndim);
  }
  std::vector<int64_t> sizes(ndim);
  for (int a = 0; a < ndim; ++a) {
    if (!absl::SimpleAtoi(size_tok[a], &sizes[a])) {
      return Invalid(path, "sizes[", a, "] = '", size_tok[a], "', expected an integer");
    }
  }
  std::vector<std::string> kinds;
  if (const std::string* k = Field(h, {"kinds"})) {
    kinds = Tokens(*k);
    if (static_cast<int>(kinds.size()) != ndim) {
      return Invalid(path, "kinds has ", kinds.size(), " entries, dimension is ", ndim);
    }
  }
  // Which axes are the three spatial ones.
  int first = 0;
  if (ndim == 4) {
    if (sizes[0] == 1) {
      first = 1;
    } else if (sizes[3] != 1) {
      return Unsupported(path, "4D data (sizes ", *sizes_s,
                         "): only 3D scalar volumes are supported (vector or time series "
                         "data are not)");
    }
  }
  for (int c = 0; c < 3; ++c) {
    if (kinds.empty()) break;
    const std::string kind = absl::AsciiStrToLower(kinds[first + c]);
    if (kind != "domain" && kind != "space" && kind != "time" && kind != "???" && kind != "none") {
      return Unsupported(path, "kinds[", first + c, "] = '", kinds[first + c],
                         "': vector, color or list data are not supported (scalar volumes only)");
    }
  }
  const std::array<int64_t, 3> dims{sizes[first], sizes[first + 1], sizes[first + 2]};
  DECIMA_RETURN_IF_ERROR(internal::CheckDims(path, dims, "sizes"));

  const std::string* type_s = Field(h, {"type"});
  if (type_s == nullptr) return Invalid(path, "header has no 'type' field");
  DECIMA_ASSIGN_OR_RETURN(const VoxelType type, ParseType(path, *type_s));

  Volume v;
  v.dims = dims;
  v.type = type;

  // Geometry.
  Eigen::Vector3d flip(1, 1, 1);
  if (const std::string* space = Field(h, {"space"})) {
    DECIMA_ASSIGN_OR_RETURN(flip, SpaceToLps(path, *space));
  } else if (const std::string* sd = Field(h, {"space dimension"}); sd != nullptr && *sd != "3") {
    return Unsupported(path, "space dimension ", *sd, ": only 3D spaces are supported");
  }
  if (const std::string* dirs = Field(h, {"space directions"})) {
    const std::vector<std::string> tok = VectorTokens(*dirs);
    if (static_cast<int>(tok.size()) != ndim) {
      return Invalid(path, "space directions has ", tok.size(), " entries, dimension is ", ndim);
    }
    for (int c = 0; c < 3; ++c) {
      DECIMA_ASSIGN_OR_RETURN(const Eigen::Vector3d d,
                              ParseVector(path, "space directions", tok[first + c]));
      const double n = d.norm();
      if (!(n > 0)) {
        return Invalid(path, "space directions axis ", c, " is a zero vector (zero spacing)");
      }
      v.spacing[c] = n;
      v.direction.col(c) = flip.cwiseProduct(d / n);
    }
  } else {
    v.direction = flip.asDiagonal();
    if (const std::string* sp = Field(h, {"spacings"})) {
      const std::vector<std::string> tok = Tokens(*sp);
      if (static_cast<int>(tok.size()) != ndim) {
        return Invalid(path, "spacings has ", tok.size(), " entries, dimension is ", ndim);
      }
      for (int c = 0; c < 3; ++c) {
        double s = 0;
        if (!absl::SimpleAtod(tok[first + c], &s) || !std::isfinite(s) || s <= 0) {
          return Invalid(path, "spacings[", first + c, "] = '", tok[first + c],
                         "', expected a finite value > 0");
        }
        v.spacing[c] = s;
      }
    }
  }
  if (const std::string* o = Field(h, {"space origin"})) {
    DECIMA_ASSIGN_OR_RETURN(const Eigen::Vector3d origin, ParseVector(path, "space origin", *o));
    v.origin = flip.cwiseProduct(origin);
  }

  // Data location and encoding.
  const std::string* enc_s = Field(h, {"encoding"});
  if (enc_s == nullptr) return Invalid(path, "header has no 'encoding' field");
  const std::string enc = absl::AsciiStrToLower(*enc_s);
  const bool gzip = enc == "gzip" || enc == "gz";
  const bool ascii = enc == "ascii" || enc == "text" || enc == "txt";
  if (!gzip && !ascii && enc != "raw") {
    return Unsupported(path, "encoding '", *enc_s, "' is not supported (raw, gzip, ascii)");
  }
  bool msb = false;
  if (const std::string* e = Field(h, {"endian"})) {
    if (*e == "big") {
      msb = true;
    } else if (*e != "little") {
      return Invalid(path, "endian = '", *e, "', expected little or big");
    }
  } else if (VoxelTypeSize(type) > 1 && !ascii) {
    return Invalid(path, "header has no 'endian' field, required for multi-byte types");
  }
  int64_t byte_skip = 0, line_skip = 0;
  if (const std::string* s = Field(h, {"byte skip", "byteskip"})) {
    if (!absl::SimpleAtoi(*s, &byte_skip) || byte_skip < -1) {
      return Invalid(path, "byte skip = '", *s, "', expected -1 or a byte count >= 0");
    }
    if (byte_skip == -1 && enc != "raw") {
      return Invalid(path, "byte skip -1 is only allowed with raw encoding");
    }
  }
  if (const std::string* s = Field(h, {"line skip", "lineskip"})) {
    if (!absl::SimpleAtoi(*s, &line_skip) || line_skip < 0) {
      return Invalid(path, "line skip = '", *s, "', expected a line count >= 0");
    }
  }
  fs::path data_path = path;
  int64_t offset = h.data_offset;
  if (const std::string* df = Field(h, {"data file", "datafile"})) {
    if (df->rfind("LIST", 0) == 0 || df->find('%') != std::string::npos) {
      return Unsupported(path, "data file '", *df, "': file lists and patterns are not supported");
    }
    DECIMA_ASSIGN_OR_RETURN(data_path, internal::ResolveDataFile(path, *df, "data file"));
    offset = 0;
  } else if (!h.ended_with_blank_line) {
    return Invalid(path,
                   "truncated: header has no blank line before the data and no "
                   "'data file' field");
  }
  DECIMA_ASSIGN_OR_RETURN(offset, SkipLines(data_path, offset, line_skip));
  const int64_t nbytes = internal::DataBytes(dims, type);

  if (ascii) {
    DECIMA_ASSIGN_OR_RETURN(const int64_t size, internal::RegularFileSize(data_path));
    const int64_t text_bytes = size - offset;
    // Every value needs at least one character and one separator (bar the last).
    if (v.voxel_count() > text_bytes / 2 + 1) {
      return Invalid(data_path, "truncated: ", text_bytes, " bytes of ascii data cannot hold ",
                     v.voxel_count(), " values");
    }
    if (mode == ReadMode::kHeaderOnly) return v;
    DECIMA_ASSIGN_OR_RETURN(
        auto in,
        internal::InputStream::Open(data_path, offset, internal::InputStream::Compression::kNone));
    std::string text(static_cast<size_t>(text_bytes), '\0');
    DECIMA_RETURN_IF_ERROR(in.ReadExact(text.data(), text.size(), "ascii data"));
    v.bytes.assign(static_cast<size_t>(nbytes), 0);
    DECIMA_RETURN_IF_ERROR(ParseAsciiTyped(data_path, text, v));
  } else {
    if (byte_skip == -1) {
      DECIMA_ASSIGN_OR_RETURN(const int64_t size, internal::RegularFileSize(data_path));
      if (size - offset < nbytes) {
        return Invalid(data_path, "truncated: voxel data needs ", nbytes, " bytes, only ",
                       size - offset, " available");
      }
      offset = size - nbytes;
      byte_skip = 0;
    }
    if (mode == ReadMode::kHeaderOnly) {
      DECIMA_RETURN_IF_ERROR(
          internal::CheckVoxelBytes(data_path, offset, gzip, byte_skip, nbytes, "voxel data"));
      return v;
    }
    DECIMA_ASSIGN_OR_RETURN(v.bytes, internal::ReadVoxelBytes(data_path, offset, gzip, byte_skip,
                                                              nbytes, "voxel data"));
    if (msb) {
      internal::SwapBytes(v.bytes.data(), static_cast<size_t>(v.voxel_count()),
                          VoxelTypeSize(type));
    }
  }
  DECIMA_RETURN_IF_ERROR(Validate(v, path.string()));
  return v;
}

}  // namespace internal

absl::StatusOr<Volume> ReadNrrd(const fs::path& path) {
  return internal::ReadNrrd(path, internal::ReadMode::kVolume);
}

}  // namespace decima::io
