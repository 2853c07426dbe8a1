// The one way decima_core splits a loop over both cores: contiguous static ranges, so every
// thread writes its own slice and results never depend on scheduling.
#pragma once

#include <algorithm>
#include <cstdint>
#include <thread>
#include <vector>

namespace decima {

// Worker count for a `threads` option: itself if > 0, else the hardware concurrency.
inline int ResolveThreads(int threads) {
  return threads > 0 ? threads
                     : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
}

// Calls fn(begin, end) on up to `threads` contiguous ranges covering [0, n), one thread each, and
// joins them. Ranges are at least `min_chunk` items long (fewer threads for small n); with one
// range fn runs on the calling thread.
template <typename Fn>
void ParallelFor(int64_t n, int threads, Fn&& fn, int64_t min_chunk = 1) {
  const int64_t max_ranges = std::max<int64_t>(1, n / std::max<int64_t>(1, min_chunk));
  threads = static_cast<int>(std::clamp<int64_t>(std::min<int64_t>(threads, max_ranges), 1, 64));
  if (threads == 1) {
    fn(int64_t{0}, n);
    return;
  }
  std::vector<std::thread> pool;
  pool.reserve(threads);
  for (int t = 0; t < threads; ++t) {
    const int64_t begin = n * t / threads, end = n * (t + 1) / threads;
    pool.emplace_back([&fn, begin, end] { fn(begin, end); });
  }
  for (auto& th : pool) th.join();
}

}  // namespace decima
