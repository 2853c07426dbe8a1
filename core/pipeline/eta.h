// The job's clock: how long each stage of a job should take (a model of the stage's work from the
// volume's size and the spec), and, while the job runs, how its stages actually go against that
// model. It gives every progress event the whole job's fraction and the seconds left, from the
// first event after the volume is loaded (README "ETA").
//
// Why a model and measured rates together: the model alone is the reference machine's speed
// (another machine, another load, another scan differ by a factor), and the measured rate alone
// knows nothing before a stage starts (the old client bar weighted stages by one CT job and
// showed no ETA below 2 %). The clock scales the model by how fast the finished stages and the
// open one ran against it, and inside a long stage it trusts that stage's own rate more as the
// stage advances.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/pipeline/pipeline.h"

namespace decima::pipeline {

struct StagePlan {
  std::string stage;   // a stage name as JobRun::Stage gets it
  double seconds = 0;  // predicted on the reference machine
};

// The stages RunJob will run for `spec` on a volume of `dims`, in order, with the seconds each
// should take on the reference machine (the constants in eta.cc, measured: README "ETA").
std::vector<StagePlan> PredictStages(const JobSpec& spec, const std::array<int64_t, 3>& dims);

class JobClock {
 public:
  struct Estimate {
    double overall = 0;      // 0..1, never lower than an earlier estimate
    double eta_seconds = 0;  // >= 0
  };

  // `plan` as PredictStages gives it; times are seconds since the job began.
  explicit JobClock(std::vector<StagePlan> plan);

  // The stage `stage` starts at `now` (a stage the plan lacks adds nothing and is timed apart).
  void Begin(const std::string& stage, double now);
  // The stage ended at `now`; `resumed`: it was loaded from a checkpoint, so its time says
  // nothing about the machine's speed and its predicted time is dropped.
  void End(const std::string& stage, double now, bool resumed = false);
  // Where the job is when `stage` reports `fraction` of its own work at `now`.
  Estimate At(const std::string& stage, double fraction, double now);

  const std::vector<StagePlan>& plan() const { return plan_; }

 private:
  struct Entry {
    double predicted = 0;
    double began = -1, ended = -1;
    bool resumed = false;
  };
  std::vector<StagePlan> plan_;
  std::vector<Entry> entries_;
  double last_overall_ = 0;
  int Find(const std::string& stage) const;
};

}  // namespace decima::pipeline
