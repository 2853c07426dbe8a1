#include "tests/bench/simplify_policy_names.h"

#include <gtest/gtest.h>

namespace decima {
namespace {

TEST(SimplifyPolicyNames, EveryNameRoundTripsAndIsUnique) {
  for (const auto& [name, policy] : kSimplifyPolicyNames) {
    const auto parsed = ParseSimplifyPolicy(name);
    ASSERT_TRUE(parsed.has_value()) << name;
    EXPECT_EQ(*parsed, policy) << name;
    EXPECT_EQ(SimplifyPolicyName(policy), name);
  }
  EXPECT_EQ(ParseSimplifyPolicy("paper"), SimplifyPolicy::kPaper);
  EXPECT_EQ(ParseSimplifyPolicy("tetfusion"), SimplifyPolicy::kTetFusion);
}

TEST(SimplifyPolicyNames, UnknownNamesAreNotGuessed) {
  EXPECT_FALSE(ParseSimplifyPolicy("").has_value());
  EXPECT_FALSE(ParseSimplifyPolicy("Paper").has_value());
  EXPECT_FALSE(ParseSimplifyPolicy("no-such-policy").has_value());
  EXPECT_NE(KnownSimplifyPolicies().find("paper"), std::string::npos);
}

}  // namespace
}  // namespace decima
