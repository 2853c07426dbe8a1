#include "core/simplify/simplify.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <string>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/parallel.h"
#include "core/common/status.h"
#include "core/mesh/tetrahedralize.h"
#include "core/simplify/collapse_engine.h"
#include "core/simplify/field_engine.h"
#include "core/simplify/field_refit.h"
#include "core/simplify/levels.h"
#include "core/simplify/levels_io.h"

namespace decima {
namespace {

using simplify_internal::CollapseEngine;
using simplify_internal::Outcome;

// The reason cell t of m is unusable, or "" if it is fine (indexes in range, four distinct
// vertices, positive volume).
std::string CellProblem(const TetMesh& m, int64_t t) {
  const int64_t nv = m.vertex_count();
  int32_t v[4];
  m.Cell(t, v);
  for (int k = 0; k < 4; ++k) {
    if (v[k] < 0 || v[k] >= nv) {
      return absl::StrCat("cell ", t, " has vertex index ", v[k], " outside [0, ", nv, ")");
    }
    for (int j = 0; j < k; ++j) {
      if (v[j] == v[k]) return absl::StrCat("cell ", t, " repeats vertex ", v[k]);
    }
  }
  if (const double volume = TetVolume(m, t); !(volume > 0)) {
    return absl::StrCat("cell ", t, " is not positively oriented (volume ", volume, " mm^3)");
  }
  return "";
}

absl::Status ValidateMesh(const TetMesh& m, int threads) {
  const int64_t nv = m.vertex_count(), nt = m.tet_count();
  auto bad = [](const std::string& what) {
    return absl::InvalidArgumentError("simplify: input mesh " + what);
  };
  if (nv > std::numeric_limits<int32_t>::max()) return bad("has more vertices than int32 indexes");
  if (int64_t(m.positions.size()) != 3 * nv || int64_t(m.labels.size()) != nv ||
      int64_t(m.interface_distance.size()) != nv || int64_t(m.vertex_flags.size()) != nv) {
    return bad(absl::StrCat("has inconsistent per-vertex arrays: ", m.scalars.size(), " scalars, ",
                            m.positions.size(), " position floats, ", m.labels.size(), " labels, ",
                            m.interface_distance.size(), " interface distances, ",
                            m.vertex_flags.size(), " flags"));
  }
  if (m.tets.size() % 4 != 0) return bad("tets size is not a multiple of 4");
  if (m.cells_dropped && m.grid->vertex_count() != nv) {
    return bad(absl::StrCat("has its cells dropped, and its grid ", m.grid->nx(), "x", m.grid->ny(),
                            "x", m.grid->nz(), " does not have its ", nv, " vertices"));
  }
  if (4 * nt > int64_t(std::numeric_limits<int32_t>::max())) {
    return bad(absl::StrCat("has ", nt, " cells; at most ", std::numeric_limits<int32_t>::max() / 4,
                            " are supported (4 * cells must fit int32 indexes)"));
  }
  for (float x : m.positions) {
    if (!std::isfinite(x)) return bad("has a non-finite vertex position");
  }
  for (float s : m.scalars) {
    if (!std::isfinite(s)) return bad("has a non-finite scalar");
  }
  // The cells on all threads, since a serial scan is slow on the largest meshes (figures in
  // core/simplify/README.md); the lowest bad cell is reported, as a serial scan would.
  std::atomic<int64_t> first_bad{nt};
  ParallelFor(nt, threads, 65536, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1 && t < first_bad.load(std::memory_order_relaxed); ++t) {
      if (CellProblem(m, t).empty()) continue;
      int64_t seen = first_bad.load(std::memory_order_relaxed);
      while (t < seen && !first_bad.compare_exchange_weak(seen, t)) {
      }
      return;
    }
  });
  if (first_bad < nt) return bad(CellProblem(m, first_bad));
  return absl::OkStatus();
}

// The paper's and TetFusion's greedy cell collapse, pass after pass (collapse_engine.h).
absl::Status RunCellCollapse(const TetMesh& mesh, const SimplifyOptions& options, int threads,
                             int64_t target, bool has_target, const ProgressFn& progress,
                             const CancelToken* cancel, SimplifyResult* result) {
  const bool has_tolerance = options.error_tolerance > 0;
  CollapseEngine engine(mesh, options, threads);
  bool stopped = false;
  for (int pass = 1; pass <= options.max_passes && !stopped; ++pass) {
    if (engine.removed_cells() >= target) break;
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));
    engine.BeginPass(threads);
    simplify_internal::EnginePassStats run;
    DECIMA_RETURN_IF_ERROR(
        engine.RunPass(target, has_tolerance ? options.error_tolerance : 0, cancel, &run));
    SimplifyPassStats stats;
    stats.candidates = run.candidates;
    stats.collapses = run.collapses;
    stats.cells_removed = run.cells_removed;
    stats.rejected_flip = run.rejected_flip;
    stats.rejected_rule4 = run.rejected_rule4;
    stats.requeued = run.requeued;
    stats.other_point = run.other_point;
    stats.last_error = run.last_error;
    result->max_error = std::max(result->max_error, run.max_error);
    const int64_t removed = engine.removed_cells();
    result->passes = pass;
    result->collapses += stats.collapses;
    result->pass_stats.push_back(stats);
    Report(progress, {"simplify",
                      has_target ? std::min(1.0, double(removed) / double(target)) : 0.0,
                      absl::StrFormat("pass %d: %d collapses removed %d cells (%.1f%% so far)",
                                      pass, stats.collapses, stats.cells_removed,
                                      100.0 * double(removed) /
                                          double(std::max<int64_t>(1, result->input_cells))),
                      {{"pass", double(pass)},
                       {"cells_removed", double(removed)},
                       {"error", stats.last_error}}});
    if (stats.collapses == 0) {
      stopped = true;
      result->stop_reason =
          run.tolerance_hit ? StopReason::kErrorTolerance : StopReason::kNoValidCollapse;
    } else if (run.tolerance_hit) {
      stopped = true;
      result->stop_reason = StopReason::kErrorTolerance;
    } else if (removed < target &&
               double(stats.cells_removed) < options.min_pass_gain * double(result->input_cells)) {
      stopped = true;
      result->stop_reason = StopReason::kStalled;
    }
  }
  if (engine.removed_cells() >= target) {
    result->stop_reason = StopReason::kTargetReached;
  } else if (!stopped) {
    result->stop_reason = StopReason::kMaxPasses;
  }

  engine.Finish(&result->mesh, &result->vertex_map);
  return absl::OkStatus();
}

}  // namespace

absl::Status ValidateSimplifyOptions(const SimplifyOptions& o) {
  auto bad = [](const std::string& what) {
    return absl::InvalidArgumentError("simplify: option " + what);
  };
  if (!ParseSimplifyPolicy(SimplifyPolicyName(o.policy))) {
    return bad(absl::StrCat("policy = ", static_cast<int>(o.policy), ": not a policy"));
  }
  if (!ParseInterfaceMode(InterfaceModeName(o.interfaces))) {
    return bad(absl::StrCat("interfaces = ", static_cast<int>(o.interfaces),
                            ": not an interface mode (free, voxel-faces)"));
  }
  if (!(o.target_reduction >= 0 && o.target_reduction <= 0.99)) {
    return bad(absl::StrCat("target_reduction = ", o.target_reduction,
                            ": expected a fraction of cells to remove in [0, 0.99]"));
  }
  if (!(o.error_tolerance >= 0 && std::isfinite(o.error_tolerance))) {
    return bad(absl::StrCat("error_tolerance = ", o.error_tolerance,
                            ": expected a finite value >= 0 (0 for none)"));
  }
  const std::pair<const char*, double> weights[] = {{"weights.regional", o.weights.regional},
                                                    {"weights.gradient", o.weights.gradient},
                                                    {"weights.shape", o.weights.shape},
                                                    {"weights.volume", o.weights.volume},
                                                    {"weights.neighbour", o.weights.neighbour}};
  for (const auto& [name, w] : weights) {
    if (!(w >= 0 && std::isfinite(w))) {
      return bad(absl::StrCat(name, " = ", w, ": expected a finite weight >= 0"));
    }
  }
  if (o.feature_threshold_voxels &&
      !(*o.feature_threshold_voxels >= 0 && std::isfinite(*o.feature_threshold_voxels))) {
    return bad(absl::StrCat("feature_threshold_voxels = ", *o.feature_threshold_voxels,
                            ": expected a finite distance >= 0 voxels (unset: the mesh's flags)"));
  }
  if (!(o.voxel_size_mm >= 0 && std::isfinite(o.voxel_size_mm))) {
    return bad(absl::StrCat("voxel_size_mm = ", o.voxel_size_mm, ": expected >= 0 mm"));
  }
  if (!(o.min_volume_fraction > 0 && o.min_volume_fraction < 1)) {
    return bad(absl::StrCat("min_volume_fraction = ", o.min_volume_fraction,
                            ": expected a value in (0, 1) voxels^3"));
  }
  if (!(o.min_dihedral_degrees >= 0 && o.min_dihedral_degrees <= 30)) {
    return bad(absl::StrCat("min_dihedral_degrees = ", o.min_dihedral_degrees,
                            ": expected [0, 30] degrees"));
  }
  if (!(o.min_pass_gain >= 0 && o.min_pass_gain <= 0.5)) {
    return bad(absl::StrCat("min_pass_gain = ", o.min_pass_gain, ": expected [0, 0.5]"));
  }
  if (o.max_passes < 1 || o.max_passes > 10000) {
    return bad(absl::StrCat("max_passes = ", o.max_passes, ": expected 1..10000"));
  }
  if (o.refit_iterations < 0 || o.refit_iterations > 1000) {
    return bad(absl::StrCat("refit_iterations = ", o.refit_iterations, ": expected 0..1000"));
  }
  if (!(o.record_levels_to >= 0 && o.record_levels_to <= 0.99)) {
    return bad(absl::StrCat("record_levels_to = ", o.record_levels_to,
                            ": expected a fraction of cells in [0, 0.99] (0: no levels)"));
  }
  if (o.record_levels_to > 0 && o.policy != SimplifyPolicy::kField) {
    return bad(absl::StrCat("record_levels_to = ", o.record_levels_to,
                            ": only the field policy records levels, not ",
                            SimplifyPolicyName(o.policy)));
  }
  if (o.threads < 0 || o.threads > 1024) {
    return bad(absl::StrCat("threads = ", o.threads, ": expected 0..1024"));
  }
  return absl::OkStatus();
}

const char* StopReasonName(StopReason reason) {
  switch (reason) {
    case StopReason::kTargetReached:
      return "target_reached";
    case StopReason::kErrorTolerance:
      return "error_tolerance";
    case StopReason::kNoValidCollapse:
      return "no_valid_collapse";
    case StopReason::kMaxPasses:
      return "max_passes";
    case StopReason::kStalled:
      return "stalled";
    case StopReason::kPsnrFloor:
      return "min_psnr";
  }
  return "?";
}

const char* SimplifyPolicyName(SimplifyPolicy policy) {
  switch (policy) {
    case SimplifyPolicy::kPaper:
      return "paper";
    case SimplifyPolicy::kTetFusion:
      return "tetfusion";
    case SimplifyPolicy::kField:
      return "field";
  }
  return "?";
}

const char* InterfaceModeName(InterfaceMode mode) {
  switch (mode) {
    case InterfaceMode::kFree:
      return "free";
    case InterfaceMode::kVoxelFaces:
      return "voxel-faces";
  }
  return "unknown";
}

std::optional<InterfaceMode> ParseInterfaceMode(std::string_view name) {
  for (InterfaceMode m : {InterfaceMode::kFree, InterfaceMode::kVoxelFaces}) {
    if (name == InterfaceModeName(m)) return m;
  }
  return std::nullopt;
}

namespace {
constexpr SimplifyPolicy kAllPolicies[] = {SimplifyPolicy::kField, SimplifyPolicy::kPaper,
                                           SimplifyPolicy::kTetFusion};
}  // namespace

std::optional<SimplifyPolicy> ParseSimplifyPolicy(std::string_view name) {
  for (SimplifyPolicy p : kAllPolicies) {
    if (name == SimplifyPolicyName(p)) return p;
  }
  return std::nullopt;
}

std::string SimplifyPolicyNames() {
  std::string out;
  for (SimplifyPolicy p : kAllPolicies)
    absl::StrAppend(&out, out.empty() ? "" : ", ", SimplifyPolicyName(p));
  return out;
}

bool RunsWithoutCells(const SimplifyOptions& options) {
  return options.policy == SimplifyPolicy::kField && options.record_levels_to == 0;
}

absl::StatusOr<SimplifyResult> Simplify(const TetMesh& mesh, const SimplifyOptions& options,
                                        const ProgressFn& progress, const CancelToken* cancel) {
  DECIMA_RETURN_IF_ERROR(ValidateSimplifyOptions(options));
  const int threads = ResolveThreads(options.threads);
  DECIMA_RETURN_IF_ERROR(ValidateMesh(mesh, threads));
  if (mesh.cells_dropped && !RunsWithoutCells(options)) {
    return absl::InvalidArgumentError(
        absl::StrCat("simplify: the input mesh's cells are dropped (DropGridCells); the ",
                     SimplifyPolicyName(options.policy), " policy",
                     options.record_levels_to > 0 ? " with record_levels_to" : "",
                     " needs them restored (RestoreGridCells)"));
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));

  SimplifyResult result;
  result.input_cells = mesh.tet_count();
  const bool has_target = options.target_reduction > 0;
  const int64_t target =
      has_target ? int64_t(std::ceil(options.target_reduction * double(result.input_cells)))
                 : std::numeric_limits<int64_t>::max();
  const bool has_tolerance = options.error_tolerance > 0;

  if (options.policy == SimplifyPolicy::kField && options.record_levels_to > 0) {
    // The run goes to the floor (or deeper, to the target), and the mesh at the target is a level
    // of the record: the same as any other run with this floor gives for it (levels.h).
    const int64_t floor = int64_t(std::ceil(options.record_levels_to * double(result.input_cells)));
    SimplifyLevels levels;
    levels.refit_iterations = options.refit_iterations;
    levels.base_digest = BaseMeshDigest(mesh);
    SimplifyResult deep;
    DECIMA_RETURN_IF_ERROR(simplify_internal::RunFieldSimplify(
        mesh, options, threads, std::max(target, floor),
        has_tolerance ? options.error_tolerance : 0, progress, cancel, &deep, &levels));
    deep.mesh = TetMesh();  // the level below is built from `mesh` and the record
    DECIMA_ASSIGN_OR_RETURN(
        result, ExtractLevel(mesh, levels, options.target_reduction, threads, progress, cancel));
    result.passes = deep.passes;
    result.pass_stats = std::move(deep.pass_stats);
    result.max_error = deep.max_error;
    if (!result.reached_target && has_target) result.stop_reason = deep.stop_reason;
    result.levels = std::move(levels);
  } else if (options.policy == SimplifyPolicy::kField) {
    DECIMA_RETURN_IF_ERROR(simplify_internal::RunFieldSimplify(
        mesh, options, threads, target, has_tolerance ? options.error_tolerance : 0, progress,
        cancel, &result));
    DECIMA_RETURN_IF_ERROR(simplify_internal::RefitAndReport(mesh, result.vertex_map, &result.mesh,
                                                             options.refit_iterations, threads,
                                                             cancel, progress));
  } else {
    DECIMA_RETURN_IF_ERROR(
        RunCellCollapse(mesh, options, threads, target, has_target, progress, cancel, &result));
  }
  const int64_t removed = result.input_cells - result.mesh.tet_count();
  result.output_cells = result.mesh.tet_count();
  result.achieved_reduction =
      result.input_cells > 0 ? 1.0 - double(result.output_cells) / double(result.input_cells) : 0;
  result.reached_target = has_target && removed >= target;
  const std::string achieved =
      absl::StrFormat("removed %d of %d cells (%.2f%%) in %d passes", removed, result.input_cells,
                      100 * result.achieved_reduction, result.passes);
  switch (result.stop_reason) {
    case StopReason::kTargetReached:
      result.stop_message = absl::StrCat("target reached: ", achieved);
      break;
    case StopReason::kErrorTolerance:
      result.stop_message = absl::StrCat(
          has_target ? "target not reached: " : "", "every remaining collapse ",
          "predicts an error above the tolerance ", options.error_tolerance, "; ", achieved);
      break;
    case StopReason::kNoValidCollapse:
      result.stop_message = absl::StrCat(has_target ? "target not reached: " : "",
                                         "no collapse left that rules 1-6 allow; ", achieved);
      break;
    case StopReason::kStalled:
      result.stop_message = absl::StrCat("target not reached: pass ", result.passes,
                                         " removed only ", result.pass_stats.back().cells_removed,
                                         " cells (min_pass_gain = ", options.min_pass_gain,
                                         " of the input); the mesh is jammed; ", achieved);
      break;
    case StopReason::kMaxPasses:
      result.stop_message = absl::StrCat("target not reached: max_passes = ", options.max_passes,
                                         " ran out; ", achieved);
      break;
    case StopReason::kPsnrFloor:
      break;  // never set by Simplify (see the enum); the search that sets it writes the message
  }
  return result;
}

absl::StatusOr<SimplifyResult> SimplifyDroppingCells(TetMesh* mesh, const SimplifyOptions& options,
                                                     const ProgressFn& progress,
                                                     const CancelToken* cancel,
                                                     bool restore_cells) {
  const bool drop = mesh->grid && RunsWithoutCells(options) && !mesh->cells_dropped;
  if (drop) DropGridCells(mesh);
  absl::StatusOr<SimplifyResult> result = Simplify(*mesh, options, progress, cancel);
  if (drop && restore_cells) RestoreGridCells(mesh, options.threads);
  return result;
}

}  // namespace decima
