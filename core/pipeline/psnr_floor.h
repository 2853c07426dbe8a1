// A job's PSNR floor (JobSpec::min_psnr): the deepest level of the field policy's collapse record
// whose field still measures >= the floor against the original grid, searched by bisection of the
// reduction. core/pipeline/README.md ("PSNR floor") says why this design and what it costs.
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"
#include "core/volume/volume.h"

namespace decima::pipeline {

// The bisection stops when the bracket (last level at or above the floor, first below it) is
// narrower than this fraction of the input cells.
inline constexpr double kPsnrSearchStep = 0.005;

// The reduction the search records and starts from: the target (the reduction is the maximum),
// or 0.99, the deepest SimplifyOptions allows, when there is none (target 0).
double PsnrSearchDepth(double target_reduction);

// One mesh measured by the search: a level of the record, or a run to its reduction.
struct PsnrProbe {
  double requested = 0;  // the reduction asked for
  double reduction = 0;  // achieved
  int64_t cells = 0;
  double psnr_db = 0;  // MeasureFieldError's, the metrics.json "fidelity.psnr_db" of that mesh
  bool run = false;    // a run to `requested` (no record); false: a level of the deep record
};

// What the search did, for metrics.json and the progress messages.
struct PsnrFloorSearch {
  double floor_db = 0;
  std::vector<PsnrProbe> probes;  // in the order measured; the first is the deepest level
  // true: the floor stopped the job before its deepest level. false: the deepest level (the
  // target, or where the run ran out of collapses) already measures >= the floor.
  bool floor_stopped = false;
  PsnrProbe kept;                   // the level returned (reduction 0: the unsimplified mesh)
  std::optional<PsnrProbe> deeper;  // with floor_stopped: the shallowest probe below the floor
  double seconds = 0;               // the search after the run: extractions and measurements
};

// Simplifies `original` (the mesh of `image`'s grid) with `options` (field policy;
// options.target_reduction is the job's target, 0 = none) and returns the deepest mesh the
// search finds with a PSNR >= `min_psnr` dB, at most the target. First a run records its
// collapses down to max(options.record_levels_to, PsnrSearchDepth(target)) and its levels are
// bisected. Then, with `refine` and a record whose floor is that depth, runs to reductions
// between the level kept and the deepest level are bisected the same way (each a Simplify
// without record): a run keeps the floor deeper than the level of a deep record at the same
// reduction. Without `refine` (a job that writes the record, whose mesh must be a level of it)
// the result is a level and keeps the record. When the floor stopped it: stop_reason
// kPsnrFloor and a stop_message with the kept and the next deeper mesh's figures;
// reached_target as Simplify defines it (the target's cells removed). Errors: Simplify's,
// ExtractLevel's, MeasureFieldError's; InvalidArgument if the policy is not field or min_psnr is
// not finite and > 0.
absl::StatusOr<SimplifyResult> SimplifyToPsnrFloor(const Volume& image, const TetMesh& original,
                                                   const SimplifyOptions& options, double min_psnr,
                                                   bool refine, PsnrFloorSearch* search,
                                                   const ProgressFn& progress = nullptr,
                                                   const CancelToken* cancel = nullptr);

}  // namespace decima::pipeline
