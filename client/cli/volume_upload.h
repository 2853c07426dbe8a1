// A volume made on the server from local files: the files collected and hashed, uploaded
// (only what the server lacks, resuming), then CreateVolume. Used by `submit`, one INPUT or a
// batch's studies.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "client/cli/context.h"
#include "decima/v1/jobs.pb.h"

namespace decima::client {

// Issue 30: asks the server (Jobs.CheckJobMemory) whether a job with `spec` on INPUT fits its
// job memory limit, from INPUT's header alone (core/io ProbeVolume: the same header reader the
// server runs on the upload, so one definition of the formats), before a byte is uploaded.
// Returns kOk when it fits or the check cannot be made here, else the refusal as Report gives
// it (the server's message: size, estimate, limit and the flag that raises it). Not checked:
// - a DICOM folder: the series' dims are known only after reading its files (the server checks
//   at CreateJob, after the upload, as before);
// - a file whose header does not parse: the upload goes on and CreateVolume names the problem,
//   so a bad file gets the same error from every client;
// - a server older than the RPC (UNIMPLEMENTED): CreateJob refuses as before.
int CheckJobMemoryBeforeUpload(CliContext& ctx, const std::filesystem::path& input,
                               const v1::JobSpec& spec);

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
