#include "server/util/sha256.h"

#include <cstdio>
#include <vector>

#include "absl/strings/str_cat.h"

namespace decima::server {

absl::Status HashFilePrefix(const std::filesystem::path& path, int64_t limit, Sha256& hash) {
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) return absl::NotFoundError(absl::StrCat(path.string(), ": cannot open"));
  std::vector<char> buf(1 << 20);
  int64_t left = limit < 0 ? INT64_MAX : limit;
  while (left > 0) {
    size_t want = static_cast<size_t>(std::min<int64_t>(left, static_cast<int64_t>(buf.size())));
    size_t got = std::fread(buf.data(), 1, want, f);
    if (got == 0) break;
    hash.Update(buf.data(), got);
    left -= static_cast<int64_t>(got);
  }
  bool err = std::ferror(f) != 0;
  std::fclose(f);
  if (err) return absl::DataLossError(absl::StrCat(path.string(), ": read error"));
  if (limit >= 0 && left > 0) {
    return absl::DataLossError(absl::StrCat(path.string(), ": shorter than ", limit, " bytes"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> Sha256OfFile(const std::filesystem::path& path) {
  Sha256 h;
  absl::Status s = HashFilePrefix(path, -1, h);
  if (!s.ok()) return s;
  return h.HexDigest();
}

bool IsSha256Hex(absl::string_view s) {
  if (s.size() != 64) return false;
  for (char c : s) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

}  // namespace decima::server
