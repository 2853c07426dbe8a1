// The PSNR floor (psnr_floor.h, issue 31 item 4): the kept level measures >= the floor by the
// job's own fidelity code, the next level the search measured is below it and at most one search
// step deeper, and the target reduction stops the job first when it is the shallower of the two.
#include "core/pipeline/psnr_floor.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "core/metrics/fidelity.h"
#include "core/simplify/levels.h"
#include "tests/core/simplify/simplify_test_util.h"

namespace decima::pipeline {
namespace {

using decima::testing::MakePhantomMesh;

SimplifyOptions Field(double target) {
  SimplifyOptions o;
  o.policy = SimplifyPolicy::kField;
  o.target_reduction = target;
  o.threads = 2;
  return o;
}

// The figure metrics.json reports for a mesh, through MeasureFidelity, not the search's own call.
double JobPsnr(const Volume& image, const TetMesh& mesh) {
  auto m = MeasureFidelity(image, mesh);
  EXPECT_TRUE(m.ok()) << m.status();
  return m.ok() ? m->psnr_db : std::numeric_limits<double>::quiet_NaN();
}

// A floor between the 20 % and the deepest level's PSNR on a noisy phantom: the PSNR of the
// level at 40 % of a run recorded to 99 %, so the floor stops the search near there.
struct FloorCase {
  decima::testing::PhantomMesh pm;
  double floor_db = 0;
  double deepest_db = 0;
  explicit FloorCase(int64_t n = 24) : pm(MakePhantomMesh(n, 40)) {
    SimplifyOptions o = Field(0.99);
    o.record_levels_to = 0.99;
    auto deep = Simplify(pm.mesh, o);
    EXPECT_TRUE(deep.ok()) << deep.status();
    deepest_db = JobPsnr(pm.phantom.image, deep->mesh);
    auto at40 = ExtractLevel(pm.mesh, *deep->levels, 0.4, 2);
    EXPECT_TRUE(at40.ok()) << at40.status();
    floor_db = JobPsnr(pm.phantom.image, at40->mesh);
  }
};

// Levels only (a job that writes the record): the kept mesh is a level of it.
TEST(PsnrFloor, KeepsTheDeepestLevelAboveTheFloorAndTheNextIsBelowIt) {
  FloorCase s;
  ASSERT_GT(s.floor_db, s.deepest_db + 1) << "the phantom must lose PSNR past 40 %";
  PsnrFloorSearch search;
  auto r = SimplifyToPsnrFloor(s.pm.phantom.image, s.pm.mesh, Field(0), s.floor_db,
                               /*refine=*/false, &search);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(search.floor_stopped);
  EXPECT_EQ(r->stop_reason, StopReason::kPsnrFloor);
  EXPECT_FALSE(r->reached_target) << "no target";
  EXPECT_GT(r->achieved_reduction, 0.2);
  EXPECT_LT(r->achieved_reduction, 0.7);
  EXPECT_FALSE(search.kept.run);
  // The kept mesh, measured as a job measures it, keeps the floor, and is the reported level.
  const double kept_db = JobPsnr(s.pm.phantom.image, r->mesh);
  EXPECT_GE(kept_db, s.floor_db);
  EXPECT_EQ(kept_db, search.kept.psnr_db);
  EXPECT_EQ(r->achieved_reduction, search.kept.reduction);
  // The level just deeper (at most one search step, plus the last collapse's overshoot) is below.
  ASSERT_TRUE(search.deeper.has_value());
  EXPECT_FALSE(search.deeper->run);
  EXPECT_GT(search.deeper->reduction, r->achieved_reduction);
  EXPECT_LE(search.deeper->reduction - r->achieved_reduction, kPsnrSearchStep + 0.002);
  ASSERT_TRUE(r->levels.has_value());
  auto deeper = ExtractLevel(s.pm.mesh, *r->levels, search.deeper->requested, 2);
  ASSERT_TRUE(deeper.ok()) << deeper.status();
  EXPECT_LT(JobPsnr(s.pm.phantom.image, deeper->mesh), s.floor_db);
  auto kept = ExtractLevel(s.pm.mesh, *r->levels, search.kept.requested, 2);
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_EQ(kept->mesh.tets, r->mesh.tets) << "the kept mesh is the record's level";
  EXPECT_NE(r->stop_message.find("PSNR floor"), std::string::npos) << r->stop_message;
  // Bounded: the deepest level, then one bisection step per halving down to the step.
  EXPECT_LE(search.probes.size(), 1u + size_t(std::ceil(std::log2(0.99 / kPsnrSearchStep))));
}

// With the refinement (a job without the levels output): runs between the level kept and the
// deepest level; the kept run is a plain run to its reduction, at least as deep as the level, and
// the run one step deeper is below the floor. 40^3: big enough for the parallel rounds, whose
// pacing by the record's depth is what makes a run better than a level (below their minimum the
// serial loop gives levels equal to runs).
TEST(PsnrFloor, RunsRefineTheLevelsAnswer) {
  FloorCase s(40);
  PsnrFloorSearch levels_only, refined;
  auto level = SimplifyToPsnrFloor(s.pm.phantom.image, s.pm.mesh, Field(0), s.floor_db,
                                   /*refine=*/false, &levels_only);
  ASSERT_TRUE(level.ok()) << level.status();
  auto r = SimplifyToPsnrFloor(s.pm.phantom.image, s.pm.mesh, Field(0), s.floor_db,
                               /*refine=*/true, &refined);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(refined.floor_stopped);
  EXPECT_EQ(r->stop_reason, StopReason::kPsnrFloor);
  ASSERT_TRUE(refined.kept.run) << "this phantom's runs keep the floor deeper than its levels";
  EXPECT_GE(r->achieved_reduction, level->achieved_reduction);
  EXPECT_FALSE(r->levels.has_value()) << "a run has no record";
  const double kept_db = JobPsnr(s.pm.phantom.image, r->mesh);
  EXPECT_GE(kept_db, s.floor_db);
  EXPECT_EQ(kept_db, refined.kept.psnr_db);
  auto again = Simplify(s.pm.mesh, Field(refined.kept.requested));
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->mesh.tets, r->mesh.tets) << "the kept mesh is a plain run to its reduction";
  ASSERT_TRUE(refined.deeper.has_value());
  EXPECT_TRUE(refined.deeper->run);
  EXPECT_GT(refined.deeper->reduction, r->achieved_reduction);
  EXPECT_LE(refined.deeper->reduction - r->achieved_reduction, kPsnrSearchStep + 0.002);
  auto deeper = Simplify(s.pm.mesh, Field(refined.deeper->requested));
  ASSERT_TRUE(deeper.ok()) << deeper.status();
  EXPECT_LT(JobPsnr(s.pm.phantom.image, deeper->mesh), s.floor_db);
  EXPECT_LE(refined.probes.size(),
            2u * (1u + size_t(std::ceil(std::log2(0.99 / kPsnrSearchStep)))));
}

TEST(PsnrFloor, WhicheverStopsFirstWins) {
  FloorCase s;
  // A target shallower than the floor's stop: the target wins, exactly as a plain run to it.
  PsnrFloorSearch search;
  auto shallow =
      SimplifyToPsnrFloor(s.pm.phantom.image, s.pm.mesh, Field(0.2), s.floor_db, true, &search);
  ASSERT_TRUE(shallow.ok()) << shallow.status();
  EXPECT_FALSE(search.floor_stopped);
  EXPECT_TRUE(shallow->reached_target) << shallow->stop_message;
  EXPECT_EQ(shallow->stop_reason, StopReason::kTargetReached);
  EXPECT_GE(shallow->achieved_reduction, 0.2);
  EXPECT_LT(shallow->achieved_reduction, 0.21);
  EXPECT_GE(JobPsnr(s.pm.phantom.image, shallow->mesh), s.floor_db);
  EXPECT_EQ(search.probes.size(), 1u) << "the deepest level keeps the floor: no bisection";
  // A deeper target: the floor stops first, short of the target.
  auto deep =
      SimplifyToPsnrFloor(s.pm.phantom.image, s.pm.mesh, Field(0.9), s.floor_db, true, &search);
  ASSERT_TRUE(deep.ok()) << deep.status();
  EXPECT_TRUE(search.floor_stopped);
  EXPECT_FALSE(deep->reached_target);
  EXPECT_LT(deep->achieved_reduction, 0.9);
  EXPECT_GE(JobPsnr(s.pm.phantom.image, deep->mesh), s.floor_db);
}

TEST(PsnrFloor, AFloorNoLevelKeepsGivesTheUnsimplifiedMesh) {
  auto pm = MakePhantomMesh(12, 40);
  PsnrFloorSearch search;
  auto r = SimplifyToPsnrFloor(pm.phantom.image, pm.mesh, Field(0.5), 1e6, true, &search);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(search.floor_stopped);
  EXPECT_EQ(r->output_cells, pm.mesh.tet_count());
  EXPECT_EQ(r->mesh.positions, pm.mesh.positions);
  EXPECT_EQ(search.kept.reduction, 0);
  EXPECT_TRUE(std::isinf(JobPsnr(pm.phantom.image, r->mesh)));
}

TEST(PsnrFloor, RefusesABadFloorAndOtherPolicies) {
  auto pm = MakePhantomMesh(8, 0);
  for (double bad : {std::nan(""), -1.0, 0.0, std::numeric_limits<double>::infinity()}) {
    auto r = SimplifyToPsnrFloor(pm.phantom.image, pm.mesh, Field(0.5), bad, true, nullptr);
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << bad;
  }
  SimplifyOptions paper = Field(0.5);
  paper.policy = SimplifyPolicy::kPaper;
  auto r = SimplifyToPsnrFloor(pm.phantom.image, pm.mesh, paper, 40, true, nullptr);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace decima::pipeline
