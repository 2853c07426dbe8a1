#include "server/faults.h"

#include <chrono>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace decima::server {
namespace {

absl::Status Parse(const std::string& faults, bool* crash, double* sleep_s) {
  *crash = false;
  *sleep_s = 0;
  for (absl::string_view f : absl::StrSplit(faults, ',', absl::SkipEmpty())) {
    if (f == "crash") {
      *crash = true;
    } else if (absl::ConsumePrefix(&f, "sleep:")) {
      double s = 0;
      if (!absl::SimpleAtod(f, &s) || !(s >= 0 && s <= 3600)) {
        return absl::InvalidArgumentError(
            absl::StrCat(kFaultMetadataKey, ": sleep:'", f, "', expected 0..3600 seconds"));
      }
      *sleep_s += s;
    } else {
      return absl::InvalidArgumentError(
          absl::StrCat(kFaultMetadataKey, ": unknown fault '", f, "' (crash, sleep:S)"));
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

}  // namespace decima::server
