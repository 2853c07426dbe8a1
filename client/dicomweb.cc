#include "client/dicomweb.h"

#include <curl/curl.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <memory>
#include <string_view>

#include "client/text.h"

namespace decima::client {
namespace fs = std::filesystem;
namespace {

std::string Boundary(const std::string& content_type);

// The answer, parsed as it arrives (RFC 2046 multipart/related): each application/dicom part
// goes straight to its file, so memory stays at one read plus a boundary's length whatever
// the answer's size (issue 35 part 7: a 600 MB answer took 1.07 GB of RSS when it was
// buffered whole), and the number of parts is limited.
struct Transfer {
  CURL* curl = nullptr;
  std::string url;
  fs::path out_dir;
  std::string content_type;
  int64_t max_bytes = 0;
  int max_instances = 0;
  int64_t received = 0;
  std::string error;       // set when the transfer was stopped
  std::string error_body;  // the start of a non-200 answer
  enum class State { kStart, kPreamble, kHeaders, kContent, kDone } state = State::kStart;
  std::string delimiter;  // "--" boundary
  std::string buf;        // received, not yet consumed
  std::ofstream out;
  fs::path out_path;
  int count = 0;
  int64_t bytes = 0;
};

bool Fail(Transfer* t, const std::string& error) {
  t->error = error;
  return false;
}

// Consumes what it can of t->buf; false (t->error set) on a malformed answer.
bool Parse(Transfer* t) {
  for (;;) {
    switch (t->state) {
      case Transfer::State::kStart:
      case Transfer::State::kDone:
        t->buf.clear();  // after the closing delimiter: the epilogue is ignored
        return true;
      case Transfer::State::kPreamble: {
        const size_t p = t->buf.find(t->delimiter);
        if (p == std::string::npos) {
          // Keep a tail that may hold the start of the delimiter.
          if (t->buf.size() > t->delimiter.size())
            t->buf.erase(0, t->buf.size() - t->delimiter.size());
          return true;
        }
        if (t->buf.size() < p + t->delimiter.size() + 2) return true;
        t->buf.erase(0, p + t->delimiter.size());
        if (t->buf.compare(0, 2, "--") == 0) {
          t->state = Transfer::State::kDone;
          continue;
        }
        t->state = Transfer::State::kHeaders;
        continue;
      }
      case Transfer::State::kHeaders: {
        const size_t end = t->buf.find("\r\n\r\n");
        if (end == std::string::npos) {
          if (t->buf.size() > 64 * 1024) {
            return Fail(t, t->url + ": part " + std::to_string(t->count + 1) +
                               " has no header end within 64 KiB");
          }
          return true;
        }
        const std::string head = AsciiLower(t->buf.substr(0, end));
        if (head.find("content-type: application/dicom") == std::string::npos &&
            head.find("content-type:application/dicom") == std::string::npos) {
          return Fail(
              t, t->url + ": part " + std::to_string(t->count + 1) + " is not application/dicom");
        }
        if (t->count >= t->max_instances) {
          return Fail(t, t->url + ": more than " + std::to_string(t->max_instances) +
                             " instances in the answer");
        }
        char name[32];
        std::snprintf(name, sizeof name, "%05d.dcm", t->count + 1);
        t->out_path = t->out_dir / name;
        t->out.open(t->out_path, std::ios::binary | std::ios::trunc);
        if (!t->out) return Fail(t, t->out_path.string() + ": cannot write");
        t->buf.erase(0, end + 4);
        t->state = Transfer::State::kContent;
        continue;
      }
      case Transfer::State::kContent: {
        const std::string marker = "\r\n" + t->delimiter;
        const size_t p = t->buf.find(marker);
        // Everything that cannot be the start of the marker goes to the file now.
        const size_t safe =
            p != std::string::npos
                ? p
                : (t->buf.size() > marker.size() ? t->buf.size() - marker.size() : 0);
        t->out.write(t->buf.data(), static_cast<std::streamsize>(safe));
        t->bytes += static_cast<int64_t>(safe);
        t->buf.erase(0, safe);
        if (!t->out.good()) return Fail(t, t->out_path.string() + ": write failed");
        if (p == std::string::npos) return true;
        t->out.close();
        if (!t->out.good()) return Fail(t, t->out_path.string() + ": write failed");
        ++t->count;
        t->buf.erase(0, 2);  // the CRLF before the delimiter
        t->state = Transfer::State::kPreamble;
        continue;
      }
    }
  }
}

size_t OnBody(char* data, size_t size, size_t n, void* user) {
  auto* t = static_cast<Transfer*>(user);
  const size_t len = size * n;
  t->received += static_cast<int64_t>(len);
  if (t->received > t->max_bytes) {
    t->error = t->url + ": answer larger than " + std::to_string(t->max_bytes) + " bytes";
    return 0;
  }
  if (t->state == Transfer::State::kStart) {
    long http = 0;
    curl_easy_getinfo(t->curl, CURLINFO_RESPONSE_CODE, &http);
    if (http != 200) {
      t->error_body.append(data, std::min(len, 200 - std::min<size_t>(200, t->error_body.size())));
      return len;  // read to the end; reported after the transfer
    }
    if (AsciiLower(t->content_type).find("multipart/related") == std::string::npos) {
      t->error = t->url + ": answer is '" + t->content_type + "', expected multipart/related";
      return 0;
    }
    const std::string boundary = Boundary(t->content_type);
    if (boundary.empty()) {
      t->error = t->url + ": multipart answer without a boundary";
      return 0;
    }
    std::error_code ec;
    fs::create_directories(t->out_dir, ec);
    if (ec) {
      t->error = t->out_dir.string() + ": " + ec.message();
      return 0;
    }
    t->delimiter = "--" + boundary;
    t->state = Transfer::State::kPreamble;
  }
  t->buf.append(data, len);
  return Parse(t) ? len : 0;
}

size_t OnHeader(char* data, size_t size, size_t n, void* user) {
  auto* t = static_cast<Transfer*>(user);
  const std::string line(data, size * n);
  if (AsciiLower(line.substr(0, 13)) == "content-type:") {
    std::string v = line.substr(13);
    while (!v.empty() && (v.back() == '\r' || v.back() == '\n')) v.pop_back();
    t->content_type = v;
  }
  return size * n;
}

// The boundary parameter of a multipart Content-Type, unquoted; "" if absent.
std::string Boundary(const std::string& content_type) {
  const std::string lower = AsciiLower(content_type);
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
  t.curl = curl.get();
  t.url = url;
  t.out_dir = out_dir;
  t.max_bytes = pull.max_bytes;
  t.max_instances = pull.max_instances;
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
  if (t.out.is_open()) t.out.close();
  if (!t.error.empty()) {
    *error = t.error;
    return false;
  }
  if (rc != CURLE_OK) {
    *error = url + ": " + curl_easy_strerror(rc);
    return false;
  }
  long http = 0;
  curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &http);
  if (http != 200) {
    *error = url + ": HTTP " + std::to_string(http) + " " + t.error_body;
    return false;
  }
  if (t.state == Transfer::State::kContent || t.state == Transfer::State::kHeaders) {
    *error = url + ": part " + std::to_string(t.count + 1) + " is not terminated";
    return false;
  }
  const int count = t.count;
  const int64_t bytes = t.bytes;
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
