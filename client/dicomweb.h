// DICOMweb pull for `decima submit --dicomweb URL --study UID [--series UID]` and
// `decima pull`: WADO-RS retrieve of a study or series (GET {URL}/studies/{study}[/series/
// {series}], Accept: multipart/related; type="application/dicom") into a folder, one file per
// part, which then uploads as any DICOM folder.
//
// Client-side on purpose: the credentials for the PACS stay with the user who has them, the
// server makes no outbound HTTP request to a URL a caller chose (no server-side request
// forgery), and the server's API needs no change; the server's own PACS link is the C-STORE
// receiver. libcurl does TLS (system trust store or --dicomweb-ca), basic and bearer auth.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

namespace decima::client {

struct DicomWebPull {
  std::string base_url;  // e.g. https://pacs/dicom-web (no trailing /studies)
  std::string study_uid;
  std::string series_uid;    // "" = the whole study
  std::string user;          // "name:password" for basic auth, "" none
  std::string bearer_token;  // "" none
  std::string ca_file;       // "" = system trust store
  int timeout_seconds = 300;
  int64_t max_bytes = int64_t{4} << 30;  // larger answers are refused
  int max_instances = 100000;            // answers with more parts are refused
};

struct DicomWebResult {
  int instances = 0;
  int64_t bytes = 0;
  double seconds = 0;  // the HTTP transfer and the parse, wall clock
};

// Writes each application/dicom part to `out_dir`/NNNNN.dcm (created if missing). False with
// `*error` naming the URL and the problem: an HTTP status other than 200 (with the start of the
// body), a transfer error or timeout, an answer that is not multipart/related, has no boundary,
// a part that is not application/dicom, no instance, more than max_bytes or more than
// max_instances parts. The answer is parsed as it arrives and each part written as it comes:
// memory does not grow with the answer.
bool PullDicomWeb(const DicomWebPull& pull, const std::filesystem::path& out_dir,
                  DicomWebResult* result, std::string* error);

// The UIDs pass this before they go into a URL: digits and dots, 1..64 characters.
bool IsDicomUid(const std::string& uid);

}  // namespace decima::client
