// core/common: the cancellation token, progress forwarding, the status macros, BitSet and the
// one ParallelFor (ranges cover [0, n) exactly once, contiguous, at most `threads`).
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <mutex>
#include <thread>
#include <vector>

#include "core/common/bit_set.h"
#include "core/common/parallel.h"
#include "core/common/progress.h"
#include "core/common/status.h"

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

}  // namespace
}  // namespace decima
