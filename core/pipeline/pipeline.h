// One job end to end: load -> segment -> tetrahedralize -> classify -> simplify -> write mesh ->
// render original and simplified -> diff -> metrics. This is the only entry point the server's
// job runner calls; it knows nothing about gRPC or the job store.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"

namespace decima::pipeline {

struct JobSpec {
  // A volume file (.nii, .nii.gz, .mha, .mhd, .nrrd, .nhdr) or a directory of DICOM files.
  std::filesystem::path input;
  std::string series_instance_uid;  // DICOM: pick this series when the folder holds several
  // Segmentation: K regions (2..8) by the multiphase level set, or a label map on the same grid.
  int regions = 3;
  std::vector<double> class_means;                 // empty: estimated by k-means
  std::optional<std::filesystem::path> label_map;  // replaces the level set when set
  // Simplification.
  double target_reduction = 0.5;          // fraction of cells to remove, 0..0.95
  std::string policy = "paper";           // "paper" or "tetfusion"
  double error_tolerance = 0;             // 0 = no tolerance, stop on target only
  std::map<std::string, double> weights;  // overrides of w_r, w_g, w_s, w_v, w_n by name
  // Rendering.
  std::vector<std::string> views{"anterior"};
  int image_size = 512;
  std::string transfer_function = "auto";  // preset name, "auto" (from modality), or JSON text
  // Test-only fault injection: "crash" aborts the process in the named stage.
  std::string fault;
};

struct Artifact {
  std::string name;  // "mesh.vtu", "diff.png", ...
  std::filesystem::path path;
  uint64_t size_bytes = 0;
};

struct JobResult {
  std::vector<Artifact> artifacts;
  std::string metrics_json;  // the content of metrics.json
  double seconds = 0;
};

// Runs the job, writing every artifact into `out_dir` (created if missing). Progress stages, in
// order: "load", "segment", "tetra", "simplify", "write", "render", "diff". Returns
// InvalidArgument for bad input (the message names the file and the problem), Cancelled if
// `cancel` fired (checked at least once per iteration of every stage).
absl::StatusOr<JobResult> RunJob(const JobSpec& spec, const std::filesystem::path& out_dir,
                                 const ProgressFn& progress, const CancelToken* cancel);

}  // namespace decima::pipeline
