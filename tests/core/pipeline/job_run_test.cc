// JobRun, the state RunJob carries between stages: stages report progress in the order they run,
// a cancelled run stops at the next stage, each timed stage gets its seconds and memory in
// metrics.json, and the scratch folder leaves nothing behind.
#include "core/pipeline/job_run.h"

#include <gtest/gtest.h>

#include <fstream>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <vector>

#include "tests/testing/test_data.h"

namespace decima::pipeline {
namespace {

namespace fs = std::filesystem;

struct Event {
  std::string stage;
  double fraction;
  std::string message;
  bool operator==(const Event&) const = default;
};

ProgressFn Recorder(std::vector<Event>* events) {
  return [events](const Progress& p) { events->push_back({p.stage, p.fraction, p.message}); };
}

TEST(JobRun, StagesReportProgressInTheOrderTheyRunUnderTheirOwnNames) {
  const fs::path dir = decima::testing::MakeScratchDir("job_run");
  std::vector<Event> events;
  JobRun run(dir / "out", Recorder(&events), nullptr);
  ASSERT_TRUE(run.Open().ok());
  for (const char* name : {"load", "segment", "tetra"}) {
    auto stage = run.Stage(name);
    ASSERT_TRUE(stage.ok()) << stage.status();
    stage->Report(0, "start");
    // A module's own progress arrives under the stage's name whatever it called itself.
    stage->Forward()({"module-internal", 0.5, "half", {}});
    stage->Report(1, "done");
  }
  const std::vector<Event> expected = {
      {"load", 0, "start"},    {"load", 0.5, "half"},    {"load", 1, "done"},
      {"segment", 0, "start"}, {"segment", 0.5, "half"}, {"segment", 1, "done"},
      {"tetra", 0, "start"},   {"tetra", 0.5, "half"},   {"tetra", 1, "done"}};
  EXPECT_EQ(events, expected);
}

TEST(JobRun, ACancelledRunStopsAtTheNextStageWithoutReportingIt) {
  const fs::path dir = decima::testing::MakeScratchDir("job_run");
  std::vector<Event> events;
  CancelToken cancel;
  JobRun run(dir / "out", Recorder(&events), &cancel);
  ASSERT_TRUE(run.Open().ok());
  {
    auto stage = run.Stage("load");
    ASSERT_TRUE(stage.ok()) << stage.status();
    stage->Report(1, "loaded");
    cancel.Cancel();  // fires inside "load", after its last check
    EXPECT_EQ(stage->CheckCancelled().code(), absl::StatusCode::kCancelled);
  }
  auto next = run.Stage("segment");
  EXPECT_EQ(next.status().code(), absl::StatusCode::kCancelled);
  EXPECT_NE(next.status().message().find("segment"), std::string::npos) << next.status();
  ASSERT_EQ(events.size(), 1u);
  EXPECT_EQ(events[0].stage, "load");
}

TEST(JobRun, MetricsHoldEachTimedStagesSecondsAndEveryStagesMemory) {
  const fs::path dir = decima::testing::MakeScratchDir("job_run");
  JobRun run(dir / "out", nullptr, nullptr);
  ASSERT_TRUE(run.Open().ok());
  {
    auto render = run.Stage("render");
    ASSERT_TRUE(render.ok());
    render->SplitTiming("fidelity");
  }
  {
    auto diff = run.Stage("diff", JobRun::Timing::kNotRecorded);
    ASSERT_TRUE(diff.ok());
    diff->End();
    diff->End();  // once only
  }
  run.metrics()["input"] = {{"voxels", 8}};
  ASSERT_TRUE(run.WriteMetrics().ok());
  const JobResult result = run.TakeResult();
  ASSERT_EQ(result.artifacts.size(), 1u);
  EXPECT_EQ(result.artifacts[0].name, "metrics.json");
  EXPECT_EQ(result.artifacts[0].path, dir / "out" / "metrics.json");
  std::ifstream in(dir / "out" / "metrics.json");
  const auto m = nlohmann::json::parse(in);
  EXPECT_EQ(m["input"]["voxels"], 8);
  std::set<std::string> seconds;
  for (const auto& [k, v] : m["seconds"].items()) seconds.insert(k);
  EXPECT_EQ(seconds, (std::set<std::string>{"fidelity", "render", "total"}));
  EXPECT_GE(m["seconds"]["total"].get<double>(), m["seconds"]["render"].get<double>());
  std::set<std::string> memory;
  for (const auto& [k, v] : m["stage_peak_rss_mb"].items()) memory.insert(k);
  EXPECT_EQ(memory, (std::set<std::string>{"render", "diff"}));
  EXPECT_EQ(m["resumed_stages"], nlohmann::json::array());
}

TEST(JobRun, TheScratchFolderGoesWithTheRunAndAnEarlierAttemptsIsCleared) {
  const fs::path dir = decima::testing::MakeScratchDir("job_run");
  fs::path scratch_file;
  {
    JobRun run(dir / "out", nullptr, nullptr);
    ASSERT_TRUE(run.Open().ok());
    scratch_file = run.ScratchPath("comparison.png");
    std::ofstream(scratch_file) << "picture";
    ASSERT_TRUE(fs::exists(scratch_file));
    EXPECT_NE(scratch_file.parent_path(), dir / "out");
  }
  EXPECT_FALSE(fs::exists(scratch_file.parent_path()));
  EXPECT_TRUE(fs::is_empty(dir / "out"));
  // A crashed attempt's scratch folder is emptied by the next attempt's Open.
  fs::create_directories(scratch_file.parent_path());
  std::ofstream(scratch_file) << "stale";
  JobRun again(dir / "out", nullptr, nullptr);
  ASSERT_TRUE(again.Open().ok());
  EXPECT_FALSE(fs::exists(scratch_file));
}

TEST(JobRun, AnOutputFolderThatCannotBeMadeIsAnErrorNamingIt) {
  const fs::path dir = decima::testing::MakeScratchDir("job_run");
  std::ofstream(dir / "file") << "x";
  JobRun run(dir / "file" / "out", nullptr, nullptr);
  const absl::Status st = run.Open();
  EXPECT_EQ(st.code(), absl::StatusCode::kInternal);
  EXPECT_NE(st.message().find((dir / "file" / "out").string()), std::string::npos) << st;
}

TEST(JobRun, OncePlannedEveryEventCarriesTheJobsFractionAndEtaAndMetricsTheForecast) {
  const fs::path dir = decima::testing::MakeScratchDir("job_run");
  std::vector<Progress> events;
  JobRun run(
      dir / "out", [&](const Progress& p) { events.push_back(p); }, nullptr);
  ASSERT_TRUE(run.Open().ok());
  {
    auto load = run.Stage("load");
    ASSERT_TRUE(load.ok()) << load.status();
    load->Report(0, "reading");
    run.Plan(PredictStages(JobSpec{}, {32, 32, 32}));
    load->Report(1, "read");
  }
  for (const char* name : {"segment", "tetra", "simplify"}) {
    auto stage = run.Stage(name);
    ASSERT_TRUE(stage.ok()) << stage.status();
    stage->Report(0, "start");
    stage->Forward()({"module-internal", 0.5, "half", {}});
    stage->Report(1, "done");
  }
  ASSERT_EQ(events.size(), 11u);
  // Before the plan the job's own figures are unknown; after it every event has them.
  EXPECT_LT(events[0].overall, 0);
  EXPECT_LT(events[0].eta_seconds, 0);
  double last = 0;
  for (size_t i = 1; i < events.size(); ++i) {
    EXPECT_GE(events[i].overall, last) << i;
    EXPECT_LT(events[i].overall, 1) << i << ": write, render and diff are still to come";
    EXPECT_GT(events[i].eta_seconds, 0) << i;
    last = events[i].overall;
  }
  ASSERT_TRUE(run.WriteMetrics().ok());
  std::ifstream in(dir / "out" / "metrics.json");
  const auto m = nlohmann::json::parse(in);
  ASSERT_TRUE(m.contains("eta")) << m.dump();
  EXPECT_GT(m["eta"]["predicted_seconds"]["simplify"].get<double>(), 0);
  EXPECT_EQ(m["eta"]["predicted_seconds"].size(), 7u);
  // A forecast of the whole job as each stage after the plan began.
  EXPECT_TRUE(m["eta"]["forecast_total_seconds_at_stage_start"].contains("simplify"));
  EXPECT_FALSE(m["eta"]["forecast_total_seconds_at_stage_start"].contains("load"));
}

}  // namespace
}  // namespace decima::pipeline
