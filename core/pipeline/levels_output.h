// The "levels" output of a job: its simplification's collapse record as `mesh.levels`
// (core/simplify/levels_io.h), from which the mesh at any recorded reduction is extracted later
// without another job. Kept apart from RunJob, which only calls these two functions.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/pipeline/pipeline.h"
#include "core/simplify/simplify.h"

namespace decima::pipeline {

inline constexpr char kLevelsFileName[] = "mesh.levels";

// SimplifyOptions::record_levels_to for the job: the spec's floor when it asks for the "levels"
// output and its policy records levels (field), else 0 (no record, the run as without levels).
double LevelFloor(const JobSpec& spec);

// What WriteLevelsOutput did, for metrics.json.
struct LevelsOutput {
  std::optional<std::string> artifact;  // the file written, if any
  std::string note;                     // why none was written, or what was
  int64_t bytes = 0;
  int64_t collapses = 0;
  double deepest_reduction = 0;
  bool exhausted = false;
  double seconds = 0;  // writing (and, after a resume, recording again)
};

// Writes out_dir/mesh.levels from simplified->levels when LevelFloor(spec) > 0. A simplification
// resumed from a checkpoint has no record (checkpoints hold the mesh only): it is run again with
// `options` on `original` for it, which gives the same mesh (the run is deterministic). Errors:
// the file cannot be written, Cancelled.
absl::StatusOr<LevelsOutput> WriteLevelsOutput(const JobSpec& spec, const SimplifyOptions& options,
                                               const TetMesh& original, SimplifyResult* simplified,
                                               const std::filesystem::path& out_dir,
                                               const CancelToken* cancel);

}  // namespace decima::pipeline
