#include "server/files/volume_probe.h"

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

namespace {

// `status` with every mention of `dir` removed, so that a client reads its own file names.
absl::Status WithoutServerPath(const absl::Status& status, const fs::path& dir) {
  std::string msg(status.message());
  for (const std::string& prefix : {dir.string() + "/", dir.string()}) {
    for (size_t at; (at = msg.find(prefix)) != std::string::npos;) msg.erase(at, prefix.size());
  }
  return absl::Status(status.code(), msg);
}

}  // namespace

absl::StatusOr<VolumeHeader> ProbeVolume(const fs::path& dir, const std::vector<std::string>& files,
                                         v1::VolumeFormat format,
                                         const std::string& series_instance_uid) {
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
    auto series = decima::ListDicomSeries(dir);
    if (!series.ok()) return WithoutServerPath(series.status(), dir);
    auto describe = [&] {
      std::string list;
      for (const auto& s : *series) {
        absl::StrAppend(&list, "\n  ", s.series_instance_uid, "  ", s.modality, "  ", s.file_count,
                        " files", s.series_description.empty() ? "" : "  ", s.series_description);
      }
      return list;
    };
    const DicomSeriesInfo* chosen = nullptr;
    for (const auto& s : *series) {
      if (s.series_instance_uid == series_instance_uid) chosen = &s;
    }
    if (!series_instance_uid.empty() && chosen == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat("series_instance_uid ", series_instance_uid,
                       " is not among the series of these files:", describe()));
    }
    if (series_instance_uid.empty()) {
      if (series->size() > 1) {
        return absl::InvalidArgumentError(absl::StrCat(
            "the files hold ", series->size(),
            " series; choose one with series_instance_uid (decima submit --series UID):",
            describe()));
      }
      chosen = &series->front();
    }
    h.modality = chosen->modality;
    h.input = dir;
    return h;
  }
  // The header only, by the same readers as the job's load stage: no voxel is decoded here.
  auto probe = io::ProbeVolume(dir / main);
  if (!probe.ok()) {
    // Name the file as the client did, not by its path on the server.
    return WithoutServerPath(absl::Status(probe.status().code() == absl::StatusCode::kNotFound
                                              ? absl::StatusCode::kInvalidArgument
                                              : probe.status().code(),
                                          probe.status().message()),
                             dir);
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
