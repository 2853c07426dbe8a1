// A volume made on the server from local files: the files collected and hashed, uploaded
// (only what the server lacks, resuming), then CreateVolume. Used by `submit`, one INPUT or a
// batch's studies.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "client/cli/context.h"

namespace decima::client {

// Uploads the files of INPUT and creates a volume; returns its name in *name. With a job
// request id, the volume's request id is derived from it and the files, so a retried submit
// finds the same volume (and the server can tell a retry from a different request).
int MakeVolume(CliContext& ctx, const std::filesystem::path& input, const std::string& series,
               const std::string& request_id, std::string* name);

// The upload and CreateVolume half of MakeVolume, for files already chosen (a batch's DICOM
// series). `input` names the volume in progress lines.
int UploadVolume(CliContext& ctx, const std::filesystem::path& input, std::vector<InputFile> files,
                 const std::string& display_name, const std::string& series,
                 const std::string& request_id, std::string* name);

}  // namespace decima::client
