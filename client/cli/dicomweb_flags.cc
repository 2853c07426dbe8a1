#include "client/cli/dicomweb_flags.h"

#include <CLI/CLI.hpp>
#include <cstdio>
#include <fstream>

namespace decima::client {

void AddDicomWebFlags(CLI::App* cmd, DicomWebFlags& f, bool is_pull) {
  DicomWebPull& web = f.web;
  auto* url = cmd->add_option("--dicomweb", web.base_url,
                              "DICOMweb base URL: pull the series by WADO-RS instead of INPUT");
  auto* study = cmd->add_option("--study", web.study_uid, "StudyInstanceUID to pull");
  if (is_pull) {
    cmd->add_option("--series", web.series_uid, "SeriesInstanceUID (default: the whole study)")
        ->needs(study);
  }
  cmd->add_option("--dicomweb-user", web.user, "NAME:PASSWORD for HTTP basic auth")
      ->envname("DECIMA_DICOMWEB_USER");
  cmd->add_option("--dicomweb-token-file", f.token_file, "bearer token for the DICOMweb server")
      ->check(CLI::ExistingFile);
  cmd->add_option("--dicomweb-ca", web.ca_file, "PEM roots for https (default: the system's)")
      ->check(CLI::ExistingFile);
  url->needs(study);
  study->needs(url);
  if (is_pull) {
    url->required();
    study->required();
  }
}

int ReadDicomWebToken(DicomWebFlags& f) {
  if (f.token_file.empty()) return kOk;
  std::ifstream in(f.token_file);
  std::getline(in, f.web.bearer_token);
  if (f.web.bearer_token.empty()) {
    std::fprintf(stderr, "decima: --dicomweb-token-file %s: empty\n", f.token_file.c_str());
    return kUsage;
  }
  return kOk;
}

int PullDicomWebInto(CliContext& ctx, DicomWebFlags& f, const std::filesystem::path& dir,
                     bool json_line, const std::filesystem::path& remove_on_error) {
  DicomWebResult pulled;
  std::string err;
  if (!PullDicomWeb(f.web, dir, &pulled, &err)) {
    if (!remove_on_error.empty()) std::filesystem::remove_all(remove_on_error);
    std::fprintf(stderr, "decima: dicomweb: %s\n", err.c_str());
    return kError;
  }
  if (json_line) {
    std::printf("{\"instances\":%d,\"bytes\":%lld,\"seconds\":%.4f,\"out\":\"%s\"}\n",
                pulled.instances, static_cast<long long>(pulled.bytes), pulled.seconds,
                dir.c_str());
  } else if (!ctx.flags.quiet) {
    std::fprintf(stderr, "decima: pulled %d instances (%lld bytes) by WADO-RS in %.3f s\n",
                 pulled.instances, static_cast<long long>(pulled.bytes), pulled.seconds);
  }
  return kOk;
}

}  // namespace decima::client
