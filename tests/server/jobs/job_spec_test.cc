// JobSpecFromProto / NormalizeJobSpec: defaults applied once, every out-of-range value refused
// naming its field, and a stored (normalized) spec converts to the same pipeline spec again.
#include "server/jobs/job_spec.h"

#include <gmock/gmock.h>
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <limits>

#include "tests/server/jobs/bad_job_specs.h"

namespace decima::server {
namespace {

using ::testing::HasSubstr;
using ::testing::StartsWith;

v1::JobSpec Minimal() {
  v1::JobSpec s;
  s.set_volume("volumes/abc");
  return s;
}

TEST(JobSpecFromProto, AnEmptySpecGetsTheDocumentedDefaults) {
  auto p = JobSpecFromProto(Minimal());
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->regions, 3);
  EXPECT_DOUBLE_EQ(p->target_reduction, 0.5);
  EXPECT_EQ(p->policy, SimplifyPolicy::kField);
  EXPECT_EQ(p->error_tolerance, 0);
  EXPECT_EQ(p->weights.regional, ErrorWeights{}.regional);
  EXPECT_EQ(p->views, std::vector<std::string>{"anterior"});
  EXPECT_EQ(p->image_size, 512);
  EXPECT_EQ(p->transfer_function, "auto");
}

TEST(JobSpecFromProto, ZeroTargetReductionIsARealValueNotTheDefault) {
  v1::JobSpec s = Minimal();
  s.set_target_reduction(0);
  s.set_error_tolerance(0.25);
  auto p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->target_reduction, 0) << "0 = no target: simplify down to the error tolerance";
}

TEST(JobSpecFromProto, ExplicitValuesAreKept) {
  v1::JobSpec s = Minimal();
  s.set_regions(4);
  s.add_class_means(1);
  s.add_class_means(2);
  s.add_class_means(3);
  s.add_class_means(4);
  s.set_target_reduction(0.9);
  s.set_policy(v1::TETFUSION);
  s.mutable_weights()->set_shape(0);
  s.add_views("lateral");
  s.add_views("30,15");
  s.set_image_size(64);
  s.set_transfer_function("ct-bone");
  auto p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->regions, 4);
  EXPECT_EQ(p->class_means.size(), 4u);
  EXPECT_DOUBLE_EQ(p->target_reduction, 0.9);
  EXPECT_EQ(p->policy, SimplifyPolicy::kTetFusion);
  EXPECT_EQ(p->weights.shape, 0);
  EXPECT_EQ(p->weights.regional, ErrorWeights{}.regional);
  EXPECT_EQ(p->views, (std::vector<std::string>{"lateral", "30,15"}));
  EXPECT_EQ(p->image_size, 64);
  EXPECT_EQ(p->transfer_function, "ct-bone");
}

// Issue 31 item 4: a floor alone means "as far as the floor allows" (target 0, no target), a
// floor with a reduction keeps the reduction as the maximum; both survive normalization.
TEST(JobSpecFromProto, MinPsnrAloneDropsTheDefaultTargetAndIsStored) {
  v1::JobSpec s = Minimal();
  auto p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_FALSE(p->min_psnr.has_value());
  s.set_min_psnr(50);
  p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  ASSERT_TRUE(p->min_psnr.has_value());
  EXPECT_EQ(*p->min_psnr, 50);
  EXPECT_EQ(p->target_reduction, 0);
  s.set_target_reduction(0.8);
  p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_DOUBLE_EQ(p->target_reduction, 0.8);
  auto n = NormalizeJobSpec(Minimal());
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_FALSE(n->has_min_psnr()) << "no floor unless asked for";
  v1::JobSpec floor_only = Minimal();
  floor_only.set_min_psnr(42.5);
  n = NormalizeJobSpec(floor_only);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->min_psnr(), 42.5);
  EXPECT_TRUE(n->has_target_reduction());
  EXPECT_EQ(n->target_reduction(), 0);
  auto again = JobSpecFromProto(*n);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->target_reduction, 0);
  EXPECT_EQ(*again->min_psnr, 42.5);
}

TEST(NormalizeJobSpec, WritesEveryDefaultAndIsIdempotent) {
  auto n = NormalizeJobSpec(Minimal());
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_TRUE(n->has_regions() && n->has_target_reduction() && n->has_error_tolerance() &&
              n->has_image_size() && n->weights().has_regional() && n->weights().has_neighbour());
  EXPECT_EQ(n->policy(), v1::FIELD);
  EXPECT_EQ(n->views_size(), 1);
  auto again = NormalizeJobSpec(*n);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(google::protobuf::util::MessageDifferencer::Equals(*n, *again))
      << n->DebugString() << "\nvs\n"
      << again->DebugString();
}

TEST(NormalizeJobSpec, OutputsAreCaseInsensitiveStoredInOrderAndDefaultSmall) {
  auto n = NormalizeJobSpec(Minimal());
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_THAT(n->outputs(),
              ::testing::ElementsAre("vtu", "labels", "images", "segmentation", "report"));
  EXPECT_EQ(n->vtu_compression_level(), 1);
  v1::JobSpec s = Minimal();
  s.add_outputs("Report");
  s.add_outputs("MSH");
  s.set_vtu_compression_level(0);
  n = NormalizeJobSpec(s);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_THAT(n->outputs(), ::testing::ElementsAre("msh", "report"));
  EXPECT_EQ(n->vtu_compression_level(), 0);
  s.add_outputs("obj");  // not a kind
  std::string field;
  EXPECT_EQ(NormalizeJobSpec(s, &field).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(field, "spec.outputs");
  s = Minimal();
  s.add_outputs("vtu");
  s.add_outputs("VTU");
  EXPECT_EQ(NormalizeJobSpec(s, &field).status().code(), absl::StatusCode::kInvalidArgument);
  s = Minimal();
  s.set_vtu_compression_level(12);
  EXPECT_EQ(NormalizeJobSpec(s, &field).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(field, "spec.vtu_compression_level");
}

TEST(JobSpecFromProto, EveryBadSpecIsInvalidArgumentNamingItsField) {
  const auto cases = BadJobSpecs();
  ASSERT_GE(cases.size(), 20u);
  for (const auto& c : cases) {
    v1::JobSpec s = Minimal();
    c.mutate(&s);
    std::string field;
    auto p = JobSpecFromProto(s, &field);
    ASSERT_FALSE(p.ok()) << c.name << " was accepted";
    EXPECT_EQ(p.status().code(), absl::StatusCode::kInvalidArgument) << c.name;
    EXPECT_THAT(std::string(p.status().message()), StartsWith(c.field + ":")) << c.name;
    EXPECT_EQ(field, c.field) << c.name;
  }
}

}  // namespace
}  // namespace decima::server
