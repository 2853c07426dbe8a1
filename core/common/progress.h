// Progress reporting and cooperative cancellation shared by every long-running core function.
//
// Contract: a core function that takes a `const ProgressFn&` calls it from the thread that
// called the function (never from a worker thread it started), at most a few hundred times per
// stage, so callbacks may log or send over the network. A function that takes a
// `const CancelToken*` (nullptr = never cancelled) polls it at least once per iteration of its
// outer loop and returns absl::CancelledError when it fires, leaving its inputs untouched.
#pragma once

#include <atomic>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"

namespace decima {

struct Progress {
  std::string stage;    // "load", "segment", "tetra", "simplify", "render", ...
  double fraction = 0;  // 0..1 within the stage
  std::string message;  // human readable, one line
  // Stage-specific numbers (e.g. {"iteration", 12}, {"energy", 3.1e6}); ordered, small.
  std::vector<std::pair<std::string, double>> metrics;
  // The whole job's progress (0..1) and seconds left, filled in by the job's clock
  // (core/pipeline/eta.h) from its stage model and the stages' measured rates; < 0 = unknown
  // (a core function never sets them).
  double overall = -1;
  double eta_seconds = -1;
};

using ProgressFn = std::function<void(const Progress&)>;

// Thread-safe flag; Cancel() may be called from any thread, including a signal-safe context.
class CancelToken {
 public:
  void Cancel() { cancelled_.store(true, std::memory_order_relaxed); }
  bool cancelled() const { return cancelled_.load(std::memory_order_relaxed); }

 private:
  std::atomic<bool> cancelled_{false};
};

// Returns absl::CancelledError naming `stage` if `token` fired, OK otherwise (also for nullptr).
absl::Status CheckCancelled(const CancelToken* token, const char* stage);

// Calls `fn` if it is set.
inline void Report(const ProgressFn& fn, const Progress& p) {
  if (fn) fn(p);
}

}  // namespace decima
