#include "core/pipeline/job_run.h"

#include <sys/resource.h>

#ifdef __GLIBC__
#include <malloc.h>
#endif

#include <algorithm>
#include <cstdlib>
#include <fstream>
#include <utility>

#include "absl/strings/str_cat.h"
#include "core/common/status.h"

namespace decima::pipeline {
namespace {

using Json = nlohmann::ordered_json;
using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// A dot keeps it apart from the artifacts' names, which never start with one.
constexpr char kScratchFolder[] = ".scratch";

bool ResetHighWaterMark() {
  std::ofstream out("/proc/self/clear_refs");
  out << "5";
  out.flush();
  return out.good();
}

double ProcessPeakMb() {
  rusage ru{};
  if (getrusage(RUSAGE_SELF, &ru) != 0) return 0;
  return static_cast<double>(ru.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB on Linux
}

double HighWaterMb() {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::atof(line.c_str() + 6) / 1024.0;
  }
  return ProcessPeakMb();
}

// Gives the heap's free pages back to the system. glibc keeps freed chunks below its mmap
// threshold (which rises to 32 MiB as large blocks are freed) in its arenas, resident: on the CT
// head 256x256x113 about 370 MiB of the simplify stage's work arrays stayed resident under the
// write and render stages, more than those stages hold (issue 30). Called between stages, after
// the stage's peak is read; the next stage reuses the pages it needs.
void ReleaseFreeHeap() {
#ifdef __GLIBC__
  malloc_trim(0);
#endif
}

}  // namespace

PeakRss::PeakRss() { resettable_ = ResetHighWaterMark(); }

void PeakRss::EndStage(const std::string& stage) {
  const double mb = HighWaterMb();
  if (mb > 0) stages_[stage] = std::max(stages_.value(stage, 0.0), mb);
  ReleaseFreeHeap();
  if (resettable_) resettable_ = ResetHighWaterMark();
}

double PeakRss::PeakMb() const {
  double peak = ProcessPeakMb();
  for (const auto& [stage, mb] : stages_.items()) peak = std::max(peak, mb.get<double>());
  return peak;
}

JobRun::StageScope::StageScope(JobRun* run, const char* name, Timing timing)
    : run_(run), name_(name), timing_(timing), start_(Clock::now()), open_(true) {
  run_->StageBegan(name_);
}

JobRun::StageScope::StageScope(StageScope&& other) noexcept
    : run_(other.run_),
      name_(other.name_),
      timing_(other.timing_),
      start_(other.start_),
      open_(std::exchange(other.open_, false)) {}

void JobRun::StageScope::Report(double fraction, std::string message,
                                std::vector<std::pair<std::string, double>> metrics) const {
  Progress p;
  p.stage = name_;
  p.fraction = fraction;
  p.message = std::move(message);
  p.metrics = std::move(metrics);
  run_->Emit(std::move(p));
}

ProgressFn JobRun::StageScope::Forward() const {
  if (!run_->progress_) return nullptr;
  return [run = run_, stage = name_](const Progress& p) {
    Progress q = p;
    q.stage = stage;
    run->Emit(std::move(q));
  };
}

const CancelToken* JobRun::StageScope::cancel() const { return run_->cancel_; }

absl::Status JobRun::StageScope::CheckCancelled() const {
  return decima::CheckCancelled(run_->cancel_, name_);
}

void JobRun::StageScope::SplitTiming(const char* part) {
  run_->seconds_[part] = Seconds(start_);
  start_ = Clock::now();
}

void JobRun::StageScope::End() {
  if (!open_) return;
  open_ = false;
  if (timing_ == Timing::kRecorded) run_->seconds_[name_] = Seconds(start_);
  run_->rss_.EndStage(name_);
  run_->StageEnded(name_);
}

JobRun::JobRun(std::filesystem::path out_dir, ProgressFn progress, const CancelToken* cancel)
    : out_dir_(std::move(out_dir)),
      progress_(std::move(progress)),
      cancel_(cancel),
      start_(Clock::now()) {}

JobRun::~JobRun() {
  if (scratch_.empty()) return;
  std::error_code ec;
  std::filesystem::remove_all(scratch_, ec);
}

absl::Status JobRun::Open() {
  std::error_code ec;
  std::filesystem::create_directories(out_dir_, ec);
  if (ec) return absl::InternalError(absl::StrCat(out_dir_.string(), ": ", ec.message()));
  const std::filesystem::path scratch = out_dir_ / kScratchFolder;
  std::filesystem::remove_all(scratch, ec);
  if (!ec) std::filesystem::create_directory(scratch, ec);
  if (ec) return absl::InternalError(absl::StrCat(scratch.string(), ": ", ec.message()));
  scratch_ = scratch;
  return absl::OkStatus();
}

absl::StatusOr<JobRun::StageScope> JobRun::Stage(const char* name, Timing timing) {
  DECIMA_RETURN_IF_ERROR(decima::CheckCancelled(cancel_, name));
  return StageScope(this, name, timing);
}

void JobRun::AddArtifact(const std::string& name) {
  const std::filesystem::path path = OutputPath(name);
  std::error_code ec;
  artifacts_.push_back({name, path, std::filesystem::file_size(path, ec)});
}

double JobRun::Now() const { return Seconds(start_); }

void JobRun::StageBegan(const char* stage) {
  const double now = Now();
  if (!clock_) {
    stage_times_.push_back({stage, now, -1});
    return;
  }
  clock_->Begin(stage, now);
  // What the clock forecast for the whole job as each stage began: metrics.json "eta", to
  // compare with seconds.total.
  const JobClock::Estimate e = clock_->At(stage, 0, now);
  forecasts_[stage] = now + e.eta_seconds;
}

void JobRun::StageEnded(const char* stage) {
  const double now = Now();
  if (clock_) {
    clock_->End(stage, now, WasResumed(stage));
    return;
  }
  for (auto& t : stage_times_) {
    if (t.stage == stage && t.ended < 0) t.ended = now;
  }
}

bool JobRun::WasResumed(const std::string& stage) const {
  return std::find(resumed_.begin(), resumed_.end(), stage) != resumed_.end();
}

void JobRun::Plan(std::vector<StagePlan> plan) {
  clock_.emplace(std::move(plan));
  for (const auto& t : stage_times_) {
    clock_->Begin(t.stage, t.began);
    if (t.ended >= 0) clock_->End(t.stage, t.ended, WasResumed(t.stage));
  }
  stage_times_.clear();
}

void JobRun::Emit(Progress p) {
  if (!progress_) return;
  if (clock_) {
    const JobClock::Estimate e = clock_->At(p.stage, p.fraction, Now());
    p.overall = e.overall;
    p.eta_seconds = e.eta_seconds;
  }
  progress_(p);
}

absl::Status JobRun::WriteMetrics() {
  total_seconds_ = Seconds(start_);
  seconds_["total"] = total_seconds_;
  metrics_["seconds"] = seconds_;
  if (clock_) {
    Json predicted = Json::object();
    for (const auto& s : clock_->plan()) predicted[s.stage] = s.seconds;
    metrics_["eta"] = {{"predicted_seconds", predicted},
                       {"forecast_total_seconds_at_stage_start", forecasts_}};
  }
  metrics_["peak_rss_mb"] = rss_.PeakMb();
  metrics_["stage_peak_rss_mb"] = rss_.stages();
  metrics_["stage_peak_rss_per_stage"] = rss_.resettable();
  metrics_["resumed_stages"] = resumed_;
  metrics_json_ = metrics_.dump(2);
  DECIMA_RETURN_IF_ERROR(WriteText(OutputPath("metrics.json"), metrics_json_));
  AddArtifact("metrics.json");
  return absl::OkStatus();
}

JobResult JobRun::TakeResult() {
  JobResult result;
  result.artifacts = std::move(artifacts_);
  result.metrics_json = std::move(metrics_json_);
  result.seconds = total_seconds_;
  return result;
}

absl::Status WriteText(const std::filesystem::path& path, const std::string& text) {
  const std::filesystem::path tmp = path.string() + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out << text;
    if (!out.good()) return absl::InternalError(absl::StrCat(path.string(), ": write failed"));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) return absl::InternalError(absl::StrCat(path.string(), ": ", ec.message()));
  return absl::OkStatus();
}

}  // namespace decima::pipeline
