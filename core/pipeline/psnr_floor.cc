#include "core/pipeline/psnr_floor.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <numeric>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status.h"
#include "core/metrics/fidelity.h"
#include "core/simplify/levels.h"

namespace decima::pipeline {
namespace {

// The unsimplified mesh as a result: every original grid point is a vertex with its own sample,
// so its field is the image itself (PSNR infinite) and it meets any floor.
SimplifyResult Unsimplified(const TetMesh& original) {
  SimplifyResult r;
  r.mesh = original;
  r.vertex_map.resize(size_t(original.vertex_count()));
  std::iota(r.vertex_map.begin(), r.vertex_map.end(), 0);
  r.input_cells = r.output_cells = original.tet_count();
  return r;
}

std::string Percent(double fraction) { return absl::StrFormat("%.2f %%", 100 * fraction); }

}  // namespace

double PsnrSearchDepth(double target_reduction) {
  return target_reduction > 0 ? target_reduction : 0.99;
}

absl::StatusOr<SimplifyResult> SimplifyToPsnrFloor(const Volume& image, const TetMesh& original,
                                                   const SimplifyOptions& options, double min_psnr,
                                                   bool refine, PsnrFloorSearch* search,
                                                   const ProgressFn& progress,
                                                   const CancelToken* cancel) {
  if (options.policy != SimplifyPolicy::kField) {
    return absl::InvalidArgumentError(absl::StrCat(
        "min_psnr: only the field policy records the levels the floor is searched in, not ",
        SimplifyPolicyName(options.policy)));
  }
  if (!(std::isfinite(min_psnr) && min_psnr > 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("min_psnr: ", min_psnr, " dB, expected a finite floor > 0"));
  }
  PsnrFloorSearch local;
  PsnrFloorSearch& s = search != nullptr ? *search : local;
  s = PsnrFloorSearch();
  s.floor_db = min_psnr;

  const double target = options.target_reduction;
  const double depth = PsnrSearchDepth(target);
  SimplifyOptions deep_options = options;
  deep_options.target_reduction = depth;
  deep_options.record_levels_to = std::max(options.record_levels_to, depth);
  DECIMA_ASSIGN_OR_RETURN(SimplifyResult deep, Simplify(original, deep_options, progress, cancel));
  const auto start = std::chrono::steady_clock::now();
  // The same resampling and tolerance as the job's fidelity step, so the floor is checked on the
  // number metrics.json reports.
  const double tolerance = FidelityOptions().inside_tolerance;
  auto measure = [&](const SimplifyResult& mesh, double requested,
                     bool run) -> absl::StatusOr<PsnrProbe> {
    DECIMA_ASSIGN_OR_RETURN(const FieldError e, MeasureFieldError(image, mesh.mesh, options.threads,
                                                                  tolerance, cancel));
    PsnrProbe p{requested, mesh.achieved_reduction, mesh.output_cells, e.psnr_db, run};
    s.probes.push_back(p);
    Report(progress,
           {"simplify",
            1,
            absl::StrFormat("PSNR floor %g dB: %s %s measures %.2f dB", min_psnr,
                            run ? "a run to" : "the level at", Percent(p.reduction), p.psnr_db),
            {{"reduction", p.reduction}, {"psnr_db", p.psnr_db}}});
    return p;
  };
  auto seconds = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  };

  // The deepest level is the mesh of a run to it when the record's floor is the depth (levels.h).
  DECIMA_ASSIGN_OR_RETURN(const PsnrProbe deepest,
                          measure(deep, depth, deep_options.record_levels_to == depth));
  if (deepest.psnr_db >= min_psnr) {
    // The reduction (or the end of the collapses) stops the job before the floor does.
    s.kept = deepest;
    deep.stop_message =
        absl::StrFormat("the PSNR floor %g dB did not stop it (%s measures %.2f dB); %s", min_psnr,
                        Percent(deepest.reduction), deepest.psnr_db, deep.stop_message);
    s.seconds = seconds();
    return deep;
  }

  // Bisection of the reduction between the unsimplified mesh (lo: infinite PSNR) and the deepest
  // level (hi: below the floor). The brackets are the requested reductions: ExtractLevel's level
  // for R is the shortest prefix removing ceil(R * cells), so it only grows with R.
  double lo = 0;
  std::optional<SimplifyResult> kept;
  // Halves (lo, hi] until it is one search step wide; `make` gives the mesh at a reduction.
  auto bisect = [&](double hi, bool run, auto&& make) -> absl::Status {
    s.deeper = deepest;
    for (int step = 0; step < 32 && hi - lo > kPsnrSearchStep; ++step) {
      const double mid = 0.5 * (lo + hi);
      DECIMA_ASSIGN_OR_RETURN(SimplifyResult mesh, make(mid));
      DECIMA_ASSIGN_OR_RETURN(const PsnrProbe p, measure(mesh, mid, run));
      if (p.psnr_db >= min_psnr) {
        lo = mid;
        s.kept = p;
        kept = std::move(mesh);
      } else {
        hi = mid;
        s.deeper = p;
      }
    }
    return absl::OkStatus();
  };
  const SimplifyLevels& levels = *deep.levels;
  DECIMA_RETURN_IF_ERROR(bisect(deepest.reduction, false, [&](double r) {
    return ExtractLevel(original, levels, r, options.threads, nullptr, cancel);
  }));
  // The levels of a deep record measure lower than runs to the same reduction (the record's
  // rounds are paced by its depth, levels.h), so runs between the level kept and the deepest
  // level, which is itself a run, usually keep the floor deeper. README "PSNR floor" has figures.
  if (refine && deepest.run) {
    SimplifyOptions run_options = options;
    run_options.record_levels_to = 0;
    // hi: the deepest run (one that ran out of collapses stops there too).
    DECIMA_RETURN_IF_ERROR(bisect(deepest.reduction, true, [&](double r) {
      run_options.target_reduction = r;
      return Simplify(original, run_options, nullptr, cancel);
    }));
  }
  SimplifyResult result = kept ? std::move(*kept) : Unsimplified(original);
  if (!kept) s.kept = {0, 0, original.tet_count(), std::numeric_limits<double>::infinity(), true};
  s.floor_stopped = true;
  result.passes = deep.passes;
  result.pass_stats = std::move(deep.pass_stats);
  result.max_error = deep.max_error;
  // A level keeps the record it came from (the levels output writes it); a run has none.
  if (!refine || !s.kept.run) result.levels = std::move(deep.levels);
  result.stop_reason = StopReason::kPsnrFloor;
  const int64_t removed = result.input_cells - result.output_cells;
  result.reached_target =
      target > 0 && removed >= int64_t(std::ceil(target * double(result.input_cells)));
  auto describe = [](const PsnrProbe& p) {
    return absl::StrFormat("%s %s (%.2f dB)", p.run ? "the run to" : "the level at",
                           Percent(p.reduction), p.psnr_db);
  };
  result.stop_message = absl::StrFormat(
      "PSNR floor %g dB: kept %s; %s, the next searched, is below it; removed %d of %d cells",
      min_psnr, kept ? describe(s.kept) : std::string("the unsimplified mesh"), describe(*s.deeper),
      removed, result.input_cells);
  s.seconds = seconds();
  Report(progress, {"simplify", 1, result.stop_message, {}});
  return result;
}

}  // namespace decima::pipeline
