#include "core/pipeline/levels_output.h"

#include <algorithm>
#include <chrono>

#include "absl/strings/str_format.h"
#include "core/common/status.h"
#include "core/simplify/levels_io.h"

namespace decima::pipeline {

double LevelFloor(const JobSpec& spec) {
  return Wants(spec, "levels") && spec.policy == SimplifyPolicy::kField ? spec.record_levels_to : 0;
}

absl::StatusOr<LevelsOutput> WriteLevelsOutput(const JobSpec& spec, const SimplifyOptions& options,
                                               const TetMesh& original, SimplifyResult* simplified,
                                               const std::filesystem::path& out_dir,
                                               const CancelToken* cancel) {
  LevelsOutput out;
  if (!Wants(spec, "levels")) return out;
  if (LevelFloor(spec) == 0) {
    out.note = absl::StrFormat("no levels: the %s policy does not record them (field does)",
                               SimplifyPolicyName(spec.policy));
    return out;
  }
  const auto start = std::chrono::steady_clock::now();
  if (!simplified->levels) {
    DECIMA_ASSIGN_OR_RETURN(SimplifyResult again, Simplify(original, options, nullptr, cancel));
    simplified->levels = std::move(again.levels);
  }
  const SimplifyLevels& levels = *simplified->levels;
  DECIMA_RETURN_IF_ERROR(WriteLevels(levels, out_dir / kLevelsFileName));
  std::error_code ec;
  out.artifact = kLevelsFileName;
  out.bytes = int64_t(std::filesystem::file_size(out_dir / kLevelsFileName, ec));
  out.collapses = levels.collapses();
  out.deepest_reduction = levels.deepest_reduction();
  out.exhausted = levels.exhausted;
  out.note = absl::StrFormat("%d collapses down to %.2f%% of the cells%s", out.collapses,
                             100 * out.deepest_reduction,
                             levels.exhausted ? " (no collapse left below)" : "");
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace decima::pipeline
