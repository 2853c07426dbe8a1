#include "tests/testing/test_data.h"

#include <atomic>
#include <cstdlib>
#include <mutex>
#include <vector>

#include <unistd.h>

#include "absl/strings/str_cat.h"
#include "gtest/gtest.h"

namespace decima::testing {

std::optional<std::filesystem::path> SharedDataFile(const std::string& name) {
  const char* env = std::getenv("DECIMA_SHARED_DATA");
  if (env == nullptr || *env == '\0') return std::nullopt;
  std::filesystem::path p = std::filesystem::path(env) / name;
  std::error_code ec;
  if (!std::filesystem::exists(p, ec)) return std::nullopt;
  return p;
}

namespace {

std::mutex scratch_mu;
std::vector<std::filesystem::path>* scratch_dirs = nullptr;  // leaked: used at exit

void RemoveScratchDirs() {
  const char* keep = std::getenv("DECIMA_KEEP_SCRATCH");
  if ((keep != nullptr && *keep != '\0' && *keep != '0') ||
      !::testing::UnitTest::GetInstance()->Passed()) {
    return;
  }
  std::lock_guard<std::mutex> lock(scratch_mu);
  for (const auto& dir : *scratch_dirs) {
    std::error_code ec;
    std::filesystem::remove_all(dir, ec);
  }
}

}  // namespace

std::filesystem::path MakeScratchDir(const std::string& tag) {
  static std::atomic<int> counter{0};
  const char* tmp = std::getenv("TEST_TMPDIR");
  std::filesystem::path base = (tmp && *tmp) ? tmp : std::filesystem::temp_directory_path();
  std::filesystem::path dir =
      base / absl::StrCat("decima-", tag, "-", ::getpid(), "-", counter.fetch_add(1));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  std::lock_guard<std::mutex> lock(scratch_mu);
  if (scratch_dirs == nullptr) {
    scratch_dirs = new std::vector<std::filesystem::path>;
    std::atexit(RemoveScratchDirs);
  }
  scratch_dirs->push_back(dir);
  return dir;
}

}  // namespace decima::testing
