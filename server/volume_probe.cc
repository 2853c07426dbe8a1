#include "server/volume_probe.h"

#include <zlib.h>

#include <cstring>
#include <fstream>
#include <map>
#include <sstream>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "core/volume/volume.h"
#ifdef DECIMA_HAVE_IO
#include "core/io/volume_io.h"
#endif

namespace decima::server {
namespace fs = std::filesystem;
namespace {

absl::Status Bad(const std::string& file, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat(file, ": ", what));
}

// Reads up to `n` bytes from the start of a plain or gzip file (gzread passes plain files
// through unchanged).
std::string ReadPrefix(const fs::path& path, size_t n) {
  gzFile f = gzopen(path.c_str(), "rb");
  if (f == nullptr) return {};
  std::string buf(n, '\0');
  int got = gzread(f, buf.data(), static_cast<unsigned>(n));
  gzclose(f);
  buf.resize(got > 0 ? static_cast<size_t>(got) : 0);
  return buf;
}

absl::Status CheckDims(const std::string& file, const std::array<int64_t, 3>& d) {
  for (int64_t v : d) {
    if (v < 1 || v > (int64_t{1} << 20))
      return Bad(file, absl::StrCat("dimension ", v, " out of range"));
  }
  if (d[0] * d[1] * d[2] > kMaxVoxels) {
    return Bad(file, absl::StrCat(d[0] * d[1] * d[2], " voxels exceed the limit of ", kMaxVoxels));
  }
  return absl::OkStatus();
}

template <typename T>
T Get(const std::string& b, size_t off, bool swap) {
  T v;
  std::memcpy(&v, b.data() + off, sizeof(T));
  if (swap) {
    auto* p = reinterpret_cast<unsigned char*>(&v);
    for (size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(p[i], p[sizeof(T) - 1 - i]);
  }
  return v;
}

std::string NiftiType(int code) {
  switch (code) {
    case 2:
      return "uint8";
    case 4:
      return "int16";
    case 8:
      return "int32";
    case 16:
      return "float32";
    case 64:
      return "float64";
    case 256:
      return "int8";
    case 512:
      return "uint16";
    case 768:
      return "uint32";
    default:
      return "";
  }
}

absl::Status ProbeNifti(const fs::path& path, const std::string& name, VolumeHeader& h) {
  std::string b = ReadPrefix(path, 544);
  if (b.size() < 348) return Bad(name, "too short for a NIfTI header (348 bytes)");
  int32_t n1 = Get<int32_t>(b, 0, false);
  bool swap = false;
  int version = 0;
  if (n1 == 348 || Get<int32_t>(b, 0, true) == 348) {
    version = 1;
    swap = n1 != 348;
  } else if (n1 == 540 || Get<int32_t>(b, 0, true) == 540) {
    version = 2;
    swap = n1 != 540;
  } else {
    return Bad(name, "not a NIfTI file (sizeof_hdr is neither 348 nor 540)");
  }
  if (version == 1) {
    if (std::memcmp(b.data() + 344, "n+1", 4) != 0 && std::memcmp(b.data() + 344, "ni1", 4) != 0) {
      return Bad(name, "NIfTI-1 magic is neither 'n+1' nor 'ni1'");
    }
    int16_t ndim = Get<int16_t>(b, 40, swap);
    if (ndim < 1 || ndim > 7) return Bad(name, absl::StrCat("dim[0]=", ndim, " not in 1..7"));
    for (int i = 0; i < 3; ++i) {
      h.dims[i] = i < ndim ? Get<int16_t>(b, 42 + 2 * i, swap) : 1;
      h.spacing[i] = i < ndim ? Get<float>(b, 80 + 4 * i, swap) : 1.0;
    }
    h.scalar_type = NiftiType(Get<int16_t>(b, 70, swap));
  } else {
    if (b.size() < 540) return Bad(name, "too short for a NIfTI-2 header (540 bytes)");
    int64_t ndim = Get<int64_t>(b, 16, swap);
    if (ndim < 1 || ndim > 7) return Bad(name, absl::StrCat("dim[0]=", ndim, " not in 1..7"));
    for (int i = 0; i < 3; ++i) {
      h.dims[i] = i < ndim ? Get<int64_t>(b, 24 + 8 * i, swap) : 1;
      h.spacing[i] = i < ndim ? Get<double>(b, 112 + 8 * i, swap) : 1.0;
    }
    h.scalar_type = NiftiType(Get<int16_t>(b, 12, swap));
  }
  if (h.scalar_type.empty()) return Bad(name, "unsupported NIfTI datatype");
  return CheckDims(name, h.dims);
}

// "key = value" (MetaImage) or "key: value" (NRRD) lines up to the data.
std::map<std::string, std::string> TextHeader(const std::string& text, char sep,
                                              size_t* header_bytes) {
  std::map<std::string, std::string> kv;
  size_t pos = 0;
  while (pos < text.size()) {
    size_t eol = text.find('\n', pos);
    if (eol == std::string::npos) break;
    std::string line(absl::StripTrailingAsciiWhitespace(text.substr(pos, eol - pos)));
    pos = eol + 1;
    if (sep == ':' && line.empty()) break;  // NRRD: blank line ends the header
    size_t k = line.find(sep);
    if (k == std::string::npos) continue;
    std::string key(absl::StripAsciiWhitespace(line.substr(0, k)));
    std::string val(absl::StripAsciiWhitespace(line.substr(k + 1)));
    if (sep == ':' && !val.empty() && val[0] == '=') continue;  // NRRD key:=value
    kv[absl::AsciiStrToLower(key)] = val;
    if (sep == '=' && absl::AsciiStrToLower(key) == "elementdatafile") break;
  }
  *header_bytes = pos;
  return kv;
}

bool ParseNumbers(const std::string& s, std::vector<double>* out) {
  for (absl::string_view t : absl::StrSplit(s, absl::ByAnyChar(" \t,()"), absl::SkipEmpty())) {
    double v;
    if (!absl::SimpleAtod(t, &v)) return false;
    out->push_back(v);
  }
  return true;
}

absl::Status ProbeMeta(const fs::path& path, const std::string& name, VolumeHeader& h) {
  std::string text = ReadPrefix(path, 16384);
  size_t header_bytes = 0;
  auto kv = TextHeader(text, '=', &header_bytes);
  if (!kv.count("ndims") || !kv.count("dimsize")) {
    return Bad(name, "not a MetaImage header (NDims and DimSize missing)");
  }
  std::vector<double> d, s;
  if (!ParseNumbers(kv["dimsize"], &d) || d.size() < 3) return Bad(name, "DimSize needs 3 numbers");
  for (int i = 0; i < 3; ++i) h.dims[i] = static_cast<int64_t>(d[i]);
  std::string sp = kv.count("elementspacing") ? kv["elementspacing"] : kv["elementsize"];
  if (ParseNumbers(sp, &s) && s.size() >= 3) {
    for (int i = 0; i < 3; ++i) h.spacing[i] = s[i];
  } else {
    h.spacing = {1, 1, 1};
  }
  static const std::map<std::string, std::string> kTypes = {
      {"met_uchar", "uint8"},   {"met_char", "int8"},     {"met_short", "int16"},
      {"met_ushort", "uint16"}, {"met_int", "int32"},     {"met_uint", "uint32"},
      {"met_float", "float32"}, {"met_double", "float64"}};
  auto t = kTypes.find(absl::AsciiStrToLower(kv["elementtype"]));
  if (t == kTypes.end())
    return Bad(name, absl::StrCat("ElementType '", kv["elementtype"], "' unsupported"));
  h.scalar_type = t->second;
  if (kv.count("modality")) {
    std::string m = kv["modality"];
    h.modality = absl::StartsWith(m, "MET_MOD_") ? m.substr(8) : m;
  }
  if (!kv.count("elementdatafile")) return Bad(name, "ElementDataFile missing");
  return CheckDims(name, h.dims);
}

absl::Status ProbeNrrd(const fs::path& path, const std::string& name, VolumeHeader& h) {
  std::string text = ReadPrefix(path, 16384);
  if (!absl::StartsWith(text, "NRRD000")) return Bad(name, "not a NRRD file (no NRRD000x magic)");
  size_t header_bytes = 0;
  auto kv = TextHeader(text, ':', &header_bytes);
  std::vector<double> d;
  if (!ParseNumbers(kv["sizes"], &d) || d.size() != 3)
    return Bad(name, "sizes must hold 3 numbers");
  for (int i = 0; i < 3; ++i) h.dims[i] = static_cast<int64_t>(d[i]);
  std::vector<double> s;
  if (kv.count("spacings") && ParseNumbers(kv["spacings"], &s) && s.size() == 3) {
    for (int i = 0; i < 3; ++i) h.spacing[i] = s[i];
  } else if (kv.count("space directions")) {
    std::vector<double> m;
    if (ParseNumbers(kv["space directions"], &m) && m.size() == 9) {
      for (int i = 0; i < 3; ++i) {
        h.spacing[i] = std::sqrt(m[3 * i] * m[3 * i] + m[3 * i + 1] * m[3 * i + 1] +
                                 m[3 * i + 2] * m[3 * i + 2]);
      }
    }
  } else {
    h.spacing = {1, 1, 1};
  }
  std::string type = kv["type"];
  static const std::map<std::string, std::string> kTypes = {
      {"uchar", "uint8"},   {"unsigned char", "uint8"},   {"uint8", "uint8"},
      {"short", "int16"},   {"int16", "int16"},           {"signed short", "int16"},
      {"ushort", "uint16"}, {"unsigned short", "uint16"}, {"uint16", "uint16"},
      {"int", "int32"},     {"int32", "int32"},           {"float", "float32"},
      {"double", "float64"}};
  auto t = kTypes.find(type);
  if (t == kTypes.end()) return Bad(name, absl::StrCat("type '", type, "' unsupported"));
  h.scalar_type = t->second;
  return CheckDims(name, h.dims);
}

bool HasDicmPreamble(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  char buf[132];
  return in.read(buf, 132) && std::memcmp(buf + 128, "DICM", 4) == 0;
}

}  // namespace

absl::StatusOr<VolumeHeader> ProbeVolume(const fs::path& dir, const std::vector<std::string>& files,
                                         v1::VolumeFormat format) {
  if (files.empty()) return absl::InvalidArgumentError("files: a volume needs at least one file");
  VolumeHeader h;
  auto lower = [](const std::string& s) { return absl::AsciiStrToLower(s); };
  // The header file among the files, and the format it implies.
  std::string main;
  v1::VolumeFormat detected = v1::VOLUME_FORMAT_UNSPECIFIED;
  for (const auto& f : files) {
    std::string l = lower(f);
    if (absl::EndsWith(l, ".nii") || absl::EndsWith(l, ".nii.gz")) {
      detected = v1::VOLUME_FORMAT_NIFTI;
    } else if (absl::EndsWith(l, ".mha") || absl::EndsWith(l, ".mhd")) {
      detected = v1::VOLUME_FORMAT_METAIMAGE;
    } else if (absl::EndsWith(l, ".nrrd") || absl::EndsWith(l, ".nhdr")) {
      detected = v1::VOLUME_FORMAT_NRRD;
    } else {
      continue;
    }
    main = f;
    break;
  }
  if (detected == v1::VOLUME_FORMAT_UNSPECIFIED &&
      (files.size() > 1 || HasDicmPreamble(dir / files[0]) || lower(files[0]).ends_with(".dcm"))) {
    detected = v1::VOLUME_FORMAT_DICOM;
  }
  if (format == v1::VOLUME_FORMAT_UNSPECIFIED) format = detected;
  if (format == v1::VOLUME_FORMAT_UNSPECIFIED) {
    return absl::InvalidArgumentError(
        absl::StrCat(files[0],
                     ": unknown volume format (expected .nii, .nii.gz, .mha, .mhd, .nrrd, .nhdr "
                     "or DICOM files)"));
  }
  if (format != v1::VOLUME_FORMAT_DICOM && format != detected) {
    return absl::InvalidArgumentError(absl::StrCat("format ", v1::VolumeFormat_Name(format),
                                                   ": no file with a matching extension"));
  }
  h.format = format;
  absl::Status s;
#ifdef DECIMA_HAVE_IO
  // The core reader: the same code the job's load stage runs, so a volume accepted here loads.
  if (format != v1::VOLUME_FORMAT_DICOM) {
    auto vol = io::ReadVolume(dir / main);
    if (!vol.ok()) {
      // Name the file as the client did, not by its path on the server.
      std::string msg(vol.status().message());
      std::string server_path = (dir / main).string();
      if (absl::StartsWith(msg, server_path)) msg = main + msg.substr(server_path.size());
      return absl::Status(vol.status().code() == absl::StatusCode::kNotFound
                              ? absl::StatusCode::kInvalidArgument
                              : vol.status().code(),
                          msg);
    }
    for (int i = 0; i < 3; ++i) {
      h.dims[i] = vol->dims[i];
      h.spacing[i] = vol->spacing[i];
    }
    h.modality = vol->modality;
    h.scalar_type = std::string(VoxelTypeName(vol->type));
    h.parsed = true;
    h.input = dir / main;
    return h;
  }
#endif
  switch (format) {
    case v1::VOLUME_FORMAT_NIFTI:
      s = ProbeNifti(dir / main, main, h);
      break;
    case v1::VOLUME_FORMAT_METAIMAGE:
      s = ProbeMeta(dir / main, main, h);
      break;
    case v1::VOLUME_FORMAT_NRRD:
      s = ProbeNrrd(dir / main, main, h);
      break;
    default: {
      // DICOM: check every file carries the preamble; dims come from the job's load stage.
      for (const auto& f : files) {
        if (!HasDicmPreamble(dir / f)) {
          return absl::InvalidArgumentError(
              absl::StrCat(f, ": not a DICOM file (no 'DICM' at byte 128)"));
        }
      }
      h.input = dir;
      return h;
    }
  }
  if (!s.ok()) return s;
  h.parsed = true;
  h.input = dir / main;
  return h;
}

}  // namespace decima::server

namespace decima::server {

std::filesystem::path VolumeInput(const std::filesystem::path& files_dir,
                                  const v1::Volume& volume) {
  if (volume.format() == v1::VOLUME_FORMAT_DICOM || volume.files().empty()) return files_dir;
  for (const auto& f : volume.files()) {
    std::string l = absl::AsciiStrToLower(f.path());
    for (const char* ext : {".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr"}) {
      if (absl::EndsWith(l, ext)) return files_dir / f.path();
    }
  }
  return files_dir / volume.files(0).path();
}

}  // namespace decima::server
