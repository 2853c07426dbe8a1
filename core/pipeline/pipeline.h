// One job end to end: load -> segment -> tetrahedralize -> classify -> simplify -> write mesh ->
// render original and simplified -> diff -> metrics. This is the only entry point the server's
// job runner calls; it knows nothing about gRPC or the job store.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/mesh_io.h"
#include "core/simplify/simplify.h"
#include "core/volume/regions.h"

namespace decima::pipeline {

// One job's parameters. The member initializers are THE defaults of the service (the server's
// JobSpecFromProto starts from them); ValidateJobSpec holds the ranges, taken from the validators
// of the core modules.
struct JobSpec {
  // A volume file (.nii, .nii.gz, .hdr/.img, .mha, .mhd, .nrrd, .nhdr) or a DICOM folder.
  std::filesystem::path input;
  std::string series_instance_uid;  // DICOM: pick this series when the folder holds several
  // Segmentation: K regions (2..8) by the multiphase level set, or a label map on the same grid.
  int regions = 3;
  std::vector<double> class_means;                 // empty: estimated by k-means
  std::optional<std::filesystem::path> label_map;  // replaces the level set when set
  // One name per region (label order), or empty: named from intensity (core/volume/regions.h).
  std::vector<std::string> region_names;
  // Simplification (SimplifyOptions of the same names; ranges from ValidateSimplifyOptions).
  double target_reduction = 0.5;  // fraction of cells to remove, [0, 0.99]; 0 = no target
  SimplifyPolicy policy = SimplifyPolicy::kField;
  double error_tolerance = 0;  // >= 0; 0 = no tolerance, stop on the target only
  // Field policy: interfaces free under the label guard (default) or kept as the voxel staircase
  // (core/simplify/README.md, "Interfaces free inside their voxels").
  InterfaceMode interfaces = InterfaceMode::kFree;
  ErrorWeights weights;
  // With the "levels" output and the field policy: the collapses are recorded down to this
  // reduction (SimplifyOptions::record_levels_to, (0, 0.99]) and written as mesh.levels, so the
  // mesh at any reduction down to it can be had later without another job. The run then goes to
  // this floor (or to target_reduction if deeper), and the job's mesh is the level of the record.
  double record_levels_to = 0.9;
  // A level record (mesh.levels of an earlier job on the same volume and segmentation): the
  // simplify stage extracts its level at target_reduction (ExtractLevel) instead of simplifying.
  // The record's digest refuses a base mesh other than the one it was made on. Field policy
  // only, and no "levels" output of its own.
  std::optional<std::filesystem::path> levels_file;
  // A PSNR floor in dB (field policy only; finite, > 0): the job keeps the deepest level of its
  // collapse record whose field measures >= this against the original grid (the metrics.json
  // "fidelity.psnr_db"), found by bisection (psnr_floor.h). target_reduction stays the maximum:
  // whichever stops first wins. Unset: no floor.
  std::optional<double> min_psnr;
  // Streamed simplification (issue 30; core/simplify/stream.h): > 0 simplifies the grid mesh in
  // slabs of this many voxel layers along z, so the engine holds one window's state instead of
  // the whole volume's. 0 (the default) simplifies in memory. Field policy only, without a PSNR
  // floor, a level record or the "levels" output; >= kMinStreamSlabVoxels.
  int stream_slab_voxels = 0;
  // Rendering.
  std::vector<std::string> views{"anterior"};  // 1..16 names ParseView accepts
  int image_size = 512;                        // pixels, 16..4096
  std::string transfer_function = "auto";      // preset name, "auto" (from modality), or JSON text
  // Where the render stage takes the original from: the voxel grid (RenderableGrid, nothing held
  // per tet; issue 30) or the materialized 5-tet mesh (the earlier path, kept so decima-bench
  // --original-from can compare the two). The pictures and metrics are the same either way.
  enum class OriginalSource { kGrid, kMesh };
  OriginalSource original_from = OriginalSource::kGrid;
  // Artifacts (kOutputKinds), in that order; metrics.json is always written.
  // "levels" is not a default: it takes the run down to record_levels_to (core/pipeline/README.md).
  std::vector<std::string> outputs{"vtu", "labels", "images", "segmentation", "report"};
  int vtu_compression_level = 1;  // 0 = uncompressed, 1..9 the level of mesh_compression
  // mesh.vtu's compressor: zlib, or VTK's LZMA (~44 % fewer bytes, writes 5-20x slower, VTK
  // reads it ~2x slower; core/mesh/README.md "Compact meshes"). With LZMA the level is xz's preset.
  VtuCompressor mesh_compression = VtuCompressor::kZlib;
  // Captions only (picture footers, report.html); empty: the input's file name / nothing.
  std::string job_name;
  std::string input_name;
};

// Every artifact kind a JobSpec may ask for, in the order RunJob writes them.
// "curve" (curve.png, the paper's Fig. 5 for this job) costs one more simplification and render
// per 10 % step below the job's reduction, so it is never a default.
// "stl" writes surface-<name>.stl per region (SurfaceFileNames) and "glb" one surfaces.glb with
// every region named and coloured as the region table says: the closed surfaces of the simplified
// mesh's cells of each region (core/mesh/region_surface.h), so they agree with the tets. "levels"
// writes mesh.levels, the collapse record (core/pipeline/levels_output.h).
inline constexpr const char* kOutputKinds[] = {"vtu",          "msh",    "medit",  "stl",
                                               "glb",          "levels", "labels", "images",
                                               "segmentation", "report", "curve"};

// Whether `spec` asks for the output `kind` (one of kOutputKinds).
bool Wants(const JobSpec& spec, const char* kind);

// OK, or InvalidArgument for the first parameter out of range; `*field` (when given) receives
// its JobSpec member name ("target_reduction", "weights.shape", ...). Checks the parameters
// only, not that `input` exists. Uses ValidateSegmentOptions, ValidateSimplifyOptions,
// ParseView and the transfer-function parser, so it accepts exactly what RunJob can run.
absl::Status ValidateJobSpec(const JobSpec& spec, std::string* field = nullptr);

// Why `spec` cannot be simplified in slabs (stream_slab_voxels > 0), in words for an error
// message ("streamed simplification runs the field policy only; ..."), or empty when it can:
// the field policy, a target_reduction > 0 and no error tolerance, no PSNR floor, level record,
// "levels" or "curve" output. ValidateJobSpec refuses a streamed spec with it; the server asks
// before choosing to stream a job that does not fit in memory.
std::string StreamingRefusal(const JobSpec& spec);

// How the file names of a streamed simplify stage's window records begin, in the checkpoint
// folder ("simplify.pass-P.window-K.ckpt"; README "Stage checkpoints").
inline constexpr char kSimplifyWindowRecordPrefix[] = "simplify.pass-";

// The disk that a streamed simplify stage's checkpoints take at most, for a volume of `voxels`
// voxels simplified to `target_reduction`: one pass's window records (the cells written out and,
// in the final pass, the survivors; every window's carried cells) and the stage's checkpoint,
// which is written before the records are removed (README "Stage checkpoints"). The server
// admits a streamed job only when this fits on its data dir.
int64_t StreamRecordBytes(int64_t voxels, double target_reduction);

struct Artifact {
  std::string name;  // "mesh.vtu", "diff.png", ...
  std::filesystem::path path;
  uint64_t size_bytes = 0;
};

struct JobResult {
  std::vector<Artifact> artifacts;
  std::string metrics_json;  // the content of metrics.json
  // The job's region names, colours and DICOM codes (metrics.json "regions"), for the steps
  // after RunJob (the DICOM SEG).
  RegionTable regions;
  double seconds = 0;
};

// Where RunJob keeps its stage checkpoints (checkpoint.h): after "segment" the segmentation,
// after "simplify" the simplified mesh. A later RunJob with the same folder and key resumes after
// the last stage whose checkpoint is intact, with outputs identical to an uninterrupted run.
struct CheckpointOptions {
  std::filesystem::path dir;  // empty: no checkpoints are read or written
  // What the input is, e.g. the volume's sha256 (and the label map's). RunJob adds the spec's
  // parameters each stage depends on, so a checkpoint of another volume or spec is ignored.
  std::string key;
  // Called after a checkpoint was saved (not after one was resumed), with the stage name; the
  // server's test fault seam uses it to stop a job exactly at a stage boundary.
  std::function<void(const std::string& stage)> on_saved;
};

// Runs the job, writing every artifact into `out_dir` (created if missing). Progress stages, in
// order: "load", "segment", "tetra", "simplify", "write", "render", "curve" (only with the
// "curve" output), "diff"; a stage resumed from a checkpoint reports once, at 1, "resumed from
// checkpoint". Returns
// InvalidArgument for bad input (the message names the file and the problem), Cancelled if
// `cancel` fired (checked at least once per iteration of every stage). A checkpoint that cannot
// be written is reported in a progress message and the job goes on (it only costs a resume).
absl::StatusOr<JobResult> RunJob(const JobSpec& spec, const std::filesystem::path& out_dir,
                                 const ProgressFn& progress, const CancelToken* cancel,
                                 const CheckpointOptions& checkpoints = {});

}  // namespace decima::pipeline
