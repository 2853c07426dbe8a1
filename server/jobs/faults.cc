#include "server/jobs/faults.h"

#include <chrono>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace decima::server {
namespace {

absl::Status Parse(const std::string& faults, bool* crash, double* sleep_s,
                   std::string* pause_after = nullptr) {
  *crash = false;
  *sleep_s = 0;
  for (absl::string_view f : absl::StrSplit(faults, ',', absl::SkipEmpty())) {
    if (f == "crash") {
      *crash = true;
    } else if (absl::ConsumePrefix(&f, "pause-after:")) {
      absl::string_view window = f;
      int n = 0;
      const bool simplify_window = absl::ConsumePrefix(&window, "simplify-window-") &&
                                   absl::SimpleAtoi(window, &n) && n >= 1;
      if (f != "segment" && f != "simplify" && !simplify_window) {
        return absl::InvalidArgumentError(
            absl::StrCat(kFaultMetadataKey, ": pause-after:'", f,
                         "', expected segment, simplify or simplify-window-N (N >= 1)"));
      }
      if (pause_after) *pause_after = std::string(f);
    } else if (absl::ConsumePrefix(&f, "sleep:")) {
      double s = 0;
      if (!absl::SimpleAtod(f, &s) || !(s >= 0 && s <= 3600)) {
        return absl::InvalidArgumentError(
            absl::StrCat(kFaultMetadataKey, ": sleep:'", f, "', expected 0..3600 seconds"));
      }
      *sleep_s += s;
    } else {
      return absl::InvalidArgumentError(absl::StrCat(kFaultMetadataKey, ": unknown fault '", f,
                                                     "' (crash, sleep:S, pause-after:STAGE)"));
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status ValidateFaults(const std::string& faults) {
  bool crash;
  double sleep_s;
  return Parse(faults, &crash, &sleep_s);
}

absl::Status ApplyFaults(const std::string& faults, const ProgressFn& progress,
                         const CancelToken& cancel, bool* crash) {
  double seconds = 0;
  if (auto st = Parse(faults, crash, &seconds); !st.ok()) return st;
  const auto start = std::chrono::steady_clock::now();
  while (seconds > 0) {
    double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (t >= seconds) break;
    if (cancel.cancelled()) return absl::CancelledError("prepare: cancelled");
    Report(progress, {"prepare", t / seconds, "test fault: sleeping", {{"elapsed_s", t}}});
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return absl::OkStatus();
}

absl::Status PauseAfterCheckpoint(const std::string& faults, const std::string& stage,
                                  const ProgressFn& progress, const CancelToken& cancel) {
  bool crash;
  double sleep_s;
  std::string pause_after;
  if (auto st = Parse(faults, &crash, &sleep_s, &pause_after); !st.ok()) return st;
  if (pause_after != stage) return absl::OkStatus();
  const auto start = std::chrono::steady_clock::now();
  for (int64_t tick = 0;; ++tick) {
    const double t =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (t >= kMaxPauseSeconds) break;
    if (cancel.cancelled()) return absl::CancelledError(absl::StrCat(stage, ": cancelled"));
    // Once a second: enough for a test to see it, few enough not to flood the event log.
    if (tick % 20 == 0) {
      // A window record is saved inside the simplify stage, which is still the job's stage.
      const bool window = absl::StartsWith(stage, "simplify-window-");
      Report(progress, {window ? std::string("simplify") : stage,
                        window ? 0.5 : 1,
                        absl::StrCat("test fault: paused after the ", stage, " checkpoint"),
                        {{"elapsed_s", t}}});
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return absl::OkStatus();
}

}  // namespace decima::server
