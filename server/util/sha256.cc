#include "server/util/sha256.h"

namespace decima::server {

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
