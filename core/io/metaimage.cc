// MetaImage (.mha / .mhd) reader and writer, following the MetaIO key set that ITK writes.
//
// TransformMatrix convention (checked against ITK's MetaImageIO, which calls
// SetDirection(axis, {m[axis*N], ..., m[axis*N + N-1]})): the nine numbers are written axis by
// axis, so direction column c (the LPS unit vector of image axis c) is m[3c .. 3c+2], i.e.
// direction(r, c) = m[c * 3 + r]. MetaImage coordinates are LPS, no conversion.
#include <charconv>
#include <cmath>
#include <optional>

#include <map>
#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "core/common/atomic_file.h"
#include "core/common/status.h"
#include "core/io/io_util.h"
#include "core/io/volume_io.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;
using internal::Invalid;
using internal::Unsupported;

// A header longer than this is not a MetaImage header (ITK's are < 1 KiB).
constexpr size_t kMaxMetaHeaderBytes = 1 << 16;

struct ElementTypeName {
  const char* name;
  VoxelType type;
};
constexpr ElementTypeName kElementTypes[] = {
    {"MET_UCHAR", VoxelType::kUInt8},   {"MET_CHAR", VoxelType::kInt8},
    {"MET_USHORT", VoxelType::kUInt16}, {"MET_SHORT", VoxelType::kInt16},
    {"MET_UINT", VoxelType::kUInt32},   {"MET_INT", VoxelType::kInt32},
    {"MET_FLOAT", VoxelType::kFloat32}, {"MET_DOUBLE", VoxelType::kFloat64},
};

// Header fields by lower-cased key, plus where the data starts for ElementDataFile = LOCAL.
struct MetaHeader {
  std::map<std::string, std::string> fields;
  int64_t local_data_offset = 0;
};

absl::StatusOr<MetaHeader> ParseMetaHeader(const fs::path& path) {
  DECIMA_ASSIGN_OR_RETURN(const std::string head,
                          internal::ReadFileHead(path, kMaxMetaHeaderBytes));
  if (head.empty()) return Invalid(path, "empty file, expected a MetaImage header");
  MetaHeader h;
  size_t pos = 0;
  while (true) {
    const size_t eol = head.find('\n', pos);
    if (eol == std::string::npos) {
      if (head.size() >= kMaxMetaHeaderBytes) {
        return Invalid(path, "no ElementDataFile line within the first ", kMaxMetaHeaderBytes,
                       " bytes: not a MetaImage header");
      }
    }
    const size_t end = eol == std::string::npos ? head.size() : eol;
    absl::string_view line(head.data() + pos, end - pos);
    line = absl::StripAsciiWhitespace(line);
    pos = eol == std::string::npos ? head.size() : eol + 1;
    if (!line.empty()) {
      const size_t eq = line.find('=');
      if (eq == absl::string_view::npos) {
        return Invalid(path, "header line '", line.substr(0, 60),
                       "' is not 'Key = Value': not a MetaImage header");
      }
      const std::string key = absl::AsciiStrToLower(absl::StripAsciiWhitespace(line.substr(0, eq)));
      h.fields[key] = std::string(absl::StripAsciiWhitespace(line.substr(eq + 1)));
      // ElementDataFile is always the last header field; LOCAL data starts on the next line.
      if (key == "elementdatafile") {
        h.local_data_offset = static_cast<int64_t>(pos);
        return h;
      }
    }
    if (pos >= head.size()) break;
  }
  return Invalid(path, "header has no ElementDataFile field");
}

const std::string* Field(const MetaHeader& h, std::initializer_list<const char*> keys) {
  for (const char* k : keys) {
    auto it = h.fields.find(k);
    if (it != h.fields.end()) return &it->second;
  }
  return nullptr;
}

absl::StatusOr<std::vector<double>> Numbers(const fs::path& path, absl::string_view key,
                                            const std::string& value, size_t count) {
  std::vector<double> out;
  for (absl::string_view tok : absl::StrSplit(value, absl::ByAnyChar(" \t"), absl::SkipEmpty())) {
    double d;
    if (!absl::SimpleAtod(tok, &d)) {
      return Invalid(path, key, " has '", tok, "', expected a number");
    }
    out.push_back(d);
  }
  if (out.size() != count) {
    return Invalid(path, key, " has ", out.size(), " values, expected ", count);
  }
  return out;
}

absl::StatusOr<bool> Boolean(const fs::path& path, absl::string_view key, const std::string* v,
                             bool fallback) {
  if (v == nullptr) return fallback;
  const std::string s = absl::AsciiStrToLower(*v);
  if (s == "true" || s == "1") return true;
  if (s == "false" || s == "0") return false;
  return Invalid(path, key, " = '", *v, "', expected True or False");
}

std::string Num(double d) {
  char buf[32];
  auto r = std::to_chars(buf, buf + sizeof(buf), d);  // shortest exact round-trip form
  return std::string(buf, r.ptr);
}

}  // namespace

namespace internal {

absl::StatusOr<Volume> ReadMetaImage(const fs::path& path, ReadMode mode) {
  DECIMA_ASSIGN_OR_RETURN(const MetaHeader h, ParseMetaHeader(path));
  if (const std::string* ot = Field(h, {"objecttype"}); ot != nullptr && *ot != "Image") {
    return Unsupported(path, "ObjectType = ", *ot, ", expected Image");
  }
  const std::string* ndims_s = Field(h, {"ndims"});
  if (ndims_s == nullptr) return Invalid(path, "header has no NDims field");
  int ndims = 0;
  if (!absl::SimpleAtoi(*ndims_s, &ndims)) {
    return Invalid(path, "NDims = '", *ndims_s, "', expected an integer");
  }
  if (ndims == 2) return Invalid(path, "2D image: Decima needs a 3D volume (NDims = 2)");
  if (ndims != 3) return Unsupported(path, "NDims = ", ndims, ", only 3D volumes are supported");

  const std::string* dim_s = Field(h, {"dimsize"});
  if (dim_s == nullptr) return Invalid(path, "header has no DimSize field");
  DECIMA_ASSIGN_OR_RETURN(const auto dimv, Numbers(path, "DimSize", *dim_s, 3));
  std::array<int64_t, 3> dims{};
  for (int c = 0; c < 3; ++c) {
    if (!(dimv[c] >= -1e15 && dimv[c] <= 1e15) || dimv[c] != std::floor(dimv[c])) {
      return Invalid(path, "DimSize[", c, "] = ", dimv[c], ", expected a whole number");
    }
    dims[c] = static_cast<int64_t>(dimv[c]);
  }
  DECIMA_RETURN_IF_ERROR(internal::CheckDims(path, dims, "DimSize"));

  if (const std::string* ch = Field(h, {"elementnumberofchannels"}); ch != nullptr && *ch != "1") {
    return Unsupported(path, "ElementNumberOfChannels = ", *ch,
                       ": only scalar volumes (1 channel) are supported");
  }
  DECIMA_ASSIGN_OR_RETURN(const bool binary,
                          Boolean(path, "BinaryData", Field(h, {"binarydata"}), true));
  if (!binary) return Unsupported(path, "BinaryData = False (ASCII data) is not supported");

  const std::string* et = Field(h, {"elementtype"});
  if (et == nullptr) return Invalid(path, "header has no ElementType field");
  std::optional<VoxelType> type;
  for (const auto& e : kElementTypes) {
    if (*et == e.name) type = e.type;
  }
  if (!type) {
    return Invalid(path, "unknown or unsupported ElementType '", *et,
                   "', expected MET_UCHAR, MET_CHAR, MET_USHORT, MET_SHORT, MET_UINT, MET_INT, "
                   "MET_FLOAT or MET_DOUBLE");
  }

  Volume v;
  v.dims = dims;
  v.type = *type;
  if (const std::string* s = Field(h, {"elementspacing", "elementsize"})) {
    DECIMA_ASSIGN_OR_RETURN(const auto sp, Numbers(path, "ElementSpacing", *s, 3));
    for (int c = 0; c < 3; ++c) {
      if (!std::isfinite(sp[c]) || sp[c] <= 0) {
        return Invalid(path, "ElementSpacing[", c, "] = ", sp[c], ", expected a finite value > 0");
      }
      v.spacing[c] = sp[c];
    }
  }
  if (const std::string* s = Field(h, {"offset", "origin", "position"})) {
    DECIMA_ASSIGN_OR_RETURN(const auto o, Numbers(path, "Offset", *s, 3));
    v.origin = Eigen::Vector3d(o[0], o[1], o[2]);
  }
  if (const std::string* s = Field(h, {"transformmatrix", "rotation", "orientation"})) {
    DECIMA_ASSIGN_OR_RETURN(const auto m, Numbers(path, "TransformMatrix", *s, 9));
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) v.direction(r, c) = m[c * 3 + r];
      const double n = v.direction.col(c).norm();
      if (!(n > 0) || !std::isfinite(n)) {
        return Invalid(path, "TransformMatrix axis ", c, " is zero or not finite");
      }
      v.direction.col(c) /= n;
    }
  }
  if (const std::string* mod = Field(h, {"modality"})) {
    if (*mod == "MET_MOD_CT") v.modality = "CT";
    if (*mod == "MET_MOD_MR") v.modality = "MR";
  }

  DECIMA_ASSIGN_OR_RETURN(
      const bool msb, Boolean(path, "BinaryDataByteOrderMSB",
                              Field(h, {"binarydatabyteordermsb", "elementbyteordermsb"}), false));
  DECIMA_ASSIGN_OR_RETURN(const bool compressed,
                          Boolean(path, "CompressedData", Field(h, {"compresseddata"}), false));
  int64_t header_size = 0;
  if (const std::string* s = Field(h, {"headersize"})) {
    if (!absl::SimpleAtoi(*s, &header_size) || header_size < -1) {
      return Invalid(path, "HeaderSize = '", *s, "', expected -1 or a byte count >= 0");
    }
  }

  const std::string& data_name = h.fields.at("elementdatafile");
  fs::path data_path = path;
  int64_t offset = h.local_data_offset;
  if (data_name == "LOCAL") {
    if (header_size == -1) {
      return Invalid(path, "HeaderSize = -1 with ElementDataFile = LOCAL is contradictory");
    }
  } else {
    if (data_name.rfind("LIST", 0) == 0 || data_name.find('%') != std::string::npos) {
      return Unsupported(path, "ElementDataFile = '", data_name,
                         "': slice lists and file patterns are not supported");
    }
    DECIMA_ASSIGN_OR_RETURN(data_path,
                            internal::ResolveDataFile(path, data_name, "ElementDataFile"));
    offset = header_size;
  }
  const int64_t nbytes = internal::DataBytes(dims, v.type);
  if (offset == -1) {
    if (compressed) {
      return Invalid(path, "HeaderSize = -1 (data at the end) is not possible for compressed data");
    }
    DECIMA_ASSIGN_OR_RETURN(const int64_t size, internal::RegularFileSize(data_path));
    if (size < nbytes) {
      return Invalid(data_path, "truncated: voxel data needs ", nbytes, " bytes, the file has ",
                     size);
    }
    offset = size - nbytes;
  }
  if (mode == ReadMode::kHeaderOnly) {
    DECIMA_RETURN_IF_ERROR(
        internal::CheckVoxelBytes(data_path, offset, compressed, 0, nbytes, "voxel data"));
    return v;
  }
  DECIMA_ASSIGN_OR_RETURN(
      v.bytes, internal::ReadVoxelBytes(data_path, offset, compressed, 0, nbytes, "voxel data"));
  if (msb) {
    internal::SwapBytes(v.bytes.data(), static_cast<size_t>(v.voxel_count()),
                        VoxelTypeSize(v.type));
  }
  DECIMA_RETURN_IF_ERROR(Validate(v, path.string()));
  return v;
}

}  // namespace internal

absl::StatusOr<Volume> ReadMetaImage(const fs::path& path) {
  return internal::ReadMetaImage(path, internal::ReadMode::kVolume);
}

absl::Status WriteMetaImage(const Volume& volume, const fs::path& path,
                            const MetaImageWriteOptions& options) {
  DECIMA_RETURN_IF_ERROR(Validate(volume, path.string()));
  const std::string lower = internal::LowerName(path);
  const bool mha = internal::EndsWith(lower, ".mha");
  if (!mha && !internal::EndsWith(lower, ".mhd")) {
    return Invalid(path, "MetaImage output needs the extension .mha or .mhd");
  }
  std::vector<uint8_t> packed;
  const uint8_t* data = volume.bytes.data();
  size_t data_size = volume.bytes.size();
  if (options.compress) {
    DECIMA_ASSIGN_OR_RETURN(packed, internal::Deflate({{data, data_size}}, /*gzip=*/false,
                                                      options.compression_level, path));
    data = packed.data();
    data_size = packed.size();
  }
  const char* element_type = "";
  for (const auto& e : kElementTypes) {
    if (e.type == volume.type) element_type = e.name;
  }
  const std::string stem = path.filename().string().substr(0, path.filename().string().size() - 4);
  const std::string data_name = mha ? "LOCAL" : stem + (options.compress ? ".zraw" : ".raw");

  std::string header = "ObjectType = Image\nNDims = 3\nBinaryData = True\n";
  header += "BinaryDataByteOrderMSB = False\n";
  header += absl::StrCat("CompressedData = ", options.compress ? "True" : "False", "\n");
  if (options.compress) header += absl::StrCat("CompressedDataSize = ", data_size, "\n");
  header += "TransformMatrix =";
  for (int c = 0; c < 3; ++c) {
    for (int r = 0; r < 3; ++r) absl::StrAppend(&header, " ", Num(volume.direction(r, c)));
  }
  header += absl::StrCat("\nOffset = ", Num(volume.origin[0]), " ", Num(volume.origin[1]), " ",
                         Num(volume.origin[2]), "\nCenterOfRotation = 0 0 0\n");
  header += absl::StrCat("ElementSpacing = ", Num(volume.spacing[0]), " ", Num(volume.spacing[1]),
                         " ", Num(volume.spacing[2]), "\n");
  header +=
      absl::StrCat("DimSize = ", volume.dims[0], " ", volume.dims[1], " ", volume.dims[2], "\n");
  if (volume.modality == "CT") header += "Modality = MET_MOD_CT\n";
  if (volume.modality == "MR") header += "Modality = MET_MOD_MR\n";
  header += absl::StrCat("ElementType = ", element_type, "\nElementDataFile = ", data_name, "\n");

  AtomicFile out;
  DECIMA_RETURN_IF_ERROR(out.Open(path));
  DECIMA_RETURN_IF_ERROR(out.Write(header.data(), header.size()));
  if (mha) {
    DECIMA_RETURN_IF_ERROR(out.Write(data, data_size));
  } else {
    // Data first, header last: a reader never finds a header whose data is not complete.
    AtomicFile raw;
    DECIMA_RETURN_IF_ERROR(raw.Open(path.parent_path() / data_name));
    DECIMA_RETURN_IF_ERROR(raw.Write(data, data_size));
    DECIMA_RETURN_IF_ERROR(raw.Commit());
  }
  return out.Commit();
}

}  // namespace decima::io
