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

// Issue 31 item 3: the field policy's interfaces, "free" unless asked otherwise, written out by
// normalization; unknown names are refused (bad_job_specs.h).
TEST(JobSpecFromProto, InterfacesDefaultToFreeAndVoxelFacesIsKept) {
  v1::JobSpec s = Minimal();
  auto p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->interfaces, InterfaceMode::kFree);
  auto n = NormalizeJobSpec(s);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->interfaces(), "free");
  s.set_interfaces("voxel-faces");
  p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->interfaces, InterfaceMode::kVoxelFaces);
  n = NormalizeJobSpec(s);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->interfaces(), "voxel-faces");
}

// Issue 32 part 5: mesh.vtu's compressor, zlib unless asked otherwise, written out by
// normalization; unknown names are refused (bad_job_specs.h).
TEST(JobSpecFromProto, MeshCompressionDefaultsToZlibAndLzmaIsKept) {
  v1::JobSpec s = Minimal();
  auto p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->mesh_compression, VtuCompressor::kZlib);
  auto n = NormalizeJobSpec(s);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->mesh_compression(), "zlib");
  s.set_mesh_compression("lzma");
  p = JobSpecFromProto(s);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->mesh_compression, VtuCompressor::kLzma);
  n = NormalizeJobSpec(s);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->mesh_compression(), "lzma");
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

// A job with a level record, as LevelJobSpec finds it: succeeded, mesh.levels and its labels,
// the range it recorded in metrics.json.
v1::Job RecordedParent() {
  v1::Job p;
  p.set_name("jobs/parent");
  p.set_state(v1::SUCCEEDED);
  p.mutable_spec()->set_volume("volumes/abc");
  p.mutable_spec()->set_regions(2);
  p.mutable_spec()->add_class_means(-1000);
  p.mutable_spec()->add_class_means(40);
  for (const char* f : {"mesh.vtu", "mesh.levels", "labels.nii.gz"}) {
    p.add_artifacts()->set_file_name(f);
  }
  p.set_metrics_json(
      R"({"levels":{"file":"mesh.levels","deepest_reduction":0.9,"exhausted":false}})");
  return p;
}

v1::JobSpec LevelOf(double reduction) {
  v1::JobSpec s;
  s.set_levels_of("jobs/parent");
  s.set_target_reduction(reduction);
  return s;
}

TEST(LevelJobSpec, TakesTheParentsVolumeAndSegmentationAndNormalizes) {
  auto spec = LevelJobSpec(LevelOf(0.8), RecordedParent());
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->volume(), "volumes/abc");
  EXPECT_EQ(spec->regions(), 2);
  EXPECT_EQ(spec->class_means_size(), 2);
  EXPECT_EQ(spec->policy(), v1::FIELD);
  auto normal = NormalizeJobSpec(*spec);
  ASSERT_TRUE(normal.ok()) << normal.status();
  EXPECT_EQ(normal->levels_of(), "jobs/parent");
  auto p = JobSpecFromProto(*normal);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_TRUE(p->levels_file.has_value());
}

TEST(LevelJobSpec, RefusesWhatTheRecordCannotGiveNamingTheField) {
  std::string field;
  // Deeper than the record: the range in the message.
  auto deep = LevelJobSpec(LevelOf(0.95), RecordedParent(), &field);
  EXPECT_EQ(deep.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(deep.status().message(), HasSubstr("(0, 0.9000]"));
  EXPECT_EQ(field, "spec.target_reduction");
  // ... unless the run ran out of collapses: then the last level.
  v1::Job exhausted = RecordedParent();
  exhausted.set_metrics_json(R"({"levels":{"deepest_reduction":0.886,"exhausted":true}})");
  EXPECT_TRUE(LevelJobSpec(LevelOf(0.95), exhausted).ok());
  // No record, or a job that did not succeed: FAILED_PRECONDITION.
  v1::Job plain = RecordedParent();
  plain.mutable_artifacts()->DeleteSubrange(1, 1);
  auto none = LevelJobSpec(LevelOf(0.5), plain, &field);
  EXPECT_EQ(none.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(none.status().message(), HasSubstr("kept no level record (mesh.levels)"));
  v1::Job running = RecordedParent();
  running.set_state(v1::RUNNING);
  EXPECT_EQ(LevelJobSpec(LevelOf(0.5), running).status().code(),
            absl::StatusCode::kFailedPrecondition);
  // What the record fixes cannot be asked otherwise.
  struct Case {
    const char* field;
    std::function<void(v1::JobSpec*)> set;
  };
  for (const Case& c :
       std::vector<Case>{{"spec.volume", [](v1::JobSpec* s) { s->set_volume("volumes/other"); }},
                         {"spec.label_map", [](v1::JobSpec* s) { s->set_label_map("volumes/lm"); }},
                         {"spec.regions", [](v1::JobSpec* s) { s->set_regions(3); }},
                         {"spec.class_means", [](v1::JobSpec* s) { s->add_class_means(2); }},
                         {"spec.policy", [](v1::JobSpec* s) { s->set_policy(v1::PAPER); }}}) {
    v1::JobSpec s = LevelOf(0.5);
    c.set(&s);
    field.clear();
    auto r = LevelJobSpec(s, RecordedParent(), &field);
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << c.field;
    EXPECT_EQ(field, c.field);
  }
  // A level job records no levels of its own, and its parent must be named as a job.
  v1::JobSpec again = *LevelJobSpec(LevelOf(0.5), RecordedParent());
  again.add_outputs("levels");
  EXPECT_FALSE(NormalizeJobSpec(again, &field).ok());
  EXPECT_EQ(field, "spec.outputs");
  again = *LevelJobSpec(LevelOf(0.5), RecordedParent());
  again.set_levels_of("volumes/abc");
  EXPECT_FALSE(NormalizeJobSpec(again, &field).ok());
  EXPECT_EQ(field, "spec.levels_of");
}

}  // namespace
}  // namespace decima::server
