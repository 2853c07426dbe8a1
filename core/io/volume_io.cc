// ReadVolume(): format dispatch by extension, then by magic bytes.
#include <zlib.h>

#include <cstring>

#include "core/common/status.h"
#include "core/io/dicom.h"
#include "core/io/io_util.h"
#include "core/io/volume_io.h"

namespace decima::io {
namespace {

namespace fs = std::filesystem;

}  // namespace

VolumeFormat VolumeFormatFromName(const fs::path& path) {
  const std::string name = internal::LowerName(path);
  for (const char* ext : {".nii", ".nii.gz", ".hdr", ".hdr.gz", ".img", ".img.gz"}) {
    if (internal::EndsWith(name, ext)) return VolumeFormat::kNifti;
  }
  if (internal::EndsWith(name, ".mha") || internal::EndsWith(name, ".mhd")) {
    return VolumeFormat::kMetaImage;
  }
  if (internal::EndsWith(name, ".nrrd") || internal::EndsWith(name, ".nhdr")) {
    return VolumeFormat::kNrrd;
  }
  return VolumeFormat::kUnknown;
}

namespace {

bool LooksLikeNiftiHeader(const uint8_t* b, size_t n) {
  if (n >= 348) {
    int32_t size;
    std::memcpy(&size, b, 4);
    if ((size == 348 || size == 0x5c010000) &&
        (std::memcmp(b + 344, "n+1\0", 4) == 0 || std::memcmp(b + 344, "ni1\0", 4) == 0)) {
      return true;
    }
  }
  return n >= 12 && (std::memcmp(b + 4, "n+2\0\r\n\032\n", 8) == 0 ||
                     std::memcmp(b + 4, "ni2\0\r\n\032\n", 8) == 0);
}

// The first up to 348 bytes of a gzip stream (uncompress only what the sniffing needs).
std::string GunzipHead(const std::string& compressed) {
  std::string out(348, '\0');
  z_stream zs{};
  if (inflateInit2(&zs, 15 + 32) != Z_OK) return {};
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(compressed.data()));
  zs.avail_in = static_cast<uInt>(compressed.size());
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = static_cast<uInt>(out.size());
  inflate(&zs, Z_SYNC_FLUSH);
  out.resize(out.size() - zs.avail_out);
  inflateEnd(&zs);
  return out;
}

}  // namespace

VolumeFormat DetectVolumeFormat(const fs::path& path) {
  std::error_code ec;
  if (fs::is_directory(path, ec)) return VolumeFormat::kDirectory;
  if (const VolumeFormat f = VolumeFormatFromName(path); f != VolumeFormat::kUnknown) return f;
  auto head = internal::ReadFileHead(path, 4096);
  if (!head.ok()) return VolumeFormat::kUnknown;
  std::string h = *head;
  if (internal::HasGzipMagic(h)) h = GunzipHead(h);
  if (LooksLikeNiftiHeader(reinterpret_cast<const uint8_t*>(h.data()), h.size())) {
    return VolumeFormat::kNifti;
  }
  if (h.rfind("NRRD000", 0) == 0) return VolumeFormat::kNrrd;
  for (const char* key : {"ObjectType", "NDims"}) {
    if (h.rfind(key, 0) == 0) return VolumeFormat::kMetaImage;
  }
  return VolumeFormat::kUnknown;
}

absl::StatusOr<VolumeHeader> ProbeVolume(const fs::path& path) {
  std::error_code ec;
  if (!fs::exists(path, ec)) {
    return absl::NotFoundError(absl::StrCat(path.string(), ": file does not exist"));
  }
  VolumeHeader h;
  h.format = DetectVolumeFormat(path);
  h.input = path;
  absl::StatusOr<Volume> v = absl::UnknownError("unset");
  switch (h.format) {
    case VolumeFormat::kNifti:
      v = internal::ReadNifti(path, internal::ReadMode::kHeaderOnly);
      break;
    case VolumeFormat::kMetaImage:
      v = internal::ReadMetaImage(path, internal::ReadMode::kHeaderOnly);
      break;
    case VolumeFormat::kNrrd:
      v = internal::ReadNrrd(path, internal::ReadMode::kHeaderOnly);
      break;
    case VolumeFormat::kDirectory: {
      int files = 0;
      for (const auto& e : fs::recursive_directory_iterator(path, ec)) {
        if (!e.is_regular_file(ec)) continue;
        std::string reason;
        if (!HasDicomMarker(e.path(), &reason)) {
          return internal::Invalid(fs::relative(e.path(), path, ec), "not a DICOM file (", reason,
                                   ")");
        }
        ++files;
      }
      if (ec) return internal::Invalid(path, ec.message());
      if (files == 0) return internal::Invalid(path, "no DICOM file in the folder");
      return h;
    }
    case VolumeFormat::kUnknown:
      return internal::Invalid(path,
                               "unknown volume format: expected NIfTI (.nii, .nii.gz, .hdr/.img), "
                               "MetaImage (.mha, .mhd) or NRRD (.nrrd, .nhdr)");
  }
  if (!v.ok()) return v.status();
  h.parsed = true;
  h.dims = v->dims;
  for (int i = 0; i < 3; ++i) h.spacing[i] = v->spacing[i];
  h.modality = v->modality;
  h.type = v->type;
  return h;
}

absl::StatusOr<Volume> ReadVolume(const fs::path& path) {
  std::error_code ec;
  if (!fs::exists(path, ec)) {
    return absl::NotFoundError(absl::StrCat(path.string(), ": file does not exist"));
  }
  switch (DetectVolumeFormat(path)) {
    case VolumeFormat::kNifti:
      return ReadNifti(path);
    case VolumeFormat::kMetaImage:
      return ReadMetaImage(path);
    case VolumeFormat::kNrrd:
      return ReadNrrd(path);
    case VolumeFormat::kDirectory:
      return ReadDicomSeries(path);
    case VolumeFormat::kUnknown:
      break;
  }
  return internal::Invalid(path,
                           "unknown volume format: expected NIfTI (.nii, .nii.gz, .hdr/.img), "
                           "MetaImage (.mha, .mhd) or NRRD (.nrrd, .nhdr)");
}

}  // namespace decima::io
