// core/common: the cancellation token, progress forwarding, the status macros, BitSet, the
// one ParallelFor (ranges cover [0, n) exactly once, contiguous, at most `threads`), ValidUtf8 and
// the huge-page hint.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <fstream>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "core/common/bit_set.h"
#include "core/common/huge_pages.h"
#include "core/common/parallel.h"
#include "core/common/progress.h"
#include "core/common/status.h"
#include "core/common/utf8.h"

namespace decima {
namespace {

TEST(CancelToken, CheckCancelledNamesTheStageOnlyAfterCancel) {
  CancelToken t;
  EXPECT_TRUE(CheckCancelled(&t, "segment").ok());
  EXPECT_TRUE(CheckCancelled(nullptr, "segment").ok());
  std::thread([&] { t.Cancel(); }).join();
  const absl::Status s = CheckCancelled(&t, "segment");
  EXPECT_EQ(s.code(), absl::StatusCode::kCancelled);
  EXPECT_NE(s.message().find("segment"), absl::string_view::npos);
}

TEST(Report, CallsOnlyASetCallback) {
  int calls = 0;
  Report(nullptr, {"load", 0, "", {}});
  Report([&](const Progress& p) { calls += p.stage == "load"; }, {"load", 1, "", {}});
  EXPECT_EQ(calls, 1);
}

absl::StatusOr<int> Half(int x) {
  if (x % 2) return absl::InvalidArgumentError("odd");
  return x / 2;
}
absl::Status Quarter(int x, int* out) {
  DECIMA_ASSIGN_OR_RETURN(const int h, Half(x));
  DECIMA_ASSIGN_OR_RETURN(*out, Half(h));
  DECIMA_RETURN_IF_ERROR(absl::OkStatus());
  return absl::OkStatus();
}

TEST(StatusMacros, ReturnTheFirstErrorAndAssignOtherwise) {
  int q = 0;
  EXPECT_TRUE(Quarter(8, &q).ok());
  EXPECT_EQ(q, 2);
  EXPECT_EQ(Quarter(6, &q).code(), absl::StatusCode::kInvalidArgument);
}

TEST(BitSet, SetsTestsAndClearsAcrossWordBoundaries) {
  BitSet b(130);
  for (int64_t i : {0, 63, 64, 129}) b.Set(i);
  for (int64_t i = 0; i < 130; ++i) EXPECT_EQ(b.Test(i), i == 0 || i == 63 || i == 64 || i == 129);
  b.ClearAll();
  for (int64_t i = 0; i < 130; ++i) EXPECT_FALSE(b.Test(i));
}

TEST(ResolveThreads, ZeroMeansTheHardwareAndPositiveIsKept) {
  EXPECT_EQ(ResolveThreads(3), 3);
  EXPECT_GE(ResolveThreads(0), 1);
  EXPECT_GE(ResolveThreads(-1), 1);
}

TEST(ParallelFor, CoversEveryIndexOnceInContiguousRangesForAnyThreadCount) {
  for (int threads : {1, 2, 3, 8, 100}) {
    for (int64_t n : {0, 1, 7, 1000}) {
      std::vector<std::atomic<int>> seen(static_cast<size_t>(n));
      std::mutex mu;
      std::vector<std::pair<int64_t, int64_t>> ranges;
      ParallelFor(n, threads, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i) seen[i]++;
        std::lock_guard<std::mutex> lock(mu);
        ranges.emplace_back(b, e);
      });
      for (int64_t i = 0; i < n; ++i) EXPECT_EQ(seen[i].load(), 1) << threads << " " << n;
      EXPECT_LE(static_cast<int>(ranges.size()), std::max(1, threads));
      std::sort(ranges.begin(), ranges.end());
      int64_t next = 0;
      for (auto [b, e] : ranges) {
        EXPECT_EQ(b, next);
        next = e;
      }
      EXPECT_EQ(next, n);
    }
  }
}

TEST(ParallelFor, MinChunkLimitsTheNumberOfRanges) {
  std::atomic<int> ranges{0};
  ParallelFor(100, 8, 40, [&](int64_t, int64_t) { ranges++; });
  EXPECT_EQ(ranges.load(), 2) << "100 items in chunks of at least 40";
}

TEST(ValidUtf8, KeepsValidTextAndReplacesEveryBrokenByte) {
  using std::string;
  // Valid: ASCII, NUL, 2-, 3- and 4-byte forms at the edges of their ranges.
  for (const string& s : {string("CT"), string("a\0b", 3),
                          string("Sch\xC3\xA4"
                                 "del"),
                          string("\xE0\xA0\x80\xED\x9F\xBF\xEF\xBF\xBF"),
                          string("\xF0\x90\x80\x80\xF4\x8F\xBF\xBF"), string()}) {
    EXPECT_EQ(ValidUtf8(s), s);
  }
  const string r = "\xEF\xBF\xBD";  // U+FFFD
  EXPECT_EQ(ValidUtf8("Sch\xE4"
                      "del"),
            "Sch" + r + "del");                             // Latin-1
  EXPECT_EQ(ValidUtf8("\xC0\xAF"), r + r);                  // overlong '/'
  EXPECT_EQ(ValidUtf8("\xED\xA0\x80"), r + r + r);          // a surrogate
  EXPECT_EQ(ValidUtf8("\xF4\x90\x80\x80"), r + r + r + r);  // above U+10FFFF
  EXPECT_EQ(ValidUtf8("ab\xE2\x82"), "ab" + r + r);         // cut short
  EXPECT_EQ(ValidUtf8("\x80x\xFF"), r + "x" + r);
}

// The kernel's THP mode, the bracketed word of /sys/kernel/mm/transparent_hugepage/enabled
// ("always", "madvise" or "never"); empty where the file does not exist.
std::string ThpMode() {
  std::ifstream in("/sys/kernel/mm/transparent_hugepage/enabled");
  std::string line;
  std::getline(in, line);
  const size_t open = line.find('['), close = line.find(']');
  if (open == std::string::npos || close == std::string::npos) return "";
  return line.substr(open + 1, close - open - 1);
}

// AnonHugePages (kB) of the mapping of /proc/self/smaps that holds address a.
int64_t AnonHugePagesKbAt(const void* a) {
  std::ifstream in("/proc/self/smaps");
  const uintptr_t at = reinterpret_cast<uintptr_t>(a);
  std::string line;
  bool inside = false;
  while (std::getline(in, line)) {
    uintptr_t lo = 0, hi = 0;
    char dash = 0;
    std::istringstream head(line);
    if (head >> std::hex >> lo >> dash >> hi && dash == '-') {
      inside = lo <= at && at < hi;
      continue;
    }
    if (inside && line.rfind("AnonHugePages:", 0) == 0) {
      return std::stoll(line.substr(14));
    }
  }
  return -1;
}

TEST(HugePages, AssignFillsLikeAssignAndGetsHugePagesWhereTheKernelGivesThem) {
  std::vector<int32_t> v = {1, 2, 3};
  const size_t n = size_t{24} << 20 >> 2;  // 24 MB: at least ten whole 2 MB pages inside
  AssignOnHugePages(&v, n, 7);
  ASSERT_EQ(v.size(), n);
  EXPECT_EQ(std::count(v.begin(), v.end(), 7), int64_t(n));
  const std::string mode = ThpMode();
  if (mode != "always" && mode != "madvise") {
    GTEST_SKIP() << "transparent huge pages are '" << mode << "' on this kernel";
  }
  // The kernel may fall back to small pages when it has no free 2 MB block; with 24 MB asked
  // for on a machine running tests, some must be huge.
  EXPECT_GT(AnonHugePagesKbAt(v.data() + n / 2), 0) << "THP mode " << mode;

  std::vector<float> small;
  AssignOnHugePages(&small, 10, 1.5f);  // below one huge page: a plain assign
  EXPECT_EQ(small, std::vector<float>(10, 1.5f));
}

TEST(HugePages, FillLaterArraysAreAlignedHugeAndHoldWhatIsWritten) {
  std::vector<double, FillLaterAllocator<double>> v;
  const size_t n = size_t{24} << 20 >> 3;  // 24 MB
  v.resize(n);                             // uninitialised
  EXPECT_EQ(reinterpret_cast<uintptr_t>(v.data()) % 64, 0u);
  ParallelFor(int64_t(n), 2, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) v[i] = double(i);
  });
  for (size_t i = 0; i < n; i += 4099) ASSERT_EQ(v[i], double(i));
  const std::string mode = ThpMode();
  if (mode == "always" || mode == "madvise") {
    EXPECT_GT(AnonHugePagesKbAt(v.data() + n / 2), 0) << "THP mode " << mode;
  }
  std::vector<int, FillLaterAllocator<int>> w(3, 7);  // with a value: constructed as usual
  EXPECT_EQ(w, (std::vector<int, FillLaterAllocator<int>>{7, 7, 7}));
}

}  // namespace
}  // namespace decima
