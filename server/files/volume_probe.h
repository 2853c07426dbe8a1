// A volume's files as uploaded -> what core/io's header-only ProbeVolume says about them: the
// format (by core/io's one extension table, or the DICM marker), the file the pipeline opens,
// dims, spacing, modality and voxel type, so garbage is refused before a job is queued. No
// voxel is decoded here: this runs in the RPC thread (a decompression bomb costs nothing).
#pragma once

#include <array>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "decima/v1/volumes.pb.h"

namespace decima::server {

struct VolumeHeader {
  v1::VolumeFormat format = v1::VOLUME_FORMAT_UNSPECIFIED;
  // What the pipeline reads: the header file, or the folder of a DICOM series.
  std::filesystem::path input;
  bool parsed = false;  // false: dims etc. unknown here, the job's load stage will tell
  std::array<int64_t, 3> dims{0, 0, 0};
  std::array<double, 3> spacing{0, 0, 0};
  std::string modality;
  std::string scalar_type;
};

// `dir` holds the volume's files at their manifest paths `files`. `format` UNSPECIFIED detects
// it from the names (.nii/.nii.gz/.hdr/.img, .mha/.mhd, .nrrd/.nhdr; several files or a "DICM"
// preamble: DICOM). INVALID_ARGUMENT naming the file and the problem for an unknown format, a
// header that does not parse, dims out of range, or data shorter than the header promises.
// DICOM: the series are listed from the headers (no pixel data); `series_instance_uid` picks
// one (INVALID_ARGUMENT listing the series present when none matches); without it the files must
// hold exactly one series (INVALID_ARGUMENT listing them otherwise). Messages name files by their
// manifest paths, never by their place on the server.
absl::StatusOr<VolumeHeader> ProbeVolume(const std::filesystem::path& dir,
                                         const std::vector<std::string>& files,
                                         v1::VolumeFormat format,
                                         const std::string& series_instance_uid = "");

}  // namespace decima::server

namespace decima::server {

// The path the pipeline reads for a stored volume whose files are under `files_dir`: the folder
// for DICOM, else its header file.
std::filesystem::path VolumeInput(const std::filesystem::path& files_dir, const v1::Volume& volume);

}  // namespace decima::server
