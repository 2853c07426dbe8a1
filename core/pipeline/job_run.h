// What one RunJob carries from stage to stage: the output folder and its artifacts, the scratch
// folder, progress, cancellation, the seconds and peak memory of each stage, and metrics.json.
//
// A stage is a scope, `DECIMA_ASSIGN_OR_RETURN(JobRun::StageScope stage, run.Stage("tetra"))`:
// opening it checks the cancellation token (a cancelled job stops at the next stage boundary even
// when the previous stage's own checks missed it), the stage reports progress under its name, and
// when the scope ends it records the stage's seconds under `metrics.json`'s "seconds" and its peak
// memory under "stage_peak_rss_mb". A stage to add is one more function that opens its own scope.
//
// Not thread-safe: one JobRun belongs to the thread running the job.
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/pipeline/eta.h"
#include "core/pipeline/pipeline.h"

namespace decima::pipeline {

// Peak resident memory of the process, in MiB: overall (getrusage, never reset) and per stage
// (the kernel's VmHWM, which writing "5" to /proc/self/clear_refs resets to the current RSS, so
// each stage's figure is the highest RSS reached during that stage). Where the reset is refused
// (not Linux, a restricted /proc), a stage's figure is the peak so far and `resettable` says so.
class PeakRss {
 public:
  PeakRss();
  void EndStage(const std::string& stage);
  const nlohmann::ordered_json& stages() const { return stages_; }
  // The kernel keeps ru_maxrss and VmHWM slightly apart (they are sampled at different
  // moments): the larger of the process's figure and every stage's is the peak.
  double PeakMb() const;
  bool resettable() const { return resettable_; }

 private:
  nlohmann::ordered_json stages_ = nlohmann::ordered_json::object();
  bool resettable_ = false;
};

class JobRun {
 public:
  // Whether a stage's wall seconds go into "seconds" (every stage's memory is recorded). The last
  // stage ("diff") is not timed: its end is the job's "total".
  enum class Timing { kRecorded, kNotRecorded };

  class StageScope {
   public:
    StageScope(StageScope&& other) noexcept;
    StageScope(const StageScope&) = delete;
    StageScope& operator=(const StageScope&) = delete;
    StageScope& operator=(StageScope&&) = delete;
    ~StageScope() { End(); }

    const char* name() const { return name_; }
    void Report(double fraction, std::string message,
                std::vector<std::pair<std::string, double>> metrics = {}) const;
    // A core module's progress, forwarded under this stage's name.
    ProgressFn Forward() const;
    const CancelToken* cancel() const;
    // Cancelled (naming the stage) if the token fired; for checks inside a stage's loops.
    absl::Status CheckCancelled() const;
    // Records the seconds since the stage began (or since the last split) under `part` and starts
    // the stage's own clock again, for a part measured apart (fidelity, within "render").
    void SplitTiming(const char* part);
    // Records the stage's seconds and memory now instead of at the end of the scope; once. The
    // stage may still report progress afterwards.
    void End();

   private:
    friend class JobRun;
    StageScope(JobRun* run, const char* name, Timing timing);
    JobRun* run_;
    const char* name_;
    Timing timing_;
    std::chrono::steady_clock::time_point start_;
    bool open_;  // false once End() ran, and in a moved-from scope
  };

  // Nothing is created yet: Open() makes the folders.
  JobRun(std::filesystem::path out_dir, ProgressFn progress, const CancelToken* cancel);
  // Removes the scratch folder (also when the job failed).
  ~JobRun();
  JobRun(const JobRun&) = delete;
  JobRun& operator=(const JobRun&) = delete;

  // Creates the output folder and an empty scratch folder inside it (a previous attempt's is
  // removed). Internal error naming the folder.
  absl::Status Open();

  // Cancelled if the token fired (nothing is reported then), else the open stage.
  absl::StatusOr<StageScope> Stage(const char* name, Timing timing = Timing::kRecorded);

  // Where an artifact is written, and where a file the job needs only for a while (a picture
  // embedded in report.html) is; the scratch folder goes when the JobRun does.
  const std::filesystem::path& out_dir() const { return out_dir_; }
  std::filesystem::path OutputPath(const std::string& name) const { return out_dir_ / name; }
  std::filesystem::path ScratchPath(const std::string& name) const { return scratch_ / name; }
  // Lists out_dir/name (already written) as an artifact, with its size.
  void AddArtifact(const std::string& name);
  const std::vector<Artifact>& artifacts() const { return artifacts_; }

  // metrics.json as it grows; the stage figures are added by Finish.
  nlohmann::ordered_json& metrics() { return metrics_; }
  // Marks a stage as loaded from its checkpoint ("resumed_stages").
  void Resumed(const std::string& stage) { resumed_.push_back(stage); }
  const ProgressFn& progress() const { return progress_; }
  // The job's stages with their predicted seconds (PredictStages), once the volume's size is
  // known: from then on every progress event carries the job's overall fraction and seconds
  // left (JobClock), and metrics.json "eta" the prediction, to compare with "seconds".
  void Plan(std::vector<StagePlan> plan);

  // Closes the figures (seconds.total, peak memory, resumed stages), writes metrics.json and
  // lists it. Call after the last stage ended.
  absl::Status WriteMetrics();
  JobResult TakeResult();

 private:
  std::filesystem::path out_dir_, scratch_;
  ProgressFn progress_;
  const CancelToken* cancel_;
  std::chrono::steady_clock::time_point start_;
  PeakRss rss_;
  nlohmann::ordered_json metrics_ = nlohmann::ordered_json::object();
  nlohmann::ordered_json seconds_ = nlohmann::ordered_json::object();
  nlohmann::ordered_json resumed_ = nlohmann::ordered_json::array();
  std::vector<Artifact> artifacts_;
  std::string metrics_json_;
  double total_seconds_ = 0;
  // Stage begin and end times (seconds since the job began; end -1 while open) of the stages
  // before the plan (the clock keeps them from then on), so a plan made in "load" knows when it
  // began.
  struct StageTimes {
    std::string stage;
    double began = 0, ended = -1;
  };
  std::vector<StageTimes> stage_times_;
  std::optional<JobClock> clock_;
  nlohmann::ordered_json forecasts_ = nlohmann::ordered_json::object();

  double Now() const;
  void StageBegan(const char* stage);
  void StageEnded(const char* stage);
  bool WasResumed(const std::string& stage) const;
  // Sends `p` with the clock's estimate filled in.
  void Emit(Progress p);
};

// `text` written to `path` through a temporary name, so a reader never sees half a file.
absl::Status WriteText(const std::filesystem::path& path, const std::string& text);

}  // namespace decima::pipeline
