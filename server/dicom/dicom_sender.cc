#include "server/dicom/dicom_sender.h"

// clang-format off
#include "dcmtk/config/osconfig.h"  // must come first
// clang-format on
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/scu.h"

#include <curl/curl.h>
#include <stdlib.h>

#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace decima::server {
namespace fs = std::filesystem;
namespace {

struct FileInfo {
  fs::path path;
  std::string sop_class, sop_instance, transfer_syntax;
};

absl::StatusOr<FileInfo> ReadInfo(const fs::path& p) {
  DcmFileFormat ff;
  OFCondition c = ff.loadFileUntilTag(p.c_str(), EXS_Unknown, EGL_noChange, DCM_MaxReadLength,
                                      ERM_autoDetect, DCM_PixelData);
  if (c.bad()) return absl::InvalidArgumentError(absl::StrCat(p.string(), ": ", c.text()));
  FileInfo f;
  f.path = p;
  OFString v;
  ff.getDataset()->findAndGetOFString(DCM_SOPClassUID, v);
  f.sop_class = v.c_str();
  ff.getDataset()->findAndGetOFString(DCM_SOPInstanceUID, v);
  f.sop_instance = v.c_str();
  ff.getMetaInfo()->findAndGetOFString(DCM_TransferSyntaxUID, v);
  f.transfer_syntax = v.c_str();
  if (f.sop_class.empty() || f.sop_instance.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(p.string(), ": no SOP Class/Instance UID"));
  }
  return f;
}

size_t AppendBody(char* data, size_t size, size_t n, void* user) {
  auto* out = static_cast<std::string*>(user);
  // Bounded: a STOW answer is a small JSON document.
  if (out->size() + size * n > (size_t{16} << 20)) return 0;
  out->append(data, size * n);
  return size * n;
}

absl::StatusOr<std::string> ReadAll(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(p.string(), ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

absl::StatusOr<std::string> StowRs(const DicomDestination& d, const std::vector<FileInfo>& files) {
  std::random_device rd;
  const std::string boundary = absl::StrCat("decima-", rd(), "-", rd());
  std::string body;
  for (const auto& f : files) {
    auto bytes = ReadAll(f.path);
    if (!bytes.ok()) return bytes.status();
    absl::StrAppend(&body, "--", boundary, "\r\nContent-Type: application/dicom\r\n\r\n", *bytes,
                    "\r\n");
  }
  absl::StrAppend(&body, "--", boundary, "--\r\n");

  std::unique_ptr<CURL, void (*)(CURL*)> curl(curl_easy_init(), curl_easy_cleanup);
  if (!curl) return absl::InternalError("STOW-RS: curl_easy_init failed");
  curl_slist* headers = nullptr;
  headers = curl_slist_append(
      headers, absl::StrCat("Content-Type: multipart/related; type=\"application/dicom\"; "
                            "boundary=",
                            boundary)
                   .c_str());
  headers = curl_slist_append(headers, "Accept: application/dicom+json");
  if (!d.bearer_token.empty()) {
    headers =
        curl_slist_append(headers, absl::StrCat("Authorization: Bearer ", d.bearer_token).c_str());
  }
  std::unique_ptr<curl_slist, void (*)(curl_slist*)> header_list(headers, curl_slist_free_all);
  std::string answer;
  CURL* c = curl.get();
  curl_easy_setopt(c, CURLOPT_URL, d.stow_url.c_str());
  curl_easy_setopt(c, CURLOPT_HTTPHEADER, headers);
  curl_easy_setopt(c, CURLOPT_POST, 1L);
  curl_easy_setopt(c, CURLOPT_POSTFIELDS, body.data());
  curl_easy_setopt(c, CURLOPT_POSTFIELDSIZE_LARGE, static_cast<curl_off_t>(body.size()));
  curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, AppendBody);
  curl_easy_setopt(c, CURLOPT_WRITEDATA, &answer);
  curl_easy_setopt(c, CURLOPT_TIMEOUT, static_cast<long>(d.timeout_seconds));
  curl_easy_setopt(c, CURLOPT_CONNECTTIMEOUT, 10L);
  curl_easy_setopt(c, CURLOPT_NOSIGNAL, 1L);
  curl_easy_setopt(c, CURLOPT_TCP_NODELAY, 1L);
  curl_easy_setopt(c, CURLOPT_PROTOCOLS_STR, "http,https");
  if (!d.ca_file.empty()) curl_easy_setopt(c, CURLOPT_CAINFO, d.ca_file.c_str());
  if (!d.username.empty()) {
    curl_easy_setopt(c, CURLOPT_HTTPAUTH, CURLAUTH_BASIC);
    curl_easy_setopt(c, CURLOPT_USERNAME, d.username.c_str());
    curl_easy_setopt(c, CURLOPT_PASSWORD, d.password.c_str());
  }
  const CURLcode rc = curl_easy_perform(c);
  if (rc != CURLE_OK) {
    return absl::UnavailableError(
        absl::StrCat("STOW-RS ", d.stow_url, ": ", curl_easy_strerror(rc)));
  }
  long http = 0;
  curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &http);
  nlohmann::json doc = nlohmann::json::parse(answer, nullptr, false);
  // FailedSOPSequence: only items count (Orthanc sends the attribute empty on success).
  std::vector<std::string> failed;
  if (doc.is_object() && doc.contains("00081198") && doc["00081198"].contains("Value")) {
    for (const auto& item : doc["00081198"]["Value"]) {
      std::string uid = "?", reason = "?";
      if (item.contains("00081155") && item["00081155"].contains("Value")) {
        uid = item["00081155"]["Value"][0].dump();
      }
      if (item.contains("00081197") && item["00081197"].contains("Value")) {
        reason = item["00081197"]["Value"][0].dump();
      }
      failed.push_back(absl::StrCat(uid, " (failure reason ", reason, ")"));
    }
  }
  if (!failed.empty()) {
    return absl::FailedPreconditionError(absl::StrCat("STOW-RS ", d.stow_url, ": HTTP ", http,
                                                      ", refused ", absl::StrJoin(failed, ", ")));
  }
  if (http < 200 || http >= 300) {
    return (http == 401 || http == 403 || http >= 500 ? absl::UnavailableError
                                                      : absl::FailedPreconditionError)(
        absl::StrCat("STOW-RS ", d.stow_url, ": HTTP ", http, " ", answer.substr(0, 200)));
  }
  size_t stored = 0;
  if (doc.is_object() && doc.contains("00081199") && doc["00081199"].contains("Value")) {
    stored = doc["00081199"]["Value"].size();
  }
  if (stored != files.size()) {
    return absl::FailedPreconditionError(absl::StrCat("STOW-RS ", d.stow_url, ": HTTP ", http,
                                                      " but ", stored, " of ", files.size(),
                                                      " instances listed as stored"));
  }
  return absl::StrCat(stored, " instances stored by STOW-RS at ", d.stow_url);
}

absl::StatusOr<std::string> CStore(const DicomDestination& d, const std::vector<FileInfo>& files) {
  DcmSCU scu;
  scu.setAETitle(d.calling_aet.empty() ? "DECIMA" : d.calling_aet.c_str());
  scu.setPeerHostName(d.host.c_str());
  scu.setPeerPort(static_cast<Uint16>(d.port));
  scu.setPeerAETitle(d.aet.c_str());
  scu.setACSETimeout(static_cast<Uint32>(d.timeout_seconds));
  scu.setDIMSETimeout(static_cast<Uint32>(d.timeout_seconds));
  scu.setDIMSEBlockingMode(DIMSE_NONBLOCKING);
  scu.setConnectionTimeout(10);
  // Exactly the SOP classes sent, each with the files' own syntaxes plus the two uncompressed
  // little-endian ones every SCP accepts.
  std::map<std::string, std::set<std::string>> contexts;
  for (const auto& f : files) {
    auto& ts = contexts[f.sop_class];
    if (!f.transfer_syntax.empty()) ts.insert(f.transfer_syntax);
    ts.insert(UID_LittleEndianExplicitTransferSyntax);
    ts.insert(UID_LittleEndianImplicitTransferSyntax);
  }
  for (const auto& [sop_class, syntaxes] : contexts) {
    OFList<OFString> ts;
    for (const auto& s : syntaxes) ts.push_back(s.c_str());
    scu.addPresentationContext(sop_class.c_str(), ts);
  }
  const std::string peer = absl::StrCat(d.aet, "@", d.host, ":", d.port);
  if (OFCondition c = scu.initNetwork(); c.bad()) {
    return absl::InternalError(absl::StrCat("C-STORE ", peer, ": ", c.text()));
  }
  if (OFCondition c = scu.negotiateAssociation(); c.bad()) {
    return absl::UnavailableError(absl::StrCat("C-STORE ", peer, ": association: ", c.text()));
  }
  std::vector<std::string> problems;
  for (const auto& f : files) {
    Uint16 status = 0;
    OFCondition c = scu.sendSTORERequest(0, f.path.c_str(), nullptr, status);
    if (c.bad()) {
      problems.push_back(absl::StrCat(f.sop_instance, ": ", c.text()));
      break;
    }
    if (status != 0) {
      problems.push_back(absl::StrCat(f.sop_instance, ": status 0x", absl::Hex(status)));
    }
  }
  scu.releaseAssociation();
  if (!problems.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat("C-STORE ", peer, ": ", absl::StrJoin(problems, "; ")));
  }
  return absl::StrCat(files.size(), " instances stored by C-STORE at ", peer);
}

}  // namespace

void EnableDcmtkTcpNoDelay() { setenv("TCP_NODELAY", "1", /*overwrite=*/1); }

absl::StatusOr<std::string> SendDicomFiles(const DicomDestination& dest,
                                           const std::vector<fs::path>& paths) {
  if (!dest.configured()) return absl::FailedPreconditionError("no destination configured");
  std::vector<FileInfo> files;
  for (const auto& p : paths) {
    auto f = ReadInfo(p);
    if (!f.ok()) return f.status();
    files.push_back(std::move(*f));
  }
  if (files.empty()) return absl::InvalidArgumentError("no file to send");
  return dest.stow_url.empty() ? CStore(dest, files) : StowRs(dest, files);
}

}  // namespace decima::server
