#include "server/volume_probe.h"

#include <cstring>
#include <fstream>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "core/io/volume_io.h"
#include "core/volume/volume.h"

namespace decima::server {
namespace fs = std::filesystem;
namespace {

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
