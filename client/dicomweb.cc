#include "client/dicomweb.h"

#include <curl/curl.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <memory>
#include <string_view>

namespace decima::client {
namespace fs = std::filesystem;
namespace {

struct Transfer {
  std::string body;
  std::string content_type;
  int64_t max_bytes = 0;
  bool too_big = false;
};

size_t OnBody(char* data, size_t size, size_t n, void* user) {
  auto* t = static_cast<Transfer*>(user);
  const size_t len = size * n;
  if (static_cast<int64_t>(t->body.size() + len) > t->max_bytes) {
    t->too_big = true;
    return 0;
  }
  t->body.append(data, len);
  return len;
}

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

size_t OnHeader(char* data, size_t size, size_t n, void* user) {
  auto* t = static_cast<Transfer*>(user);
  const std::string line(data, size * n);
  if (Lower(line.substr(0, 13)) == "content-type:") {
    std::string v = line.substr(13);
    while (!v.empty() && (v.back() == '\r' || v.back() == '\n')) v.pop_back();
    t->content_type = v;
  }
  return size * n;
}

// The boundary parameter of a multipart Content-Type, unquoted; "" if absent.
std::string Boundary(const std::string& content_type) {
  const std::string lower = Lower(content_type);
  size_t p = lower.find("boundary=");
  if (p == std::string::npos) return "";
  std::string b = content_type.substr(p + 9);
  if (!b.empty() && b[0] == '"') {
    const size_t end = b.find('"', 1);
    return end == std::string::npos ? "" : b.substr(1, end - 1);
  }
  const size_t end = b.find_first_of("; \t\r\n");
  return end == std::string::npos ? b : b.substr(0, end);
}

}  // namespace

bool IsDicomUid(const std::string& uid) {
  if (uid.empty() || uid.size() > 64) return false;
  return std::all_of(uid.begin(), uid.end(),
                     [](char c) { return (c >= '0' && c <= '9') || c == '.'; });
}

bool PullDicomWeb(const DicomWebPull& pull, const fs::path& out_dir, DicomWebResult* result,
                  std::string* error) {
  const auto t0 = std::chrono::steady_clock::now();
  if (!IsDicomUid(pull.study_uid) || (!pull.series_uid.empty() && !IsDicomUid(pull.series_uid))) {
    *error = "--study / --series: a DICOM UID is digits and dots, at most 64 characters";
    return false;
  }
  std::string url = pull.base_url;
  while (!url.empty() && url.back() == '/') url.pop_back();
  url += "/studies/" + pull.study_uid;
  if (!pull.series_uid.empty()) url += "/series/" + pull.series_uid;

  std::unique_ptr<CURL, void (*)(CURL*)> curl(curl_easy_init(), curl_easy_cleanup);
  if (!curl) {
    *error = "curl_easy_init failed";
    return false;
  }
  curl_slist* headers = nullptr;
  headers = curl_slist_append(headers, "Accept: multipart/related; type=\"application/dicom\"");
  if (!pull.bearer_token.empty()) {
    headers = curl_slist_append(headers, ("Authorization: Bearer " + pull.bearer_token).c_str());
  }
  std::unique_ptr<curl_slist, void (*)(curl_slist*)> header_list(headers, curl_slist_free_all);
  Transfer t;
  t.max_bytes = pull.max_bytes;
  CURL* c = curl.get();
  curl_easy_setopt(c, CURLOPT_URL, url.c_str());
  curl_easy_setopt(c, CURLOPT_HTTPHEADER, headers);
  curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, OnBody);
  curl_easy_setopt(c, CURLOPT_WRITEDATA, &t);
  curl_easy_setopt(c, CURLOPT_HEADERFUNCTION, OnHeader);
  curl_easy_setopt(c, CURLOPT_HEADERDATA, &t);
  curl_easy_setopt(c, CURLOPT_TIMEOUT, static_cast<long>(pull.timeout_seconds));
  curl_easy_setopt(c, CURLOPT_CONNECTTIMEOUT, 10L);
  curl_easy_setopt(c, CURLOPT_NOSIGNAL, 1L);
  curl_easy_setopt(c, CURLOPT_TCP_NODELAY, 1L);
  curl_easy_setopt(c, CURLOPT_PROTOCOLS_STR, "http,https");
  if (!pull.ca_file.empty()) curl_easy_setopt(c, CURLOPT_CAINFO, pull.ca_file.c_str());
  if (!pull.user.empty()) {
    curl_easy_setopt(c, CURLOPT_HTTPAUTH, CURLAUTH_BASIC);
    curl_easy_setopt(c, CURLOPT_USERPWD, pull.user.c_str());
  }
  const CURLcode rc = curl_easy_perform(c);
  if (t.too_big) {
    *error = url + ": answer larger than " + std::to_string(pull.max_bytes) + " bytes";
    return false;
  }
  if (rc != CURLE_OK) {
    *error = url + ": " + curl_easy_strerror(rc);
    return false;
  }
  long http = 0;
  curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &http);
  if (http != 200) {
    *error = url + ": HTTP " + std::to_string(http) + " " + t.body.substr(0, 200);
    return false;
  }
  if (Lower(t.content_type).find("multipart/related") == std::string::npos) {
    *error = url + ": answer is '" + t.content_type + "', expected multipart/related";
    return false;
  }
  const std::string boundary = Boundary(t.content_type);
  if (boundary.empty()) {
    *error = url + ": multipart answer without a boundary";
    return false;
  }
  std::error_code ec;
  fs::create_directories(out_dir, ec);
  if (ec) {
    *error = out_dir.string() + ": " + ec.message();
    return false;
  }
  // RFC 2046: parts are separated by CRLF "--" boundary; the last one ends with "--".
  const std::string_view body(t.body);
  const std::string delimiter = "--" + boundary;
  size_t pos = body.find(delimiter);
  int count = 0;
  int64_t bytes = 0;
  while (pos != std::string_view::npos) {
    pos += delimiter.size();
    if (body.substr(pos, 2) == "--") break;  // closing delimiter
    const size_t head_end = body.find("\r\n\r\n", pos);
    if (head_end == std::string_view::npos) {
      *error = url + ": part " + std::to_string(count + 1) + " has no header end";
      return false;
    }
    const std::string head = Lower(std::string(body.substr(pos, head_end - pos)));
    const size_t content = head_end + 4;
    const size_t next = body.find("\r\n" + delimiter, content);
    if (next == std::string_view::npos) {
      *error = url + ": part " + std::to_string(count + 1) + " is not terminated";
      return false;
    }
    if (head.find("content-type: application/dicom") == std::string::npos &&
        head.find("content-type:application/dicom") == std::string::npos) {
      *error = url + ": part " + std::to_string(count + 1) + " is not application/dicom";
      return false;
    }
    char name[32];
    std::snprintf(name, sizeof name, "%05d.dcm", count + 1);
    std::ofstream out(out_dir / name, std::ios::binary | std::ios::trunc);
    out.write(body.data() + content, static_cast<std::streamsize>(next - content));
    if (!out.good()) {
      *error = (out_dir / name).string() + ": write failed";
      return false;
    }
    ++count;
    bytes += static_cast<int64_t>(next - content);
    pos = next + 2;
  }
  if (count == 0) {
    *error = url + ": no instance in the answer";
    return false;
  }
  result->instances = count;
  result->bytes = bytes;
  result->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return true;
}

}  // namespace decima::client
