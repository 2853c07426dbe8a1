// Names of the SimplifyPolicy values as the benchmark programs spell them on the command line and
// in their output. One table, so a new policy is one line here (core/simplify names none itself).
#pragma once

#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include "core/simplify/simplify.h"

namespace decima {

inline constexpr std::pair<std::string_view, SimplifyPolicy> kSimplifyPolicyNames[] = {
    {"paper", SimplifyPolicy::kPaper},
    {"tetfusion", SimplifyPolicy::kTetFusion},
};

// The policy spelled `name`, or nullopt if this build has no such policy.
inline std::optional<SimplifyPolicy> ParseSimplifyPolicy(std::string_view name) {
  for (const auto& [n, p] : kSimplifyPolicyNames)
    if (n == name) return p;
  return std::nullopt;
}

// The name of `policy` ("?" for a value missing from the table, which a test would catch).
inline std::string_view SimplifyPolicyName(SimplifyPolicy policy) {
  for (const auto& [n, p] : kSimplifyPolicyNames)
    if (p == policy) return n;
  return "?";
}

// "paper, tetfusion": for help texts and error messages.
inline std::string KnownSimplifyPolicies() {
  std::string out;
  for (const auto& [n, p] : kSimplifyPolicyNames) {
    if (!out.empty()) out += ", ";
    out += n;
  }
  return out;
}

}  // namespace decima
