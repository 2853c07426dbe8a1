#include "core/pipeline/eta.h"

#include <algorithm>
#include <cmath>
#include <utility>

#include "core/pipeline/levels_output.h"

namespace decima::pipeline {
namespace {

// Seconds per unit of work on the reference machine, each stage's own unit (README "ETA" has
// the jobs they were measured on). The clock rescales them by the job's measured rates, so what
// matters most here is their ratio to each other.
constexpr double kLoadPerVoxel = 2e-8;
constexpr double kLabelMapPerVoxel = 5e-8;  // a given label map instead of the level set
constexpr double kSegmentSetupPerVoxel = 7e-7;
constexpr double kSegmentIterationPerVoxel = 7.7e-8;
// The level set's iteration count is only known as it converges (it forecasts it itself, and
// the segment stage's fraction follows that forecast): 9 on the CT heads, ~25 on the MRIs.
constexpr double kSegmentIterations = 15;
constexpr double kTetraPerVoxel = 4e-7;
// Per input cell, times (reduction + kSimplifyBase): a run's time grows with how far it goes,
// and its set-up and refit cost something at any reduction.
constexpr double kSimplifyPerCell = 2.2e-6;
constexpr double kSimplifyBase = 0.1;
constexpr double kLevelExtractPerCell = 1.5e-7;  // a level job: one pass over the base cells
// A PSNR floor bisects the levels of a record to 0.99 and then runs to the chosen level.
constexpr double kPsnrFloorFactor = 2.5;
// Streamed (JobSpec::stream_slab_voxels): one or two measuring passes over the slabs find the
// cost threshold before the final pass (CT head 256 at 80 %, slabs of 16: 303 s against 207 s
// with one pass; core/simplify/README.md "Streamed simplification").
constexpr double kStreamedFactor = 1.75;
constexpr double kWritePerOutputCell = 2.4e-7;
constexpr double kWriteLabelsPerVoxel = 1.2e-7;
constexpr double kWriteMshPerOutputCell = 1.5e-6;
constexpr double kWriteSurfacePerOutputCell = 1.5e-7;  // stl, glb
constexpr double kFidelityPerVoxel = 1e-6;
constexpr double kRenderMeshPerCell = 4.4e-7;  // original and simplified mesh, per view
constexpr double kRenderPerPixel = 2.3e-6;     // per view, both meshes and the difference
// The curve stage simplifies and renders once per 10 % step below the job's reduction.
constexpr double kCurvePerStep = 0.6;   // x the job's own simplify time at that step
constexpr double kDiffPerVoxel = 2e-8;  // segmentation picture, report

}  // namespace

std::vector<StagePlan> PredictStages(const JobSpec& spec, const std::array<int64_t, 3>& dims) {
  const double voxels = double(dims[0]) * double(dims[1]) * double(dims[2]);
  const double cells = 5.0 * double(std::max<int64_t>(dims[0] - 1, 1)) *
                       double(std::max<int64_t>(dims[1] - 1, 1)) *
                       double(std::max<int64_t>(dims[2] - 1, 1));
  // How far the simplification runs: to the target, or to the record's floor when deeper (0.99
  // for a PSNR floor, which bisects the levels of a record to 0.99).
  const double depth =
      spec.min_psnr
          ? 0.99
          : std::max(spec.target_reduction > 0 ? spec.target_reduction : 0.99, LevelFloor(spec));
  const double kept = spec.min_psnr ? 0.2 : 1 - std::min(depth, 0.99);
  const double out_cells = cells * kept;
  const double views = double(std::max<size_t>(spec.views.size(), 1));
  const double pixels = double(spec.image_size) * double(spec.image_size);

  std::vector<StagePlan> plan;
  plan.push_back({"load", kLoadPerVoxel * voxels});
  plan.push_back(
      {"segment",
       spec.label_map || spec.levels_file
           ? kLabelMapPerVoxel * voxels
           : (kSegmentSetupPerVoxel + kSegmentIterationPerVoxel * kSegmentIterations) * voxels});
  plan.push_back({"tetra", kTetraPerVoxel * voxels});
  double simplify = spec.levels_file ? kLevelExtractPerCell * cells
                                     : kSimplifyPerCell * cells * (depth + kSimplifyBase);
  if (spec.min_psnr) simplify *= kPsnrFloorFactor;
  if (spec.stream_slab_voxels > 0) simplify *= kStreamedFactor;
  plan.push_back({"simplify", simplify});
  double write = 0;
  if (Wants(spec, "vtu") || Wants(spec, "medit")) write += kWritePerOutputCell * out_cells;
  if (Wants(spec, "msh")) write += kWriteMshPerOutputCell * out_cells;
  if (Wants(spec, "stl") || Wants(spec, "glb")) write += kWriteSurfacePerOutputCell * out_cells;
  if (Wants(spec, "labels")) write += kWriteLabelsPerVoxel * voxels;
  plan.push_back({"write", write});
  plan.push_back(
      {"render", kFidelityPerVoxel * voxels + views * (kRenderMeshPerCell * (cells + out_cells) +
                                                       kRenderPerPixel * pixels)});
  if (Wants(spec, "curve")) {
    const int steps = std::max(1, int(std::floor(depth * 10 + 1e-9)));
    double curve = 0;
    for (int s = 1; s <= steps; ++s) {
      curve += kCurvePerStep * kSimplifyPerCell * cells * (0.1 * s + kSimplifyBase) +
               kRenderMeshPerCell * cells * (1 - 0.1 * s) + kRenderPerPixel * pixels;
    }
    plan.push_back({"curve", curve});
  }
  plan.push_back({"diff", kDiffPerVoxel * voxels});
  return plan;
}

JobClock::JobClock(std::vector<StagePlan> plan) : plan_(std::move(plan)) {
  entries_.resize(plan_.size());
  for (size_t i = 0; i < plan_.size(); ++i) entries_[i].predicted = std::max(plan_[i].seconds, 0.0);
}

int JobClock::Find(const std::string& stage) const {
  for (size_t i = 0; i < plan_.size(); ++i) {
    if (plan_[i].stage == stage) return int(i);
  }
  return -1;
}

void JobClock::Begin(const std::string& stage, double now) {
  const int i = Find(stage);
  if (i >= 0 && entries_[i].began < 0) entries_[i].began = now;
}

void JobClock::End(const std::string& stage, double now, bool resumed) {
  const int i = Find(stage);
  if (i < 0) return;
  Entry& e = entries_[i];
  if (e.began < 0) e.began = now;
  e.ended = now;
  e.resumed = e.resumed || resumed;
}

JobClock::Estimate JobClock::At(const std::string& stage, double fraction, double now) {
  const int open = Find(stage);
  const double f = std::clamp(std::isfinite(fraction) ? fraction : 0.0, 0.0, 1.0);
  // The machine's speed against the model: measured over predicted seconds of the stages that
  // ended (not the resumed ones), shrunk toward the model by a prior worth a little of the job so
  // that one quick stage cannot swing it. The open stage is left out: its own rate covers its
  // own rest below, and a stage slower than its model on this scan (simplify on a noisy MRI)
  // says little about the stages after it.
  double measured = 0, expected = 0, total = 0;
  for (const Entry& e : entries_) {
    total += e.resumed ? 0 : e.predicted;
    if (e.resumed || e.began < 0 || e.ended < 0) continue;
    measured += e.ended - e.began;
    expected += e.predicted;
  }
  const double prior = std::min(2.0, 0.05 * total);
  const double speed = prior > 0 ? (measured + prior) / (expected + prior) : 1.0;

  double left = 0;
  for (size_t i = 0; i < entries_.size(); ++i) {
    const Entry& e = entries_[i];
    if (e.resumed || e.ended >= 0) continue;
    if (int(i) == open && e.began >= 0) {
      // The open stage's own rate, trusted as much as it is advanced, against the model's.
      const double ran = std::max(0.0, now - e.began);
      const double by_model = e.predicted * (1 - f) * speed;
      const double by_rate = f > 0 ? ran * (1 - f) / f : by_model;
      left += f * by_rate + (1 - f) * by_model;
    } else if (open < 0 || int(i) > open) {
      left += e.predicted * speed;
    }
  }
  Estimate est;
  est.eta_seconds = std::max(0.0, left);
  const double elapsed = std::max(0.0, now);
  const double overall = elapsed + left > 0 ? elapsed / (elapsed + left) : 1.0;
  // Never backwards: a stage slower than forecast holds the bar instead of pulling it back.
  last_overall_ = std::max(last_overall_, std::clamp(overall, 0.0, 1.0));
  est.overall = last_overall_;
  return est;
}

}  // namespace decima::pipeline
