// Replays every seed of the fuzz corpora through the fuzz entry functions in the normal build,
// so the seeds (and the entries' contract checks) run on every ctest, not only under clang.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/mesh_io.h"
#include "core/render/transfer_function.h"
#include "tests/fuzz/fuzz_entries.h"

namespace decima::fuzz {
namespace {

namespace fs = std::filesystem;

std::vector<fs::path> Seeds(const char* corpus) {
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(fs::path(DECIMA_FUZZ_CORPUS_DIR) / corpus))
    if (e.is_regular_file()) files.push_back(e.path());
  std::sort(files.begin(), files.end());
  return files;
}

std::string Bytes(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Every seed of corpus/<dir> (at least 4), and the empty input, through `entry` as the fuzzer
// would feed them; the entry aborts on a broken invariant and returns 0 otherwise.
void ReplayCorpus(const char* dir, int (*entry)(const uint8_t*, size_t)) {
  const auto seeds = Seeds(dir);
  ASSERT_GE(seeds.size(), 4u);
  for (const fs::path& p : seeds) {
    SCOPED_TRACE(p.string());
    const std::string b = Bytes(p);
    EXPECT_EQ(entry(reinterpret_cast<const uint8_t*>(b.data()), b.size()), 0);
  }
  EXPECT_EQ(entry(nullptr, 0), 0);
}

TEST(FuzzReplay, EveryVtuSeedRunsThroughReadVtuEntry) { ReplayCorpus("vtu", ReadVtuEntry); }

TEST(FuzzReplay, EveryTransferFunctionSeedRunsThroughItsEntry) {
  ReplayCorpus("transfer_function", TransferFunctionEntry);
}

// The corpus must keep files the readers accept (named ok-*), so the fuzzer starts past the
// header checks and the entries' invariant checks run on real meshes and functions.
TEST(FuzzReplay, SeedsNamedOkAreAccepted) {
  int ok = 0;
  for (const fs::path& p : Seeds("vtu")) {
    if (p.filename().string().rfind("ok-", 0) != 0) continue;
    ++ok;
    auto m = ReadVtu(p);
    EXPECT_TRUE(m.ok()) << p << ": " << m.status();
  }
  for (const fs::path& p : Seeds("transfer_function")) {
    if (p.filename().string().rfind("ok-", 0) != 0) continue;
    ++ok;
    auto tf = ParseTransferFunction(Bytes(p), ScalarRange{-1024, 3071});
    EXPECT_TRUE(tf.ok()) << p << ": " << tf.status();
  }
  EXPECT_GE(ok, 4);
}

}  // namespace
}  // namespace decima::fuzz
