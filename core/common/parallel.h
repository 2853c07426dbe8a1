// How decima_core splits work over the cores: contiguous static ranges (ParallelFor), so every
// thread writes its own slice, or independent tasks taken in turn (ParallelTasks); either way
// results never depend on scheduling.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <utility>
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
void ParallelFor(int64_t n, int threads, int64_t min_chunk, Fn&& fn) {
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

// Calls fn(thread, task) for every task in [0, n) on up to `threads` threads, each taking the next
// task when it is done with one (tasks of uneven size keep both cores busy). Which thread runs a
// task varies from run to run, so tasks must not depend on each other: each writes only what it
// owns, and `thread` may only pick per-thread scratch memory.
template <typename Fn>
void ParallelTasks(int64_t n, int threads, Fn&& fn) {
  threads = static_cast<int>(std::clamp<int64_t>(std::min<int64_t>(threads, n), 1, 64));
  if (threads == 1) {
    for (int64_t i = 0; i < n; ++i) fn(0, i);
    return;
  }
  std::atomic<int64_t> next{0};
  std::vector<std::thread> pool;
  pool.reserve(threads);
  for (int t = 0; t < threads; ++t) {
    pool.emplace_back([&fn, &next, n, t] {
      for (int64_t i = next.fetch_add(1, std::memory_order_relaxed); i < n;
           i = next.fetch_add(1, std::memory_order_relaxed)) {
        fn(t, i);
      }
    });
  }
  for (auto& th : pool) th.join();
}

// Sum of f(i) over [0, n), in fixed blocks of `block` items added in block order: the same sum on
// any thread count (a sum split by thread would change in the last bits with the count).
template <typename F>
double BlockSum(int64_t n, int threads, int64_t block, F&& f) {
  std::vector<double> part((n + block - 1) / block, 0.0);
  ParallelFor(int64_t(part.size()), threads, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      double sum = 0;
      for (int64_t i = b * block; i < std::min(n, (b + 1) * block); ++i) sum += f(i);
      part[b] = sum;
    }
  });
  double sum = 0;
  for (double x : part) sum += x;
  return sum;
}

// As above with ranges of any length (coarse loops: slices, rows).
template <typename Fn>
void ParallelFor(int64_t n, int threads, Fn&& fn) {
  ParallelFor(n, threads, 1, std::forward<Fn>(fn));
}

}  // namespace decima
