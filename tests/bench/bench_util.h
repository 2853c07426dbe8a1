// Helpers the benchmark programs (decima-bench, decima-compare) share: input specs, memory and
// load figures. Header-only; benchmarks only.
#pragma once

#include <sys/resource.h>

#include <array>
#include <cstdint>
#include <cstdlib>
#include <optional>
#include <string>
#include <vector>

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
