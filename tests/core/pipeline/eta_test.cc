// The job's clock (core/pipeline/eta.h): the stage model follows RunJob's stages and grows with
// the work, and the clock's ETA follows the rates the stages really run at, on simulated time.
#include "core/pipeline/eta.h"

#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

namespace decima::pipeline {
namespace {

std::vector<std::string> Names(const std::vector<StagePlan>& plan) {
  std::vector<std::string> names;
  for (const auto& s : plan) names.push_back(s.stage);
  return names;
}

double Seconds(const std::vector<StagePlan>& plan, const std::string& stage) {
  for (const auto& s : plan) {
    if (s.stage == stage) return s.seconds;
  }
  ADD_FAILURE() << "no stage " << stage;
  return 0;
}

double Total(const std::vector<StagePlan>& plan) {
  double t = 0;
  for (const auto& s : plan) t += s.seconds;
  return t;
}

TEST(StageModel, HasRunJobsStagesInOrderAndGrowsWithTheWork) {
  JobSpec spec;
  const std::array<int64_t, 3> ct{128, 128, 53}, big{256, 256, 113};
  const auto plan = PredictStages(spec, ct);
  EXPECT_EQ(Names(plan), (std::vector<std::string>{"load", "segment", "tetra", "simplify", "write",
                                                   "render", "diff"}));
  for (const auto& s : plan) EXPECT_GT(s.seconds, 0) << s.stage;
  const auto larger = PredictStages(spec, big);
  for (size_t i = 0; i < plan.size(); ++i) EXPECT_GT(larger[i].seconds, plan[i].seconds);

  JobSpec deeper = spec;
  deeper.target_reduction = 0.9;
  EXPECT_GT(Seconds(PredictStages(deeper, ct), "simplify"), Seconds(plan, "simplify"));
  JobSpec floor = spec;
  floor.min_psnr = 45;
  EXPECT_GT(Seconds(PredictStages(floor, ct), "simplify"), Seconds(plan, "simplify"));
  JobSpec given = spec;
  given.label_map = "labels.nii.gz";
  EXPECT_LT(Seconds(PredictStages(given, ct), "segment"), Seconds(plan, "segment"));
  JobSpec curve = spec;
  curve.outputs.push_back("curve");
  EXPECT_EQ(Names(PredictStages(curve, ct)),
            (std::vector<std::string>{"load", "segment", "tetra", "simplify", "write", "render",
                                      "curve", "diff"}));
  JobSpec views = spec;
  views.views = {"anterior", "lateral", "superior"};
  EXPECT_GT(Seconds(PredictStages(views, ct), "render"), Seconds(plan, "render"));
}

// Runs `plan` on a simulated machine where stage i takes plan[i] x factor[i] seconds, reporting
// every 10 % of each stage; calls `check(stage index, fraction, now, estimate, true seconds left)`.
template <typename Check>
void Simulate(const std::vector<StagePlan>& plan, const std::vector<double>& factor, Check check,
              const std::vector<bool>& resumed = {}) {
  JobClock clock(plan);
  std::vector<double> took(plan.size());
  double total = 0;
  for (size_t i = 0; i < plan.size(); ++i) {
    const bool skip = i < resumed.size() && resumed[i];
    took[i] = skip ? 1e-3 : plan[i].seconds * factor[i];
    total += took[i];
  }
  double now = 0;
  for (size_t i = 0; i < plan.size(); ++i) {
    clock.Begin(plan[i].stage, now);
    for (int step = 0; step <= 10; ++step) {
      const double f = step / 10.0;
      const double t = now + took[i] * f;
      check(i, f, t, clock.At(plan[i].stage, f, t), total - t);
    }
    now += took[i];
    clock.End(plan[i].stage, now, i < resumed.size() && resumed[i]);
  }
}

TEST(JobClock, AtTheModelsSpeedTheEtaIsWhatIsLeft) {
  const auto plan = PredictStages(JobSpec{}, {128, 128, 53});
  Simulate(plan, std::vector<double>(plan.size(), 1.0),
           [&](size_t i, double f, double now, JobClock::Estimate e, double left) {
             EXPECT_NEAR(e.eta_seconds, left, 1e-6 * Total(plan)) << plan[i].stage << " " << f;
             EXPECT_NEAR(e.overall, now / Total(plan), 1e-6) << plan[i].stage << " " << f;
           });
}

TEST(JobClock, OnASlowerMachineTheFirstStagesRatesCarryOverToTheRest) {
  const auto plan = PredictStages(JobSpec{}, {256, 256, 113});
  // Everything three times slower than the model: by the time simplify starts, the ETA says so.
  Simulate(plan, std::vector<double>(plan.size(), 3.0),
           [&](size_t i, double f, double, JobClock::Estimate e, double left) {
             if (plan[i].stage == "simplify" && f == 0) {
               EXPECT_NEAR(e.eta_seconds / left, 1.0, 0.15) << e.eta_seconds << " vs " << left;
             }
           });
}

TEST(JobClock, InsideALongStageItsOwnRateTakesOver) {
  const auto plan = PredictStages(JobSpec{}, {128, 128, 53});
  std::vector<double> factor(plan.size(), 1.0);
  for (size_t i = 0; i < plan.size(); ++i) {
    if (plan[i].stage == "simplify") factor[i] = 2.5;  // this scan is harder than the model's
  }
  double error_early = 0, error_late = 0;
  Simulate(plan, factor, [&](size_t i, double f, double, JobClock::Estimate e, double left) {
    if (plan[i].stage != "simplify") return;
    if (f == 0.2) error_early = std::abs(e.eta_seconds / left - 1);
    if (f == 0.8) error_late = std::abs(e.eta_seconds / left - 1);
  });
  EXPECT_LT(error_late, 0.12);
  EXPECT_LT(error_late, error_early);
}

TEST(JobClock, TheOverallFractionNeverGoesBack) {
  const auto plan = PredictStages(JobSpec{}, {128, 128, 53});
  std::vector<double> factor(plan.size(), 0.5);
  for (size_t i = 0; i < plan.size(); ++i) {
    if (plan[i].stage == "render") factor[i] = 20;  // a stall late in the job
  }
  double last = 0;
  Simulate(plan, factor, [&](size_t i, double f, double, JobClock::Estimate e, double) {
    EXPECT_GE(e.overall, last) << plan[i].stage << " " << f;
    EXPECT_LE(e.overall, 1.0);
    EXPECT_GE(e.eta_seconds, 0.0);
    last = e.overall;
  });
  EXPECT_DOUBLE_EQ(last, 1.0);
}

TEST(JobClock, AResumedStageSaysNothingAboutTheMachine) {
  const auto plan = PredictStages(JobSpec{}, {128, 128, 53});
  std::vector<bool> resumed(plan.size(), false);
  size_t simplify = 0;
  for (size_t i = 0; i < plan.size(); ++i) {
    if (plan[i].stage == "segment") resumed[i] = true;  // loaded from its checkpoint in 1 ms
    if (plan[i].stage == "simplify") simplify = i;
  }
  Simulate(
      plan, std::vector<double>(plan.size(), 1.0),
      [&](size_t i, double f, double, JobClock::Estimate e, double left) {
        if (i == simplify && f == 0) {
          EXPECT_NEAR(e.eta_seconds / left, 1.0, 0.02);
        }
      },
      resumed);
}

TEST(JobClock, AStageOutsideThePlanOrAGarbageFractionChangesNothingBadly) {
  JobClock clock(PredictStages(JobSpec{}, {64, 64, 64}));
  clock.Begin("load", 0);
  clock.End("load", 0.1);
  const JobClock::Estimate a = clock.At("export", 0.5, 0.2);
  EXPECT_TRUE(std::isfinite(a.eta_seconds));
  const JobClock::Estimate b = clock.At("segment", std::nan(""), 0.3);
  EXPECT_TRUE(std::isfinite(b.eta_seconds));
  EXPECT_GE(b.overall, a.overall);
}

}  // namespace
}  // namespace decima::pipeline
