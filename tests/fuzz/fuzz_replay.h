// Replay of a fuzz corpus through its entry, shared by the fuzz_replay_test sources.
#pragma once

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "tests/fuzz/fuzz_entries.h"

namespace decima::fuzz {

namespace fs = std::filesystem;

inline std::vector<fs::path> Seeds(const char* corpus) {
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(fs::path(DECIMA_FUZZ_CORPUS_DIR) / corpus))
    if (e.is_regular_file()) files.push_back(e.path());
  std::sort(files.begin(), files.end());
  return files;
}

inline std::string Bytes(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Every seed of corpus/<dir> (at least 4), and the empty input, through `entry` as the fuzzer
// would feed them; the entry aborts on a broken invariant and returns 0 otherwise.
inline void ReplayCorpus(const char* dir, int (*entry)(const uint8_t*, size_t)) {
  const auto seeds = Seeds(dir);
  ASSERT_GE(seeds.size(), 4u);
  for (const fs::path& p : seeds) {
    SCOPED_TRACE(p.string());
    const std::string b = Bytes(p);
    EXPECT_EQ(entry(reinterpret_cast<const uint8_t*>(b.data()), b.size()), 0);
  }
  EXPECT_EQ(entry(nullptr, 0), 0);
}

// The seeds of corpus/<dir> named ok-* (at least 2) are accepted by `entry`, the others not.
inline void ExpectOkSeedsAccepted(const char* dir, int (*entry)(const uint8_t*, size_t)) {
  int ok = 0;
  for (const fs::path& p : Seeds(dir)) {
    SCOPED_TRACE(p.string());
    const std::string b = Bytes(p);
    entry(reinterpret_cast<const uint8_t*>(b.data()), b.size());
    const bool named_ok = p.filename().string().rfind("ok-", 0) == 0;
    EXPECT_EQ(LastInputAccepted(), named_ok);
    ok += named_ok;
  }
  EXPECT_GE(ok, 2) << dir;
}

}  // namespace decima::fuzz
