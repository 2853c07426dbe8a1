// DICOM series reader on GDCM 3.0, in two passes: headers of every file of the folder are
// parsed with gdcm::Reader stopped before the pixel data (pass 1); pixels are decoded only for
// the files of the chosen series (pass 2), so a folder with many series costs little more than
// the one that is read. Every file is first walked by CheckDicomStructure (dicom_preflight.h)
// because Debian's GDCM asserts or crashes on some malformed input; for the same reason native
// little-endian and RLE pixel data are decoded here and only the other codecs go to
// gdcm::ImageReader. Geometry is computed from the raw attributes rather than taken from
// gdcm::ImageHelper, whose spacing rules (SpacingBetweenSlices, SliceThickness, vendor quirks)
// differ from the "positions are the truth" rule of dicom.h.
//
// GDCM throws internally on some malformed input; every GDCM call is wrapped so no exception
// leaves this file.
#include "core/io/dicom.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <exception>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <type_traits>
#include <utility>

#include <gdcmDataSet.h>
#include <gdcmFile.h>
#include <gdcmImage.h>
#include <gdcmImageReader.h>
#include <gdcmPixelFormat.h>
#include <gdcmReader.h>
#include <gdcmSequenceOfFragments.h>
#include <gdcmTag.h>
#include <gdcmTrace.h>
#include <gdcmTransferSyntax.h>

#include "absl/strings/ascii.h"
#include "absl/strings/escaping.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/types/span.h"
#include "core/common/status.h"
#include "core/common/utf8.h"
#include "core/io/dicom_preflight.h"

namespace decima {
namespace {

namespace fs = std::filesystem;

// Attributes used (DICOM Part 6 data dictionary).
const gdcm::Tag kModality(0x0008, 0x0060);
const gdcm::Tag kSeriesDescription(0x0008, 0x103e);
const gdcm::Tag kStudyDate(0x0008, 0x0020);
const gdcm::Tag kStudyDescription(0x0008, 0x1030);
const gdcm::Tag kPatientName(0x0010, 0x0010);
const gdcm::Tag kPatientId(0x0010, 0x0020);
const gdcm::Tag kSeriesInstanceUid(0x0020, 0x000e);
const gdcm::Tag kImagePositionPatient(0x0020, 0x0032);
const gdcm::Tag kImageOrientationPatient(0x0020, 0x0037);
const gdcm::Tag kSamplesPerPixel(0x0028, 0x0002);
const gdcm::Tag kPhotometricInterpretation(0x0028, 0x0004);
const gdcm::Tag kNumberOfFrames(0x0028, 0x0008);
const gdcm::Tag kRows(0x0028, 0x0010);
const gdcm::Tag kColumns(0x0028, 0x0011);
const gdcm::Tag kPixelSpacing(0x0028, 0x0030);
const gdcm::Tag kBitsAllocated(0x0028, 0x0100);
const gdcm::Tag kBitsStored(0x0028, 0x0101);
const gdcm::Tag kHighBit(0x0028, 0x0102);
const gdcm::Tag kPixelRepresentation(0x0028, 0x0103);
const gdcm::Tag kRescaleIntercept(0x0028, 0x1052);
const gdcm::Tag kRescaleSlope(0x0028, 0x1053);
const gdcm::Tag kPixelData(0x7fe0, 0x0010);

// Tolerances. DS values carry at most 16 characters, so equal quantities written by one scanner
// may differ in the last digits.
constexpr double kOrientationTolerance = 1e-4;      // per cosine component, between slices
constexpr double kOrthonormalTolerance = 1e-3;      // |norm - 1| and |row . col| of one slice
constexpr double kPixelSpacingRelTolerance = 1e-4;  // between slices
constexpr double kDuplicatePositionMm = 1e-3;       // slices closer than this along the normal
constexpr double kMissingSliceFactor = 1.5;         // gap / median gap that means a lost slice
constexpr double kUnevenRelTolerance = 0.01;        // |gap - mean| <= 1% of mean + 0.01 mm
constexpr double kUnevenAbsToleranceMm = 0.01;
constexpr double kInPlaneShiftPixels = 0.1;  // allowed in-plane drift of slice origins
constexpr size_t kMaxListedSkips = 10;
// A single-frame slice file is far smaller; anything bigger is refused before it is read.
constexpr uintmax_t kMaxFileBytes = uintmax_t{1} << 30;

// Header attributes of one file, unparsed: required ones are checked when a series is
// assembled, so a broken file in another series does not block this one.
struct SliceHeader {
  fs::path path;
  std::string name;  // relative to the folder, used in messages
  std::string series_uid;
  std::string description;
  std::string modality;
  std::string patient_name, patient_id, study_date, study_description;  // DicomDescription
  std::optional<std::string> photometric, number_of_frames, pixel_spacing, orientation, position,
      rescale_slope, rescale_intercept;
  std::optional<uint16_t> rows, columns, samples_per_pixel, bits_allocated, bits_stored, high_bit,
      pixel_representation;
};

struct FolderScan {
  std::vector<SliceHeader> images;   // sorted by name
  std::vector<std::string> skipped;  // "name (reason)"
};

void SilenceGdcmTrace() {
  // GDCM prints to std::cerr on malformed input; our Status messages replace that output.
  static std::once_flag once;
  std::call_once(once, [] {
    gdcm::Trace::SetDebug(false);
    gdcm::Trace::SetWarning(false);
    gdcm::Trace::SetError(false);
  });
}

std::string Prefix(const fs::path& dir, const std::string& name) {
  return absl::StrCat(dir.string(), ": ", name, ": ");
}

// Text value of `tag` with DICOM padding (spaces, NUL) stripped, or nullopt if absent or empty.
std::optional<std::string> GetText(const gdcm::DataSet& ds, const gdcm::Tag& tag) {
  if (!ds.FindDataElement(tag)) return std::nullopt;
  const gdcm::ByteValue* bv = ds.GetDataElement(tag).GetByteValue();
  if (bv == nullptr || bv->GetLength() == 0) return std::nullopt;
  std::string s(bv->GetPointer(), bv->GetLength());
  while (!s.empty() && (s.back() == ' ' || s.back() == '\0')) s.pop_back();
  absl::StripLeadingAsciiWhitespace(&s);
  if (s.empty()) return std::nullopt;
  // Text may reach protobuf string fields (Volume.modality): a header's stray non-UTF-8 byte
  // (a Latin-1 description, a broken Modality) must not make every answer carrying it fail.
  return ValidUtf8(s);
}

// US value of `tag`, or nullopt if absent or not exactly 2 bytes. GDCM keeps binary values in
// file byte order, so big-endian data sets are swapped here.
std::optional<uint16_t> GetUs(const gdcm::DataSet& ds, const gdcm::Tag& tag, bool big_endian) {
  if (!ds.FindDataElement(tag)) return std::nullopt;
  const gdcm::ByteValue* bv = ds.GetDataElement(tag).GetByteValue();
  if (bv == nullptr || bv->GetLength() != 2) return std::nullopt;
  uint16_t v;
  std::memcpy(&v, bv->GetPointer(), 2);
  if (big_endian) v = static_cast<uint16_t>((v >> 8) | (v << 8));
  return v;
}

// Reads a whole file that has the DICOM marker and checks its element structure, so that GDCM
// (which asserts on some malformed input) only ever parses structurally sound bytes.
absl::StatusOr<std::string> LoadCheckedFile(const fs::path& dir, const fs::path& path,
                                            const std::string& name) {
  std::error_code ec;
  const uintmax_t size = fs::file_size(path, ec);
  if (ec) {
    return absl::InvalidArgumentError(
        absl::StrCat(Prefix(dir, name), "cannot get file size: ", ec.message()));
  }
  if (size > kMaxFileBytes) {
    return absl::InvalidArgumentError(absl::StrCat(Prefix(dir, name), "is ", size,
                                                   " bytes, more than the ", kMaxFileBytes,
                                                   " accepted for one slice"));
  }
  std::string bytes(size, '\0');
  std::ifstream in(path, std::ios::binary);
  in.read(bytes.data(), static_cast<std::streamsize>(size));
  if (!in || in.gcount() != static_cast<std::streamsize>(size)) {
    return absl::InvalidArgumentError(absl::StrCat(Prefix(dir, name), "cannot be read"));
  }
  absl::Status structure = dicom_internal::CheckDicomStructure(bytes);
  if (!structure.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat(Prefix(dir, name), "corrupt DICOM file: ", structure.message()));
  }
  return bytes;
}

// Pass 1 for one file. Returns nullopt (with `skip_reason`) for files that are not DICOM images.
absl::StatusOr<std::optional<SliceHeader>> ReadHeader(const fs::path& dir, const fs::path& path,
                                                      const std::string& name,
                                                      std::string* skip_reason) {
  if (!HasDicomMarker(path, skip_reason)) return std::nullopt;
  DECIMA_ASSIGN_OR_RETURN(std::string bytes, LoadCheckedFile(dir, path, name));
  std::istringstream stream(std::move(bytes));
  gdcm::Reader reader;
  reader.SetStream(stream);
  bool ok = false;
  std::string what;
  try {
    ok = reader.ReadUpToTag(kPixelData);
  } catch (const std::exception& e) {
    what = e.what();
  } catch (...) {
    what = "unknown exception";
  }
  if (!ok) {
    return absl::InvalidArgumentError(
        absl::StrCat(Prefix(dir, name), "has the DICOM marker but its header cannot be parsed",
                     what.empty() ? "" : absl::StrCat(" (", what, ")")));
  }
  const gdcm::File& file = reader.GetFile();
  const gdcm::DataSet& ds = file.GetDataSet();
  const bool big_endian =
      file.GetHeader().GetDataSetTransferSyntax() == gdcm::TransferSyntax::ExplicitVRBigEndian;
  SliceHeader h;
  h.path = path;
  h.name = name;
  std::optional<std::string> uid = GetText(ds, kSeriesInstanceUid);
  h.rows = GetUs(ds, kRows, big_endian);
  if (!uid || !ds.FindDataElement(kRows)) {
    // DICOMDIR, structured reports, presentation states: DICOM, but not a slice.
    *skip_reason = "DICOM without SeriesInstanceUID or Rows, not an image";
    return std::nullopt;
  }
  h.series_uid = *uid;
  h.description = GetText(ds, kSeriesDescription).value_or("");
  h.modality = GetText(ds, kModality).value_or("");
  h.patient_name = GetText(ds, kPatientName).value_or("");
  h.patient_id = GetText(ds, kPatientId).value_or("");
  h.study_date = GetText(ds, kStudyDate).value_or("");
  h.study_description = GetText(ds, kStudyDescription).value_or("");
  h.photometric = GetText(ds, kPhotometricInterpretation);
  h.number_of_frames = GetText(ds, kNumberOfFrames);
  h.pixel_spacing = GetText(ds, kPixelSpacing);
  h.orientation = GetText(ds, kImageOrientationPatient);
  h.position = GetText(ds, kImagePositionPatient);
  h.rescale_slope = GetText(ds, kRescaleSlope);
  h.rescale_intercept = GetText(ds, kRescaleIntercept);
  h.columns = GetUs(ds, kColumns, big_endian);
  h.samples_per_pixel = GetUs(ds, kSamplesPerPixel, big_endian);
  h.bits_allocated = GetUs(ds, kBitsAllocated, big_endian);
  h.bits_stored = GetUs(ds, kBitsStored, big_endian);
  h.high_bit = GetUs(ds, kHighBit, big_endian);
  h.pixel_representation = GetUs(ds, kPixelRepresentation, big_endian);
  return h;
}

absl::StatusOr<FolderScan> ScanFolder(const fs::path& dir) {
  SilenceGdcmTrace();
  std::error_code ec;
  if (!fs::exists(dir, ec)) {
    return absl::NotFoundError(absl::StrCat(dir.string(), ": DICOM folder does not exist"));
  }
  if (!fs::is_directory(dir, ec)) {
    return absl::InvalidArgumentError(
        absl::StrCat(dir.string(), ": is not a folder (a DICOM series is read from a folder)"));
  }
  // Regular files of `dir` and of its immediate subdirectories; hidden entries are ignored.
  std::vector<fs::path> files;
  auto list = [&](const fs::path& folder, bool descend) -> absl::Status {
    std::error_code iter_ec;
    fs::directory_iterator it(folder, iter_ec), end;
    for (; !iter_ec && it != end; it.increment(iter_ec)) {
      const fs::path& p = it->path();
      if (p.filename().string().starts_with(".")) continue;
      std::error_code type_ec;
      if (it->is_regular_file(type_ec)) {
        files.push_back(p);
      } else if (descend && it->is_directory(type_ec)) {
        files.push_back(p);  // marker, expanded below
      }
    }
    if (iter_ec) {
      return absl::InvalidArgumentError(
          absl::StrCat(folder.string(), ": cannot list folder: ", iter_ec.message()));
    }
    return absl::OkStatus();
  };
  DECIMA_RETURN_IF_ERROR(list(dir, true));
  std::vector<fs::path> subdirs;
  std::erase_if(files, [&](const fs::path& p) {
    std::error_code type_ec;
    if (!fs::is_directory(p, type_ec)) return false;
    subdirs.push_back(p);
    return true;
  });
  for (const fs::path& sub : subdirs) DECIMA_RETURN_IF_ERROR(list(sub, false));
  std::sort(files.begin(), files.end());

  FolderScan scan;
  for (const fs::path& path : files) {
    std::string name = path.lexically_relative(dir).generic_string();
    std::string reason;
    DECIMA_ASSIGN_OR_RETURN(std::optional<SliceHeader> header,
                            ReadHeader(dir, path, name, &reason));
    if (header) {
      scan.images.push_back(std::move(*header));
    } else {
      scan.skipped.push_back(absl::StrCat(name, " (", reason, ")"));
    }
  }
  if (scan.images.empty()) {
    std::string skipped;
    if (scan.skipped.empty()) {
      skipped = "the folder is empty";
    } else {
      std::vector<std::string> shown(
          scan.skipped.begin(),
          scan.skipped.begin() + std::min(scan.skipped.size(), kMaxListedSkips));
      skipped =
          absl::StrCat("skipped ", scan.skipped.size(), " file(s): ", absl::StrJoin(shown, ", "),
                       scan.skipped.size() > shown.size() ? ", ..." : "");
    }
    return absl::InvalidArgumentError(
        absl::StrCat(dir.string(), ": no DICOM image file found (", skipped, ")"));
  }
  return scan;
}

std::map<std::string, std::vector<const SliceHeader*>> GroupBySeries(const FolderScan& scan) {
  std::map<std::string, std::vector<const SliceHeader*>> series;
  for (const SliceHeader& h : scan.images) series[h.series_uid].push_back(&h);
  return series;
}

std::vector<DicomSeriesInfo> SeriesInfos(
    const std::map<std::string, std::vector<const SliceHeader*>>& series) {
  std::vector<DicomSeriesInfo> infos;
  for (const auto& [uid, files] : series) {
    infos.push_back({uid, files.front()->description, files.front()->modality,
                     static_cast<int64_t>(files.size())});
  }
  return infos;
}

std::string ListForMessage(const std::vector<DicomSeriesInfo>& infos) {
  std::vector<std::string> parts;
  for (const DicomSeriesInfo& s : infos) {
    parts.push_back(absl::StrCat("uid ", absl::CHexEscape(s.series_instance_uid), " (\"",
                                 absl::CHexEscape(s.series_description), "\", modality ",
                                 s.modality.empty() ? "?" : s.modality, ", ", s.file_count,
                                 " files)"));
  }
  return absl::StrJoin(parts, "; ");
}

// Parsed, checked attributes of one slice.
struct Slice {
  const SliceHeader* header = nullptr;
  int rows = 0, columns = 0, bits_allocated = 0, pixel_representation = 0;
  int bits_stored = 0, high_bit = 0;           // default BitsAllocated, BitsStored - 1
  double row_spacing = 0, column_spacing = 0;  // PixelSpacing[0], [1]
  std::array<double, 6> orientation{};
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
  double slope = 1, intercept = 0;
  double along_normal = 0;  // position . normal
};

absl::StatusOr<std::vector<double>> ParseDecimals(const fs::path& dir, const SliceHeader& h,
                                                  const std::optional<std::string>& text,
                                                  const char* field, size_t count) {
  if (!text) {
    return absl::InvalidArgumentError(absl::StrCat(Prefix(dir, h.name), field, " is missing"));
  }
  std::vector<double> values;
  for (absl::string_view part : absl::StrSplit(*text, '\\')) {
    double v;
    if (!absl::SimpleAtod(absl::StripAsciiWhitespace(part), &v) || !std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(Prefix(dir, h.name), field, " '",
                                                     absl::CHexEscape(*text),
                                                     "' is not a list of finite numbers"));
    }
    values.push_back(v);
  }
  if (values.size() != count) {
    return absl::InvalidArgumentError(absl::StrCat(Prefix(dir, h.name), field, " '",
                                                   absl::CHexEscape(*text), "' has ", values.size(),
                                                   " values, expected ", count));
  }
  return values;
}

absl::StatusOr<int> RequireUs(const fs::path& dir, const SliceHeader& h,
                              const std::optional<uint16_t>& value, const char* field) {
  if (!value) {
    return absl::InvalidArgumentError(
        absl::StrCat(Prefix(dir, h.name), field, " is missing or not a 2-byte US value"));
  }
  return static_cast<int>(*value);
}

absl::StatusOr<Slice> ParseSlice(const fs::path& dir, const SliceHeader& h) {
  Slice s;
  s.header = &h;
  const std::string prefix = Prefix(dir, h.name);
  if (h.number_of_frames) {
    int frames = 0;
    if (!absl::SimpleAtoi(*h.number_of_frames, &frames) || frames != 1) {
      return absl::InvalidArgumentError(
          absl::StrCat(prefix, "NumberOfFrames is '", *h.number_of_frames,
                       "'; only single-frame files (one slice per file) are supported"));
    }
  }
  DECIMA_ASSIGN_OR_RETURN(s.rows, RequireUs(dir, h, h.rows, "Rows (0028,0010)"));
  DECIMA_ASSIGN_OR_RETURN(s.columns, RequireUs(dir, h, h.columns, "Columns (0028,0011)"));
  if (s.rows < 1 || s.columns < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "Rows x Columns is ", s.rows, " x ", s.columns, ", expected >= 1"));
  }
  DECIMA_ASSIGN_OR_RETURN(int spp,
                          RequireUs(dir, h, h.samples_per_pixel, "SamplesPerPixel (0028,0002)"));
  if (spp != 1) {
    return absl::InvalidArgumentError(absl::StrCat(
        prefix, "SamplesPerPixel is ", spp, ", expected 1 (colour images are not supported)"));
  }
  if (h.photometric && *h.photometric != "MONOCHROME1" && *h.photometric != "MONOCHROME2") {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "PhotometricInterpretation is ",
                                                   *h.photometric,
                                                   ", expected MONOCHROME1 or MONOCHROME2"));
  }
  DECIMA_ASSIGN_OR_RETURN(s.bits_allocated,
                          RequireUs(dir, h, h.bits_allocated, "BitsAllocated (0028,0100)"));
  if (s.bits_allocated != 8 && s.bits_allocated != 16 && s.bits_allocated != 32) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "BitsAllocated is ", s.bits_allocated, ", expected 8, 16 or 32"));
  }
  s.bits_stored = h.bits_stored.value_or(s.bits_allocated);
  s.high_bit = h.high_bit.value_or(s.bits_stored - 1);
  if (s.bits_stored < 1 || s.bits_stored > s.bits_allocated || s.high_bit < s.bits_stored - 1 ||
      s.high_bit >= s.bits_allocated) {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "BitsStored ", s.bits_stored,
                                                   " / HighBit ", s.high_bit,
                                                   " do not fit BitsAllocated ", s.bits_allocated));
  }
  DECIMA_ASSIGN_OR_RETURN(s.pixel_representation, RequireUs(dir, h, h.pixel_representation,
                                                            "PixelRepresentation (0028,0103)"));
  if (s.pixel_representation > 1) {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "PixelRepresentation is ",
                                                   s.pixel_representation, ", expected 0 or 1"));
  }
  DECIMA_ASSIGN_OR_RETURN(std::vector<double> ps,
                          ParseDecimals(dir, h, h.pixel_spacing, "PixelSpacing (0028,0030)", 2));
  if (!(ps[0] > 0) || !(ps[1] > 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "PixelSpacing '", *h.pixel_spacing, "' must be > 0"));
  }
  s.row_spacing = ps[0];
  s.column_spacing = ps[1];
  DECIMA_ASSIGN_OR_RETURN(
      std::vector<double> o,
      ParseDecimals(dir, h, h.orientation, "ImageOrientationPatient (0020,0037)", 6));
  std::copy(o.begin(), o.end(), s.orientation.begin());
  DECIMA_ASSIGN_OR_RETURN(std::vector<double> p,
                          ParseDecimals(dir, h, h.position, "ImagePositionPatient (0020,0032)", 3));
  s.position = Eigen::Vector3d(p[0], p[1], p[2]);
  if (h.rescale_slope) {
    DECIMA_ASSIGN_OR_RETURN(std::vector<double> v,
                            ParseDecimals(dir, h, h.rescale_slope, "RescaleSlope (0028,1053)", 1));
    s.slope = v[0];
    if (s.slope == 0) {
      return absl::InvalidArgumentError(absl::StrCat(prefix, "RescaleSlope is 0"));
    }
  }
  if (h.rescale_intercept) {
    DECIMA_ASSIGN_OR_RETURN(
        std::vector<double> v,
        ParseDecimals(dir, h, h.rescale_intercept, "RescaleIntercept (0028,1052)", 1));
    s.intercept = v[0];
  }
  return s;
}

std::string JoinDecimals(absl::Span<const double> v) { return absl::StrJoin(v, "\\"); }

// Every slice must share the reference's grid and pixel format.
absl::Status CheckConsistent(const fs::path& dir, const Slice& ref, const Slice& s) {
  const std::string prefix = Prefix(dir, s.header->name);
  const std::string in_ref = absl::StrCat(" in ", ref.header->name);
  auto differs = [&](const char* field, auto value, auto expected) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, field, " is ", value, ", expected ", expected, in_ref));
  };
  if (s.rows != ref.rows) return differs("Rows", s.rows, ref.rows);
  if (s.columns != ref.columns) return differs("Columns", s.columns, ref.columns);
  if (s.bits_allocated != ref.bits_allocated) {
    return differs("BitsAllocated", s.bits_allocated, ref.bits_allocated);
  }
  if (s.pixel_representation != ref.pixel_representation) {
    return differs("PixelRepresentation", s.pixel_representation, ref.pixel_representation);
  }
  auto rel_differs = [](double a, double b) {
    return std::abs(a - b) > kPixelSpacingRelTolerance * std::max(std::abs(a), std::abs(b));
  };
  if (rel_differs(s.row_spacing, ref.row_spacing) ||
      rel_differs(s.column_spacing, ref.column_spacing)) {
    return differs("PixelSpacing", JoinDecimals({s.row_spacing, s.column_spacing}),
                   JoinDecimals({ref.row_spacing, ref.column_spacing}));
  }
  for (int c = 0; c < 6; ++c) {
    if (std::abs(s.orientation[c] - ref.orientation[c]) > kOrientationTolerance) {
      return differs("ImageOrientationPatient", JoinDecimals(s.orientation),
                     JoinDecimals(ref.orientation));
    }
  }
  return absl::OkStatus();
}

VoxelType StoredType(int bits_allocated, int pixel_representation) {
  const bool is_signed = pixel_representation == 1;
  switch (bits_allocated) {
    case 8:
      return is_signed ? VoxelType::kInt8 : VoxelType::kUInt8;
    case 16:
      return is_signed ? VoxelType::kInt16 : VoxelType::kUInt16;
    default:
      return is_signed ? VoxelType::kInt32 : VoxelType::kUInt32;
  }
}

// Decodes with gdcm::ImageReader, for the compressed syntaxes we do not decode ourselves (JPEG
// family, JPEG-LS, JPEG 2000, big endian). GDCM masks unused high bits itself.
absl::Status DecodeWithGdcm(std::istream& stream, const Slice& s, uint8_t* dest, size_t bytes,
                            const std::string& prefix) {
  gdcm::ImageReader reader;
  reader.SetStream(stream);
  if (!reader.Read()) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "GDCM cannot read the image (corrupt file or pixel data?)"));
  }
  const gdcm::Image& image = reader.GetImage();
  const char* ts_uid = image.GetTransferSyntax().GetString();
  const std::string ts = ts_uid ? ts_uid : "unknown";
  const unsigned int* dims = image.GetDimensions();
  const gdcm::PixelFormat& pf = image.GetPixelFormat();
  if (dims[0] != static_cast<unsigned>(s.columns) || dims[1] != static_cast<unsigned>(s.rows) ||
      (image.GetNumberOfDimensions() > 2 && dims[2] != 1)) {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "GDCM decodes an image of ", dims[0],
                                                   " x ", dims[1], ", header says Columns ",
                                                   s.columns, " x Rows ", s.rows));
  }
  if (pf.GetSamplesPerPixel() != 1 || pf.GetBitsAllocated() != s.bits_allocated ||
      pf.GetPixelRepresentation() != s.pixel_representation) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "GDCM decodes pixel format ", pf.GetScalarTypeAsString(),
                     ", header says BitsAllocated ", s.bits_allocated, " PixelRepresentation ",
                     s.pixel_representation));
  }
  const unsigned long length = image.GetBufferLength();
  if (length != bytes) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "decoded pixel data is ", length, " bytes, expected Rows * ",
                     "Columns * BitsAllocated / 8 = ", bytes, " (transfer syntax ", ts, ")"));
  }
  if (!image.GetBuffer(reinterpret_cast<char*>(dest))) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "GDCM cannot decode the pixel data (transfer syntax ", ts, ")"));
  }
  return absl::OkStatus();
}

// RLE Lossless (PS3.5 Annex G): a 64-byte header (segment count, 15 offsets) and one PackBits
// segment per byte plane, most significant plane first. Decoded here, bounds-checked, because
// GDCM's RLE codec crashes on corrupt segments.
absl::Status DecodeRle(absl::string_view frame, int64_t pixels, int bytes_per_sample, uint8_t* dest,
                       const std::string& prefix) {
  if (frame.size() < 64) {
    return absl::InvalidArgumentError(
        absl::StrCat(prefix, "RLE frame of ", frame.size(), " bytes has no 64-byte header"));
  }
  uint32_t header[16];
  std::memcpy(header, frame.data(), sizeof(header));  // little endian, as the host
  if (header[0] != static_cast<uint32_t>(bytes_per_sample)) {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "RLE frame has ", header[0],
                                                   " segments, expected ", bytes_per_sample,
                                                   " (one per byte of a sample)"));
  }
  for (int seg = 0; seg < bytes_per_sample; ++seg) {
    const size_t begin = header[1 + seg];
    const size_t end = seg + 1 < bytes_per_sample ? header[2 + seg] : frame.size();
    if (begin < 64 || begin > end || end > frame.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat(prefix, "RLE segment ", seg, " has invalid offsets ", begin, "..", end));
    }
    const int byte = bytes_per_sample - 1 - seg;  // little-endian position of this plane
    int64_t p = 0;
    size_t in = begin;
    while (p < pixels && in < end) {
      const int n = static_cast<int8_t>(frame[in++]);
      if (n == -128) continue;
      const int64_t count = n >= 0 ? n + 1 : 1 - n;
      if (p + count > pixels || in + (n >= 0 ? count : 1) > end) {
        return absl::InvalidArgumentError(
            absl::StrCat(prefix, "RLE segment ", seg, " is corrupt (a run overflows)"));
      }
      for (int64_t c = 0; c < count; ++c) {
        dest[(p + c) * bytes_per_sample + byte] = static_cast<uint8_t>(frame[n >= 0 ? in + c : in]);
      }
      in += n >= 0 ? count : 1;
      p += count;
    }
    if (p < pixels) {
      return absl::InvalidArgumentError(absl::StrCat(prefix, "RLE segment ", seg, " decodes to ", p,
                                                     " bytes, expected Rows * Columns = ", pixels));
    }
  }
  return absl::OkStatus();
}

// Keeps bits HighBit-BitsStored+1 .. HighBit and sign-extends signed samples (PS3.5 8.1.1), as
// GDCM does for the data it decodes: 12-bit CT may carry overlay or garbage in the top bits.
template <typename T>
void CleanUnusedBits(T* data, int64_t n, int bits_stored, int high_bit, bool is_signed) {
  using U = std::make_unsigned_t<T>;
  const int shift = high_bit + 1 - bits_stored;
  const U mask = bits_stored >= static_cast<int>(8 * sizeof(U))
                     ? static_cast<U>(~U{0})
                     : static_cast<U>((U{1} << bits_stored) - 1);
  for (int64_t v = 0; v < n; ++v) {
    U u = static_cast<U>(static_cast<U>(data[v]) >> shift) & mask;
    if (is_signed && ((u >> (bits_stored - 1)) & 1)) u = static_cast<U>(u | ~mask);
    data[v] = static_cast<T>(u);
  }
}

// Pass 2 for one slice: decodes its pixel data straight into `dest` (`bytes` long). Native
// little-endian and RLE data are decoded here; other syntaxes by GDCM.
absl::Status ReadPixels(const fs::path& dir, const Slice& s, uint8_t* dest, size_t bytes) {
  const std::string prefix = Prefix(dir, s.header->name);
  // Re-checked: the file may have changed since pass 1.
  DECIMA_ASSIGN_OR_RETURN(std::string file_bytes,
                          LoadCheckedFile(dir, s.header->path, s.header->name));
  std::istringstream stream(std::move(file_bytes));
  const int bytes_per_sample = s.bits_allocated / 8;
  const int64_t pixels = int64_t{s.rows} * s.columns;
  try {
    gdcm::Reader reader;
    reader.SetStream(stream);
    if (!reader.Read()) {
      return absl::InvalidArgumentError(absl::StrCat(prefix, "GDCM cannot parse the file"));
    }
    const gdcm::TransferSyntax ts = reader.GetFile().GetHeader().GetDataSetTransferSyntax();
    const gdcm::DataSet& ds = reader.GetFile().GetDataSet();
    if (!ds.FindDataElement(kPixelData)) {
      return absl::InvalidArgumentError(absl::StrCat(prefix, "PixelData (7FE0,0010) is missing"));
    }
    const gdcm::DataElement& pixel_data = ds.GetDataElement(kPixelData);
    if (ts == gdcm::TransferSyntax::ImplicitVRLittleEndian ||
        ts == gdcm::TransferSyntax::ExplicitVRLittleEndian) {
      const gdcm::ByteValue* bv = pixel_data.GetByteValue();
      if (bv == nullptr) {
        return absl::InvalidArgumentError(
            absl::StrCat(prefix, "PixelData is encapsulated in a native transfer syntax"));
      }
      if (bv->GetLength() < bytes) {
        return absl::InvalidArgumentError(absl::StrCat(
            prefix, "PixelData holds ", static_cast<uint32_t>(bv->GetLength()),
            " bytes, expected Rows * Columns * BitsAllocated / 8 = ", bytes, " (truncated file?)"));
      }
      std::memcpy(dest, bv->GetPointer(), bytes);
    } else if (ts == gdcm::TransferSyntax::RLELossless) {
      const gdcm::SequenceOfFragments* fragments = pixel_data.GetSequenceOfFragments();
      if (fragments == nullptr || fragments->GetNumberOfFragments() != 1) {
        return absl::InvalidArgumentError(
            absl::StrCat(prefix, "RLE PixelData must hold one fragment per frame, found ",
                         fragments ? fragments->GetNumberOfFragments() : 0));
      }
      const gdcm::ByteValue* frame = fragments->GetFragment(0).GetByteValue();
      if (frame == nullptr) {
        return absl::InvalidArgumentError(absl::StrCat(prefix, "RLE fragment is empty"));
      }
      DECIMA_RETURN_IF_ERROR(DecodeRle(absl::string_view(frame->GetPointer(), frame->GetLength()),
                                       pixels, bytes_per_sample, dest, prefix));
    } else {
      stream.clear();
      stream.seekg(0);
      return DecodeWithGdcm(stream, s, dest, bytes, prefix);
    }
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "GDCM failed: ", e.what()));
  } catch (...) {
    return absl::InvalidArgumentError(absl::StrCat(prefix, "GDCM failed (unknown exception)"));
  }
  if (s.bits_stored < s.bits_allocated || s.high_bit != s.bits_stored - 1) {
    const bool is_signed = s.pixel_representation == 1;
    switch (s.bits_allocated) {
      case 8:
        CleanUnusedBits(dest, pixels, s.bits_stored, s.high_bit, is_signed);
        break;
      case 16:
        CleanUnusedBits(reinterpret_cast<uint16_t*>(dest), pixels, s.bits_stored, s.high_bit,
                        is_signed);
        break;
      default:
        CleanUnusedBits(reinterpret_cast<uint32_t*>(dest), pixels, s.bits_stored, s.high_bit,
                        is_signed);
        break;
    }
  }
  return absl::OkStatus();
}

// Applies value = stored * slope + intercept slice by slice (DICOM Part 3 C.11.1.1.2).
template <typename T>
void Rescale(const std::vector<Slice>& slices, int64_t slice_voxels, Volume* volume) {
  const T* in = volume->data<T>();
  bool integral = true;
  double lo = INFINITY, hi = -INFINITY;
  for (size_t k = 0; k < slices.size(); ++k) {
    const double a = slices[k].slope, b = slices[k].intercept;
    // Integer slope and intercept give integer results; only then can int16 hold them.
    integral = integral && a == std::nearbyint(a) && b == std::nearbyint(b);
    const T* src = in + k * slice_voxels;
    for (int64_t v = 0; v < slice_voxels; ++v) {
      const double r = src[v] * a + b;
      lo = std::min(lo, r);
      hi = std::max(hi, r);
    }
  }
  const bool to_int16 = integral && lo >= -32768.0 && hi <= 32767.0;
  const VoxelType type = to_int16 ? VoxelType::kInt16 : VoxelType::kFloat32;
  std::vector<uint8_t> out(volume->voxel_count() * VoxelTypeSize(type));
  for (size_t k = 0; k < slices.size(); ++k) {
    const double a = slices[k].slope, b = slices[k].intercept;
    const T* src = in + k * slice_voxels;
    if (to_int16) {
      int16_t* dst = reinterpret_cast<int16_t*>(out.data()) + k * slice_voxels;
      for (int64_t v = 0; v < slice_voxels; ++v) dst[v] = static_cast<int16_t>(src[v] * a + b);
    } else {
      float* dst = reinterpret_cast<float*>(out.data()) + k * slice_voxels;
      for (int64_t v = 0; v < slice_voxels; ++v) dst[v] = static_cast<float>(src[v] * a + b);
    }
  }
  volume->type = type;
  volume->bytes = std::move(out);
}

absl::StatusOr<Volume> AssembleSeries(const fs::path& dir, const std::string& uid,
                                      const std::vector<const SliceHeader*>& headers) {
  const std::string series = absl::StrCat(dir.string(), ": series ", uid, ": ");
  std::vector<Slice> slices;
  slices.reserve(headers.size());
  for (const SliceHeader* h : headers) {
    DECIMA_ASSIGN_OR_RETURN(Slice s, ParseSlice(dir, *h));
    if (!slices.empty()) DECIMA_RETURN_IF_ERROR(CheckConsistent(dir, slices.front(), s));
    slices.push_back(std::move(s));
  }
  if (slices.size() < 2) {
    return absl::InvalidArgumentError(absl::StrCat(series, "has ", slices.size(), " slice (",
                                                   headers.front()->name,
                                                   "); a volume needs at least 2"));
  }

  // Direction: row cosine, column cosine (made exactly orthogonal), normal.
  const Slice& ref = slices.front();
  Eigen::Vector3d row(ref.orientation[0], ref.orientation[1], ref.orientation[2]);
  Eigen::Vector3d col(ref.orientation[3], ref.orientation[4], ref.orientation[5]);
  if (std::abs(row.norm() - 1) > kOrthonormalTolerance ||
      std::abs(col.norm() - 1) > kOrthonormalTolerance ||
      std::abs(row.dot(col)) > kOrthonormalTolerance) {
    return absl::InvalidArgumentError(
        absl::StrCat(Prefix(dir, ref.header->name), "ImageOrientationPatient ",
                     JoinDecimals(ref.orientation), " is not two orthogonal unit vectors"));
  }
  row.normalize();
  col = (col - row.dot(col) * row).normalized();
  const Eigen::Vector3d normal = row.cross(col);

  for (Slice& s : slices) s.along_normal = s.position.dot(normal);
  std::stable_sort(slices.begin(), slices.end(),
                   [](const Slice& a, const Slice& b) { return a.along_normal < b.along_normal; });

  const size_t n = slices.size();
  std::vector<double> gaps(n - 1);
  for (size_t k = 0; k + 1 < n; ++k) {
    gaps[k] = slices[k + 1].along_normal - slices[k].along_normal;
    if (gaps[k] < kDuplicatePositionMm) {
      return absl::InvalidArgumentError(absl::StrCat(
          series, slices[k].header->name, " and ", slices[k + 1].header->name,
          " have the same position along the slice normal (", slices[k].along_normal,
          " mm): duplicate slices, or several acquisitions/echoes/time points in one series"));
    }
  }
  std::vector<double> sorted_gaps = gaps;
  std::sort(sorted_gaps.begin(), sorted_gaps.end());
  const double expected = sorted_gaps[(sorted_gaps.size() - 1) / 2];  // lower median
  for (size_t k = 0; k + 1 < n; ++k) {
    if (gaps[k] > kMissingSliceFactor * expected) {
      return absl::InvalidArgumentError(absl::StrCat(
          series, "missing slice between ", slices[k].header->name, " and ",
          slices[k + 1].header->name, ": gap ", gaps[k], " mm, expected ", expected, " mm"));
    }
  }
  const double mean = (slices.back().along_normal - slices.front().along_normal) / (n - 1);
  const double tolerance = kUnevenRelTolerance * mean + kUnevenAbsToleranceMm;
  size_t worst = 0;
  for (size_t k = 1; k + 1 < n; ++k) {
    if (std::abs(gaps[k] - mean) > std::abs(gaps[worst] - mean)) worst = k;
  }
  if (std::abs(gaps[worst] - mean) > tolerance) {
    return absl::InvalidArgumentError(
        absl::StrCat(series, "uneven slice spacing: gap between ", slices[worst].header->name,
                     " and ", slices[worst + 1].header->name, " is ", gaps[worst], " mm, mean ",
                     mean, " mm (tolerance ", tolerance, " mm)"));
  }
  // A Volume has an orthogonal grid: slice origins must lie on one line along the normal.
  const double shift_tolerance =
      kInPlaneShiftPixels * std::min(ref.row_spacing, ref.column_spacing) + kUnevenAbsToleranceMm;
  for (const Slice& s : slices) {
    const Eigen::Vector3d d = s.position - slices.front().position;
    const double du = d.dot(row), dv = d.dot(col);
    if (std::abs(du) > shift_tolerance || std::abs(dv) > shift_tolerance) {
      return absl::InvalidArgumentError(absl::StrCat(
          series, s.header->name, " is shifted by (", du, ", ", dv, ") mm in its plane from ",
          slices.front().header->name,
          ": slices not stacked along their normal (gantry tilt or sheared series) are not "
          "supported"));
    }
  }

  const int64_t slice_voxels = int64_t{ref.rows} * ref.columns;
  if (slice_voxels * static_cast<int64_t>(n) > kMaxVoxels) {
    return absl::InvalidArgumentError(absl::StrCat(series, ref.columns, " x ", ref.rows, " x ", n,
                                                   " voxels exceed the limit of ", kMaxVoxels));
  }
  const VoxelType stored = StoredType(ref.bits_allocated, ref.pixel_representation);
  DECIMA_ASSIGN_OR_RETURN(Volume volume,
                          MakeVolume({ref.columns, ref.rows, static_cast<int64_t>(n)}, stored,
                                     Eigen::Vector3d(ref.column_spacing, ref.row_spacing, mean)));
  volume.origin = slices.front().position;
  volume.direction.col(0) = row;
  volume.direction.col(1) = col;
  volume.direction.col(2) = normal;
  volume.modality = ref.header->modality;

  const size_t slice_bytes = slice_voxels * VoxelTypeSize(stored);
  for (size_t k = 0; k < n; ++k) {
    DECIMA_RETURN_IF_ERROR(
        ReadPixels(dir, slices[k], volume.bytes.data() + k * slice_bytes, slice_bytes));
  }

  const bool identity = std::all_of(slices.begin(), slices.end(), [](const Slice& s) {
    return s.slope == 1 && s.intercept == 0;
  });
  if (!identity) {
    switch (stored) {
      case VoxelType::kUInt8:
        Rescale<uint8_t>(slices, slice_voxels, &volume);
        break;
      case VoxelType::kInt8:
        Rescale<int8_t>(slices, slice_voxels, &volume);
        break;
      case VoxelType::kUInt16:
        Rescale<uint16_t>(slices, slice_voxels, &volume);
        break;
      case VoxelType::kInt16:
        Rescale<int16_t>(slices, slice_voxels, &volume);
        break;
      case VoxelType::kUInt32:
        Rescale<uint32_t>(slices, slice_voxels, &volume);
        break;
      default:
        Rescale<int32_t>(slices, slice_voxels, &volume);
        break;
    }
  }
  DECIMA_RETURN_IF_ERROR(Validate(volume, dir.string()));
  return volume;
}

}  // namespace

bool HasDicomMarker(const fs::path& path, std::string* reason) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    *reason = "cannot be opened";
    return false;
  }
  char buf[132];
  in.read(buf, sizeof(buf));
  if (in.gcount() != static_cast<std::streamsize>(sizeof(buf))) {
    *reason = "shorter than the 132-byte DICOM preamble";
    return false;
  }
  if (std::memcmp(buf + 128, "DICM", 4) != 0) {
    *reason = "no DICM marker at byte 128";
    return false;
  }
  return true;
}

absl::StatusOr<std::vector<DicomSeriesInfo>> ListDicomSeries(const fs::path& dir) {
  DECIMA_ASSIGN_OR_RETURN(FolderScan scan, ScanFolder(dir));
  return SeriesInfos(GroupBySeries(scan));
}

std::string FormatPersonName(const std::string& pn) {
  const std::vector<std::string> parts =
      absl::StrSplit(pn.substr(0, pn.find('=')), '^');  // family, given, middle, prefix, suffix
  std::string rest;
  for (size_t i = 1; i < parts.size(); ++i) {
    const absl::string_view p = absl::StripAsciiWhitespace(parts[i]);
    if (!p.empty()) absl::StrAppend(&rest, rest.empty() ? "" : " ", p);
  }
  const absl::string_view family = absl::StripAsciiWhitespace(parts.front());
  if (family.empty()) return rest;
  return rest.empty() ? std::string(family) : absl::StrCat(family, ", ", rest);
}

absl::StatusOr<Volume> ReadDicomSeries(const fs::path& dir, const std::string& series_instance_uid,
                                       DicomDescription* description) {
  DECIMA_ASSIGN_OR_RETURN(FolderScan scan, ScanFolder(dir));
  const auto series = GroupBySeries(scan);
  auto it = series.begin();
  if (series_instance_uid.empty()) {
    if (series.size() > 1) {
      return absl::InvalidArgumentError(absl::StrCat(
          dir.string(), ": holds ", series.size(),
          " series, pick one by SeriesInstanceUID: ", ListForMessage(SeriesInfos(series))));
    }
  } else {
    it = series.find(series_instance_uid);
    if (it == series.end()) {
      return absl::NotFoundError(
          absl::StrCat(dir.string(), ": no series with uid ", series_instance_uid,
                       "; available: ", ListForMessage(SeriesInfos(series))));
    }
  }
  if (description != nullptr) {
    const SliceHeader& h = *it->second.front();
    *description = {h.patient_name,      h.patient_id,  h.study_date,
                    h.study_description, h.description, h.modality};
  }
  return AssembleSeries(dir, it->first, it->second);
}

}  // namespace decima
