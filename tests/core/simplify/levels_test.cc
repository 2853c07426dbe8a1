// Levels of detail from one run (levels.h): a level taken from a deep run's record is the mesh a
// run to that reduction gives, and what is outside the record is refused with its range.
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/simplify/levels.h"
#include "core/simplify/simplify.h"
#include "tests/core/simplify/simplify_test_util.h"

namespace decima {
namespace {

using testing::MakePhantomMesh;

SimplifyOptions Field(double reduction, double floor, int threads = 2) {
  SimplifyOptions o;
  o.policy = SimplifyPolicy::kField;
  o.target_reduction = reduction;
  o.record_levels_to = floor;
  o.threads = threads;
  return o;
}

using testing::ExpectSameMesh;

// A mesh shorter than the parallel rounds' minimum runs the serial loop only, whose order does not
// depend on the target: the level of a run to 70 % is a plain run (no record) to each reduction.
TEST(Levels, ALevelOfADeepSerialRunIsAPlainRunToItsReduction) {
  auto pm = MakePhantomMesh(20, 40);
  auto deep = Simplify(pm.mesh, Field(0.7, 0.7));
  ASSERT_TRUE(deep.ok()) << deep.status();
  ASSERT_TRUE(deep->levels.has_value());
  ASSERT_TRUE(deep->reached_target) << deep->stop_message;
  EXPECT_FALSE(deep->levels->exhausted);
  EXPECT_GE(deep->levels->deepest_reduction(), 0.7);
  for (double r : {0.2, 0.5, 0.65, 0.7}) {
    auto fresh = Simplify(pm.mesh, Field(r, 0));
    ASSERT_TRUE(fresh.ok()) << fresh.status();
    EXPECT_FALSE(fresh->levels.has_value());
    auto level = ExtractLevel(pm.mesh, *deep->levels, r, 2);
    ASSERT_TRUE(level.ok()) << level.status();
    ExpectSameMesh(*fresh, *level, "reduction " + std::to_string(r));
    EXPECT_EQ(fresh->collapses, level->collapses) << r;
  }
}

// With the parallel rounds (a 40^3 phantom: four slabs), runs to different targets with the
// same floor make the same collapses, so each one's level at the other's target is that run's
// mesh; and the level at the floor is what the engine itself built at the floor without a record.
TEST(Levels, RunsWithOneFloorAgreeAtEveryLevelThroughTheParallelRounds) {
  auto pm = MakePhantomMesh(40, 40);
  int rounds = 0;
  auto at30 = Simplify(pm.mesh, Field(0.3, 0.7), [&](const Progress& e) {
    rounds += e.message.find("slabs removed") != std::string::npos;
  });
  auto at60 = Simplify(pm.mesh, Field(0.6, 0.7, 1));
  auto plain70 = Simplify(pm.mesh, Field(0.7, 0));
  ASSERT_TRUE(at30.ok() && at60.ok() && plain70.ok());
  EXPECT_GE(rounds, 2);
  ASSERT_TRUE(at30->levels && at60->levels);
  EXPECT_EQ(at30->levels->removed_vertex, at60->levels->removed_vertex);
  EXPECT_EQ(at30->levels->survivor, at60->levels->survivor);
  EXPECT_EQ(at30->levels->cells_deleted, at60->levels->cells_deleted);
  EXPECT_NEAR(at30->achieved_reduction, 0.3, 0.01);
  EXPECT_NEAR(at60->achieved_reduction, 0.6, 0.01);
  auto l30 = ExtractLevel(pm.mesh, *at60->levels, 0.3);
  auto l60 = ExtractLevel(pm.mesh, *at30->levels, 0.6);
  auto l70 = ExtractLevel(pm.mesh, *at30->levels, 0.7);
  ASSERT_TRUE(l30.ok() && l60.ok() && l70.ok());
  ExpectSameMesh(*at30, *l30, "30 %");
  ExpectSameMesh(*at60, *l60, "60 %");
  ExpectSameMesh(*plain70, *l70, "70 %, against the engine's own mesh");
  // Why the floor paces the rounds: a plain run to 30 % paces them by its own target and makes
  // other collapses (this is what a record paced by the target would get wrong).
  auto plain30 = Simplify(pm.mesh, Field(0.3, 0));
  ASSERT_TRUE(plain30.ok());
  EXPECT_NE(plain30->mesh.tets, at30->mesh.tets);
}

TEST(Levels, AReductionOutsideTheRecordIsRefusedWithTheRange) {
  auto pm = MakePhantomMesh(20, 40);
  auto run = Simplify(pm.mesh, Field(0.3, 0.5));
  ASSERT_TRUE(run.ok()) << run.status();
  const double deepest = run->levels->deepest_reduction();
  for (double r : {0.6, deepest + 0.01, -0.1, 1.0, 0.0}) {
    auto level = ExtractLevel(pm.mesh, *run->levels, r);
    ASSERT_FALSE(level.ok()) << r;
    EXPECT_EQ(level.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(std::string(level.status().message()).find("outside the recorded range (0, 0.5"),
              std::string::npos)
        << level.status();
  }
  EXPECT_TRUE(ExtractLevel(pm.mesh, *run->levels, deepest).ok());
}

// A run that ran out of collapses before its floor recorded everything there is: any deeper
// reduction is its last level, which does not reach the target, as a run to it would not.
TEST(Levels, AnExhaustedRecordGivesItsLastLevelForAnyDeeperReduction) {
  auto pm = MakePhantomMesh(16, 40);
  auto run = Simplify(pm.mesh, Field(0.5, 0.99));
  ASSERT_TRUE(run.ok()) << run.status();
  ASSERT_TRUE(run->levels->exhausted);
  const double deepest = run->levels->deepest_reduction();
  ASSERT_LT(deepest, 0.99);
  auto last = ExtractLevel(pm.mesh, *run->levels, 0.99);
  auto fresh = Simplify(pm.mesh, Field(0.99, 0));
  ASSERT_TRUE(last.ok() && fresh.ok());
  EXPECT_FALSE(last->reached_target);
  EXPECT_NEAR(last->achieved_reduction, deepest, 1e-12);
  ExpectSameMesh(*fresh, *last, "deepest");
  // 0 is "no target" there as in Simplify: every collapse.
  auto all = ExtractLevel(pm.mesh, *run->levels, 0);
  auto no_target = Simplify(pm.mesh, Field(0, 0));
  ASSERT_TRUE(all.ok() && no_target.ok()) << all.status();
  ExpectSameMesh(*no_target, *all, "no target");
}

TEST(Levels, ABrokenRecordOrAnotherMeshIsRefusedWithWhatIsWrong) {
  auto pm = MakePhantomMesh(16, 40);
  auto run = Simplify(pm.mesh, Field(0.3, 0.3));
  ASSERT_TRUE(run.ok()) << run.status();
  auto refused = [&](SimplifyLevels levels, const TetMesh& base, const std::string& words) {
    auto r = ExtractLevel(base, levels, 0.1);
    ASSERT_FALSE(r.ok()) << words;
    EXPECT_NE(std::string(r.status().message()).find(words), std::string::npos) << r.status();
  };
  SimplifyLevels l = *run->levels;
  l.survivor.pop_back();
  refused(l, pm.mesh, "expected one of each per collapse");
  l = *run->levels;
  l.survivor[3] = int32_t(l.base_vertices);
  refused(l, pm.mesh, "collapse 3:");
  l = *run->levels;
  l.survivor[5] = l.removed_vertex[0];
  refused(l, pm.mesh, "was removed by an earlier collapse");
  l = *run->levels;
  l.cells_deleted[0] = 60000;
  refused(l, pm.mesh, "the collapses delete");
  l = *run->levels;
  l.cells_deleted[0] += 1;
  refused(l, pm.mesh, "the record is not of this mesh");
  auto other = MakePhantomMesh(17, 40);
  refused(*run->levels, other.mesh, "recorded on a mesh of");
}

TEST(Levels, OnlyTheFieldPolicyRecordsLevels) {
  SimplifyOptions o = Field(0.3, 0.5);
  o.policy = SimplifyPolicy::kPaper;
  const absl::Status s = ValidateSimplifyOptions(o);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(s.message()).find("record_levels_to"), std::string::npos) << s;
  o = Field(0.3, 1.5);
  EXPECT_FALSE(ValidateSimplifyOptions(o).ok());
}

}  // namespace
}  // namespace decima
