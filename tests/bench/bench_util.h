// Helpers the benchmark programs (decima-bench, decima-compare) share: input specs, memory and
// load figures. Header-only; benchmarks only.
#pragma once

#include <sys/resource.h>

#include <array>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <string>
#include <vector>

#include <cstdio>
#include "absl/status/statusor.h"

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"

namespace decima::bench {

// Peak resident memory of this process, MB (Linux reports kilobytes).
inline double PeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

// Resets the kernel's peak resident set of this process (VmHWM) to the current one, so that
// StatusHwmMb measures one stage; false where /proc/self/clear_refs refuses it.
inline bool ResetPeakRss() {
  std::FILE* f = std::fopen("/proc/self/clear_refs", "w");
  if (f == nullptr) return false;
  const bool ok = std::fputs("5", f) >= 0;
  return std::fclose(f) == 0 && ok;
}

// VmHWM of /proc/self/status, MB (-1 if unreadable): the peak since the last ResetPeakRss.
inline double StatusHwmMb() {
  std::FILE* f = std::fopen("/proc/self/status", "r");
  if (f == nullptr) return -1;
  char line[256];
  double kb = -1;
  while (std::fgets(line, sizeof line, f) != nullptr) {
    if (std::sscanf(line, "VmHWM: %lf kB", &kb) == 1) break;
  }
  std::fclose(f);
  return kb / 1024.0;
}

// 1-minute load average, or -1 if unknown: the figures say how busy the machine was.
inline double LoadAverage() {
  double load[1] = {0};
  return getloadavg(load, 1) == 1 ? load[0] : -1.0;
}

// "phantom:NxNxN" or "phantom:N" -> dims; nullopt if `input` is not a phantom spec.
inline absl::StatusOr<std::optional<std::array<int64_t, 3>>> ParsePhantom(
    const std::string& input) {
  if (input.rfind("phantom:", 0) != 0) return std::nullopt;
  std::vector<std::string> parts = absl::StrSplit(input.substr(8), 'x');
  if (parts.size() == 1) parts = {parts[0], parts[0], parts[0]};
  if (parts.size() != 3) {
    return absl::InvalidArgumentError("--input: expected phantom:NxNxN, got '" + input + "'");
  }
  std::array<int64_t, 3> dims{};
  for (int c = 0; c < 3; ++c) {
    if (!absl::SimpleAtoi(parts[c], &dims[c]) || dims[c] < 2) {
      return absl::InvalidArgumentError("--input: phantom size '" + parts[c] +
                                        "' is not an integer >= 2");
    }
  }
  return std::optional<std::array<int64_t, 3>>(dims);
}

}  // namespace decima::bench
