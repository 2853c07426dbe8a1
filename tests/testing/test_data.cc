#include "tests/testing/test_data.h"

#include <atomic>
#include <cstdlib>

#include <unistd.h>

#include "absl/strings/str_cat.h"

namespace decima::testing {

std::optional<std::filesystem::path> SharedDataFile(const std::string& name) {
  const char* env = std::getenv("DECIMA_SHARED_DATA");
  if (env == nullptr || *env == '\0') return std::nullopt;
  std::filesystem::path p = std::filesystem::path(env) / name;
  std::error_code ec;
  if (!std::filesystem::exists(p, ec)) return std::nullopt;
  return p;
}

std::filesystem::path MakeScratchDir(const std::string& tag) {
  static std::atomic<int> counter{0};
  const char* tmp = std::getenv("TEST_TMPDIR");
  std::filesystem::path base = (tmp && *tmp) ? tmp : std::filesystem::temp_directory_path();
  std::filesystem::path dir =
      base / absl::StrCat("decima-", tag, "-", ::getpid(), "-", counter.fetch_add(1));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

}  // namespace decima::testing
