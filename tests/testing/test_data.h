// Access to the real volumes in ../shared/data (see its MANIFEST.md) and scratch folders.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

namespace decima::testing {

// Absolute path of `name` inside the shared data folder ($DECIMA_SHARED_DATA, else the folder
// configured at build time), or nullopt if that file does not exist.
std::optional<std::filesystem::path> SharedDataFile(const std::string& name);

// A fresh empty directory under the test temp dir, unique per call. Every scratch directory of
// the process is removed when it exits after all its tests passed (a CI machine runs thousands
// of tests, some writing hundreds of MB each); a failing run leaves them to look at, and so does
// DECIMA_KEEP_SCRATCH=1.
std::filesystem::path MakeScratchDir(const std::string& tag);

}  // namespace decima::testing

// Skips the current test with a clear message when a shared data file is missing; otherwise
// declares `var` as its path.
#define DECIMA_REQUIRE_SHARED_DATA(var, name)                                               \
  auto var##_opt = ::decima::testing::SharedDataFile(name);                                 \
  if (!var##_opt) {                                                                         \
    GTEST_SKIP() << "shared data file '" << name                                            \
                 << "' not found (set DECIMA_SHARED_DATA to the folder of ../shared/data)"; \
  }                                                                                         \
  const std::filesystem::path var = *var##_opt
