// The DICOMweb (WADO-RS) flags shared by `submit --dicomweb` and `pull`, and the pull itself
// into a folder (client/dicomweb.h).
#pragma once

#include <filesystem>
#include <string>

#include "client/cli/context.h"
#include "client/dicomweb.h"

namespace decima::client {

struct DicomWebFlags {
  DicomWebPull web;
  std::string token_file;
};

// `submit` has its own --series (the series to process), which also names the series to
// pull; `pull` gets one here (`is_pull`), and --dicomweb and --study are required there.
void AddDicomWebFlags(CLI::App* cmd, DicomWebFlags& f, bool is_pull);

// Pulls into `dir` (after reading --dicomweb-token-file) and says how much came; with
// `json_line` (pull -o json) as a JSON line on stdout. Removes `remove_on_error` on failure.
int PullDicomWebInto(CliContext& ctx, DicomWebFlags& f, const std::filesystem::path& dir,
                     bool json_line, const std::filesystem::path& remove_on_error);
// Reads --dicomweb-token-file into the bearer token; kUsage when it is empty.
int ReadDicomWebToken(DicomWebFlags& f);

}  // namespace decima::client
