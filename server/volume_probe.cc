#include "server/volume_probe.h"

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "core/io/dicom.h"
#include "core/io/volume_io.h"
#include "core/volume/volume.h"

namespace decima::server {
namespace fs = std::filesystem;
namespace {

v1::VolumeFormat ToProto(io::VolumeFormat f) {
  switch (f) {
    case io::VolumeFormat::kNifti:
      return v1::VOLUME_FORMAT_NIFTI;
    case io::VolumeFormat::kMetaImage:
      return v1::VOLUME_FORMAT_METAIMAGE;
    case io::VolumeFormat::kNrrd:
      return v1::VOLUME_FORMAT_NRRD;
    case io::VolumeFormat::kDirectory:
      return v1::VOLUME_FORMAT_DICOM;
    case io::VolumeFormat::kUnknown:
      break;
  }
  return v1::VOLUME_FORMAT_UNSPECIFIED;
}

// The header file among `files` (core/io's extension table) or "" if none.
std::string MainFile(const std::vector<std::string>& files) {
  for (const auto& f : files) {
    if (io::VolumeFormatFromName(f) != io::VolumeFormat::kUnknown) return f;
  }
  return {};
}

}  // namespace

absl::StatusOr<VolumeHeader> ProbeVolume(const fs::path& dir, const std::vector<std::string>& files,
                                         v1::VolumeFormat format) {
  if (files.empty()) return absl::InvalidArgumentError("files: a volume needs at least one file");
  const std::string main = MainFile(files);
  v1::VolumeFormat detected = ToProto(io::VolumeFormatFromName(main));
  std::string reason;
  if (main.empty() && (files.size() > 1 || decima::HasDicomMarker(dir / files[0], &reason) ||
                       absl::EndsWith(absl::AsciiStrToLower(files[0]), ".dcm"))) {
    detected = v1::VOLUME_FORMAT_DICOM;
  }
  if (format == v1::VOLUME_FORMAT_UNSPECIFIED) format = detected;
  if (format == v1::VOLUME_FORMAT_UNSPECIFIED) {
    return absl::InvalidArgumentError(absl::StrCat(
        files[0],
        ": unknown volume format (expected .nii, .nii.gz, .hdr/.img, .mha, .mhd, .nrrd, .nhdr "
        "or DICOM files)"));
  }
  if (format != v1::VOLUME_FORMAT_DICOM && format != detected) {
    return absl::InvalidArgumentError(absl::StrCat("format ", v1::VolumeFormat_Name(format),
                                                   ": no file with a matching extension"));
  }
  VolumeHeader h;
  h.format = format;
  if (format == v1::VOLUME_FORMAT_DICOM) {
    // Every file must carry the marker; dims come from the job's load stage.
    for (const auto& f : files) {
      if (!decima::HasDicomMarker(dir / f, &reason)) {
        return absl::InvalidArgumentError(absl::StrCat(f, ": not a DICOM file (", reason, ")"));
      }
    }
    h.input = dir;
    return h;
  }
  // The header only, by the same readers as the job's load stage: no voxel is decoded here.
  auto probe = io::ProbeVolume(dir / main);
  if (!probe.ok()) {
    // Name the file as the client did, not by its path on the server.
    std::string msg(probe.status().message());
    const std::string server_path = dir.string() + "/";
    for (size_t at; (at = msg.find(server_path)) != std::string::npos;)
      msg.erase(at, server_path.size());
    return absl::Status(probe.status().code() == absl::StatusCode::kNotFound
                            ? absl::StatusCode::kInvalidArgument
                            : probe.status().code(),
                        msg);
  }
  h.parsed = true;
  h.dims = probe->dims;
  h.spacing = probe->spacing;
  h.modality = probe->modality;
  h.scalar_type = std::string(VoxelTypeName(probe->type));
  h.input = dir / main;
  return h;
}

fs::path VolumeInput(const fs::path& files_dir, const v1::Volume& volume) {
  if (volume.format() == v1::VOLUME_FORMAT_DICOM || volume.files().empty()) return files_dir;
  std::vector<std::string> names;
  for (const auto& f : volume.files()) names.push_back(f.path());
  const std::string main = MainFile(names);
  return files_dir / (main.empty() ? volume.files(0).path() : main);
}

}  // namespace decima::server
