#include "core/pipeline/pipeline.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iterator>
#include <limits>
#include <optional>
#include <string_view>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status.h"
#include "core/io/dicom.h"
#include "core/io/volume_io.h"
#include "core/mesh/mesh_io.h"
#include "core/mesh/region_surface.h"
#include "core/mesh/tetrahedralize.h"
#include "core/metrics/fidelity.h"
#include "core/metrics/fidelity_json.h"
#include "core/pipeline/checkpoint.h"
#include "core/pipeline/job_run.h"
#include "core/pipeline/levels_output.h"
#include "core/pipeline/pictures.h"
#include "core/pipeline/psnr_floor.h"
#include "core/pipeline/report.h"
#include "core/render/camera.h"
#include "core/render/canvas.h"
#include "core/render/diff.h"
#include "core/render/plot.h"
#include "core/render/renderer.h"
#include "core/render/transfer_function.h"
#include "core/segment/segment.h"
#include "core/simplify/levels.h"
#include "core/simplify/levels_io.h"
#include "core/simplify/simplify.h"
#include "core/simplify/simplify_json.h"
#include "core/simplify/stream.h"
#include "core/volume/regions.h"

namespace decima::pipeline {

bool Wants(const JobSpec& spec, const char* kind) {
  return std::find(spec.outputs.begin(), spec.outputs.end(), kind) != spec.outputs.end();
}

namespace {

using Json = nlohmann::ordered_json;
using Stage = JobRun::StageScope;

absl::StatusOr<Volume> LoadInput(const JobSpec& spec, std::optional<DicomDescription>* dicom) {
  std::error_code ec;
  if (std::filesystem::is_directory(spec.input, ec)) {
    dicom->emplace();
    return ReadDicomSeries(spec.input, spec.series_instance_uid, &**dicom);
  }
  return io::ReadVolume(spec.input);
}

bool LooksLikeCt(const Volume& image, const ScalarRange& range) {
  return image.modality == "CT" || (image.modality.empty() && range.max > 1500);
}

// Transfer function: a preset name, "auto" (CT preset for CT or HU-like ranges, MRI T1 otherwise),
// or a JSON document.
absl::StatusOr<TransferFunction> ChooseTransferFunction(const std::string& tf, const Volume& image,
                                                        const ScalarRange& range) {
  if (!tf.empty() && tf.front() == '{')
    return ParseTransferFunction(tf, range, "transfer_function");
  if (tf != "auto") return TransferFunctionPreset(tf, range);
  return TransferFunctionPreset(LooksLikeCt(image, range) ? "ct" : "mri-t1", range);
}

// The preset a transfer-function spec resolves to, for captions ("ct", "mri-t1", "custom").
std::string ChosenPresetName(const std::string& tf, const Volume& image, const ScalarRange& range) {
  if (!tf.empty() && tf.front() == '{') return "custom";
  if (tf != "auto") return tf;
  return LooksLikeCt(image, range) ? "ct" : "mri-t1";
}

Json SegmentJson(const SegmentResult& seg, bool from_label_map) {
  Json j;
  j["source"] = from_label_map ? "label_map" : "level_set";
  j["iterations"] = seg.iterations;
  j["converged"] = seg.converged;
  j["class_means"] = seg.class_means;
  j["region_voxels"] = seg.region_voxels;
  j["region_volumes_mm3"] = seg.region_volumes_mm3;
  return j;
}

// The key of a stage's checkpoint: the caller's (the input) plus every spec parameter the
// stage's output depends on, so a checkpoint made for other parameters is never resumed.
std::string SegmentKey(const JobSpec& spec, const std::string& input_key) {
  return absl::StrCat(input_key, "|segment regions=", spec.regions,
                      " means=", absl::StrJoin(spec.class_means, ","),
                      " label_map=", spec.label_map ? spec.label_map->string() : "",
                      " series=", spec.series_instance_uid);
}

std::string SimplifyKey(const JobSpec& spec, const std::string& segment_key) {
  char buf[256];
  std::snprintf(buf, sizeof buf,
                "|simplify policy=%s target=%.17g tolerance=%.17g w=%.17g,%.17g,%.17g levels=%.17g",
                SimplifyPolicyName(spec.policy), spec.target_reduction, spec.error_tolerance,
                spec.weights.shape, spec.weights.volume, spec.weights.neighbour, LevelFloor(spec));
  std::string key = segment_key + buf;
  // The field policy's default changed from the voxel staircase to free interfaces (issue 31):
  // a checkpoint made before says nothing of them and is not reused.
  if (spec.policy == SimplifyPolicy::kField) {
    absl::StrAppend(&key, " interfaces=", InterfaceModeName(spec.interfaces));
  }
  // Only when set, so the keys of jobs without a floor stay what they were.
  if (spec.min_psnr) absl::StrAppend(&key, absl::StrFormat(" min_psnr=%.17g", *spec.min_psnr));
  if (spec.stream_slab_voxels > 0) absl::StrAppend(&key, " slabs=", spec.stream_slab_voxels);
  return key;
}

Json LevelsJson(const LevelsOutput& l) {
  if (!l.artifact) return {{"note", l.note}};
  return {{"file", *l.artifact},
          {"bytes", l.bytes},
          {"collapses", l.collapses},
          {"deepest_reduction", l.deepest_reduction},
          {"exhausted", l.exhausted},
          {"seconds", l.seconds},
          {"note", l.note}};
}

// The stage's output from its checkpoint, or nothing (no checkpoints, none saved yet, or one
// that is damaged or of other inputs: reported, and the stage runs again).
template <typename T>
std::optional<T> Resume(const CheckpointOptions& c, const Stage& stage, const std::string& key,
                        absl::StatusOr<T> (*parse)(const std::string&)) {
  if (c.dir.empty()) return std::nullopt;
  auto payload = ReadCheckpoint(c.dir / absl::StrCat(stage.name(), ".ckpt"), key);
  absl::StatusOr<T> value = payload.ok() ? parse(*payload) : absl::StatusOr<T>(payload.status());
  if (!value.ok()) {
    if (!absl::IsNotFound(value.status())) {
      stage.Report(0, absl::StrCat("checkpoint ignored: ", value.status().message()));
    }
    return std::nullopt;
  }
  stage.Report(1, "resumed from checkpoint");
  return std::move(*value);
}

// Whether the checkpoint was saved. `fill` writes the payload (only when there is a folder).
bool SaveCheckpoint(const CheckpointOptions& c, const Stage& stage, const std::string& key,
                    const std::function<void(ByteWriter&)>& fill) {
  if (c.dir.empty()) return false;
  const std::filesystem::path path = c.dir / absl::StrCat(stage.name(), ".ckpt");
  if (absl::Status st = WriteCheckpoint(path, key, fill); !st.ok()) {
    stage.Report(1, absl::StrCat("checkpoint not saved: ", st.message()));
    return false;
  }
  if (c.on_saved) c.on_saved(stage.name());
  return true;
}

// The streamed simplifier's window records (StreamJournal) as checkpoint files beside the stage
// checkpoints, "simplify.pass-P.window-K.ckpt", each under the simplify key plus its (P, K), so
// a record of another job, spec or window is never read back. Saving window 0 of a pass removes
// the earlier passes' records (a run only reads back its latest pass); the stage's checkpoint
// removes them all (Remove). The on_saved hook gets "simplify-window-N" for the run's N-th window
// (counted from 1 across its passes), whichever attempt saved it.
struct WindowCheckpoints {
  const CheckpointOptions& c;
  const Stage& stage;
  const std::string& key;
  StreamJournal journal;
  double fraction = 0;  // the stage's, as last reported: the records' own messages keep it

  // The stage's progress, for SimplifyStreamed.
  ProgressFn Forward() {
    return [this, forward = stage.Forward()](const Progress& p) {
      fraction = p.fraction;
      if (forward) forward(p);
    };
  }

  static constexpr std::string_view kPrefix = kSimplifyWindowRecordPrefix;
  std::filesystem::path Path(int pass, int64_t window) const {
    return c.dir / absl::StrFormat("%s%d.window-%d.ckpt", kPrefix, pass, window);
  }
  std::string Key(int pass, int64_t window) const {
    return absl::StrCat(key, " |stream window pass=", pass, " window=", window);
  }
  // The records of passes below `below_pass` (all of them for INT_MAX), and temporary files.
  void Remove(int below_pass) const {
    std::error_code ec;
    for (const auto& e : std::filesystem::directory_iterator(c.dir, ec)) {
      const std::string name = e.path().filename().string();
      int pass = 0;
      if (name.rfind(kPrefix, 0) == 0 &&
          std::sscanf(name.c_str() + kPrefix.size(), "%d", &pass) == 1 && pass < below_pass) {
        std::filesystem::remove(e.path(), ec);
      }
    }
  }
  WindowCheckpoints(const CheckpointOptions& options, const Stage& simplify,
                    const std::string& simplify_key)
      : c(options), stage(simplify), key(simplify_key) {
    if (c.dir.empty()) return;
    journal.save = [this](int pass, int64_t window, const std::string& record) {
      if (absl::Status st = WriteCheckpoint(Path(pass, window), Key(pass, window), record);
          !st.ok()) {
        stage.Report(fraction, absl::StrCat("slab record not saved: ", st.message()));
        return;
      }
      if (window == 0) Remove(pass);
      if (c.on_saved) {
        c.on_saved(absl::StrCat("simplify-window-", pass * journal.windows_per_pass + window + 1));
      }
    };
    journal.load = [this](int pass, int64_t window) -> std::optional<std::string> {
      absl::StatusOr<std::string> payload = ReadCheckpoint(Path(pass, window), Key(pass, window));
      if (!payload.ok()) {
        if (!absl::IsNotFound(payload.status())) {
          stage.Report(fraction, absl::StrCat("slab record ignored: ", payload.status().message()));
        }
        return std::nullopt;
      }
      return std::move(*payload);
    };
  }
};

// What the stages after "render" use of it.
struct Rendered {
  std::vector<ViewRender> views;
  TransferFunction transfer_function;
  DiffImageOptions heat;  // one heat-map scale for every view of the job
  PictureCaption caption;
  // With "report": the 3D view's surfaces (ViewSurfaces), made before the render stage consumes
  // the simplified mesh, and the triangle count before merging.
  std::vector<RegionSurface> view_surfaces;
  int64_t view_surfaces_extracted = 0;
};

// One point of the diff1 curve: a simplification of the original to `reduction`.
struct CurvePoint {
  double reduction = 0;
  int64_t cells_removed = 0;
  double diff1 = 0;
};

// load: the volume file or DICOM series (and, for a series, its patient, study and series for
// the report: kept out of metrics.json, which is not meant to carry patient data).
absl::StatusOr<Volume> LoadStage(const JobSpec& spec, JobRun& run,
                                 std::optional<DicomDescription>* dicom) {
  DECIMA_ASSIGN_OR_RETURN(const Stage stage, run.Stage("load"));
  stage.Report(0, spec.input.string());
  DECIMA_ASSIGN_OR_RETURN(Volume image, LoadInput(spec, dicom));
  run.metrics()["input"] = {{"dims", image.dims},
                            {"spacing_mm", {image.spacing[0], image.spacing[1], image.spacing[2]}},
                            {"type", std::string(VoxelTypeName(image.type))},
                            {"modality", image.modality},
                            {"voxels", image.voxel_count()}};
  run.Plan(PredictStages(spec, image.dims));
  stage.Report(1, Describe(image));
  return image;
}

// segment: the level set, or the given label map; labels.nii.gz when asked for.
absl::StatusOr<SegmentResult> SegmentStage(const JobSpec& spec, const Volume& image,
                                           const CheckpointOptions& checkpoints,
                                           const std::string& key, JobRun& run) {
  DECIMA_ASSIGN_OR_RETURN(Stage stage, run.Stage("segment"));
  SegmentResult seg;
  if (auto saved = Resume(checkpoints, stage, key, &ParseSegmentResult)) {
    seg = std::move(*saved);
    run.Resumed("segment");
  } else {
    if (spec.label_map) {
      stage.Report(0, absl::StrCat("label map ", spec.label_map->string()));
      DECIMA_ASSIGN_OR_RETURN(const Volume label_map, io::ReadVolume(*spec.label_map));
      DECIMA_ASSIGN_OR_RETURN(seg, SegmentationFromLabelMap(image, label_map));
    } else {
      SegmentOptions so;
      so.regions = spec.regions;
      so.class_means = spec.class_means;
      DECIMA_ASSIGN_OR_RETURN(seg, Segment(image, so, stage.Forward(), stage.cancel()));
    }
    SaveCheckpoint(checkpoints, stage, key, [&](ByteWriter& w) { PutSegmentResult(w, seg); });
  }
  stage.End();  // the stage's figures are the segmentation's, not the label map file's
  run.metrics()["segmentation"] = SegmentJson(seg, spec.label_map.has_value());
  // A level record is applied to the mesh of this segmentation (levels_output.h), so it comes
  // with the labels it needs even when they were not asked for.
  if (Wants(spec, "labels") || LevelFloor(spec) > 0) {
    DECIMA_RETURN_IF_ERROR(io::WriteNifti(seg.labels, run.OutputPath("labels.nii.gz")));
    run.AddArtifact("labels.nii.gz");
  }
  return seg;
}

// The job's region table (core/volume/regions.h), from the segmentation's class means and the
// spec's names; metrics.json "regions" lists it.
absl::StatusOr<RegionTable> RegionTableOf(const JobSpec& spec, const Volume& image,
                                          const SegmentResult& seg, JobRun& run) {
  const auto [lo, hi] = image.ValueRange();
  const bool hu = PlausiblyHu(image.modality, lo, hi);
  if (!spec.region_names.empty() && spec.region_names.size() != seg.class_means.size()) {
    // Only a label map can get here: its label count is K, whatever spec.regions said.
    return absl::InvalidArgumentError(absl::StrCat("region_names: ", spec.region_names.size(),
                                                   " names for the ", seg.class_means.size(),
                                                   " regions of the label map"));
  }
  RegionTable table;
  DECIMA_RETURN_IF_ERROR(MakeRegionTable(seg.class_means, seg.region_voxels, hu, spec.region_names,
                                         &table, hu ? HuOffset(lo) : 0));
  Json regions = Json::array();
  for (const RegionInfo& r : table.regions) {
    char colour[8];
    std::snprintf(colour, sizeof colour, "#%02x%02x%02x", r.rgb[0], r.rgb[1], r.rgb[2]);
    Json j = {{"label", r.label},
              {"name", r.name},
              {"colour", colour},
              {"voxels", r.voxels},
              {"mean", r.mean},
              {"dicom_seg", r.in_seg},
              {"dicom_type", r.type.meaning}};
    if (r.label < seg.region_volumes_mm3.size()) j["volume_mm3"] = seg.region_volumes_mm3[r.label];
    if (hu) j["mean_hu"] = r.mean_hu;
    regions.push_back(std::move(j));
  }
  run.metrics()["regions"] = std::move(regions);
  run.metrics()["region_naming"] = table.naming;
  return table;
}

// tetra: the voxel grid as tetrahedra, region interfaces from the segmentation.
SimplifyOptions SimplifyOptionsOf(const JobSpec& spec) {
  SimplifyOptions o;
  o.policy = spec.policy;
  o.target_reduction = spec.target_reduction;
  o.error_tolerance = spec.error_tolerance;
  o.interfaces = spec.interfaces;
  o.weights = spec.weights;
  o.record_levels_to = LevelFloor(spec);
  // The floor's search records down to its depth; a re-run for the levels output (after a resume)
  // must record the same collapses, so the depth belongs to the options, not to the search alone.
  if (spec.min_psnr) {
    o.record_levels_to = std::max(o.record_levels_to, PsnrSearchDepth(spec.target_reduction));
  }
  return o;
}

// Whether a stage after simplify reads the original mesh's cells: the level record (written from
// the original and the collapses), the curve (simplifies the original again) and the render from
// the materialized mesh. Every other stage reads its vertices only (the fidelity's feature counts)
// or the voxel grid, so the cells the field run dropped stay dropped (issue 30: 17 bytes per cell,
// 85 per voxel, off the write and render peaks). These are also the only stages after simplify
// that read the original at all: without them the simplify stage counts the feature vertices and
// frees the whole original (SimplifyStage).
bool NeedsOriginalCells(const JobSpec& spec) {
  return Wants(spec, "levels") || Wants(spec, "curve") ||
         spec.original_from == JobSpec::OriginalSource::kMesh;
}

// Whether any stage reads the original mesh's cells: one after simplify (NeedsOriginalCells), or
// the simplify stage itself, unless it is a plain field run (RunsWithoutCells; a level record's
// extraction and a PSNR floor's search read them too).
bool OriginalCellsRead(const JobSpec& spec) {
  return NeedsOriginalCells(spec) || spec.levels_file || spec.min_psnr ||
         !RunsWithoutCells(SimplifyOptionsOf(spec));
}

// tetra: the 5-tet grid mesh. Its cells (17 bytes per cell, 85 per voxel) are written only when
// a stage reads them (OriginalCellsRead); otherwise they are computed from the cell id throughout
// the job (issue 30: off the tetra, simplify, write and render peaks).
absl::StatusOr<TetMesh> TetrahedralizeStage(const JobSpec& spec, const Volume& image,
                                            const SegmentResult& seg, JobRun& run) {
  DECIMA_ASSIGN_OR_RETURN(const Stage stage, run.Stage("tetra"));
  TetrahedralizeOptions to;
  to.labels = &seg.labels;
  to.interface_distance = seg.interface_distance_voxels.data();
  to.cells = OriginalCellsRead(spec);
  return Tetrahedralize(image, to, stage.Forward(), stage.cancel());
}

Json PsnrFloorJson(const PsnrFloorSearch& s) {
  auto finite = [](double v) { return std::isfinite(v) ? Json(v) : Json(nullptr); };
  Json probes = Json::array();
  for (const PsnrProbe& p : s.probes) {
    probes.push_back({{"kind", p.run ? "run" : "level"},
                      {"requested", p.requested},
                      {"reduction", p.reduction},
                      {"cells", p.cells},
                      {"psnr_db", finite(p.psnr_db)}});
  }
  Json j{{"floor_db", s.floor_db},
         {"stopped_by_floor", s.floor_stopped},
         {"kept_kind", s.kept.run ? "run" : "level"},
         {"kept_reduction", s.kept.reduction},
         {"kept_psnr_db", finite(s.kept.psnr_db)}};
  if (s.deeper) {
    j["deeper_kind"] = s.deeper->run ? "run" : "level";
    j["deeper_reduction"] = s.deeper->reduction;
    j["deeper_psnr_db"] = finite(s.deeper->psnr_db);
  }
  j["probes"] = probes;
  j["step"] = kPsnrSearchStep;
  j["seconds"] = s.seconds;
  return j;
}

// simplify: feature-preserving cell collapse down to the target.
// With a PSNR floor, the levels of the record searched for the deepest one that keeps it.
// Memory: this stage is the job's peak, so a plain field run frees the original's cells while it
// runs (SimplifyDroppingCells) and writes them back only for a later stage that reads them
// (NeedsOriginalCells).
// When no later stage reads the original (NeedsOriginalCells: the level record, the curve and the
// render from the mesh are also all that read its vertices), the fidelity's feature-vertex counts,
// the only other reader of its vertices and of the vertex map, are made at the end of this stage
// into `features`, and the original TetMesh and the vertex map are freed (issue 30: 22 + 4 bytes
// per voxel off the write and render stages).
absl::StatusOr<SimplifyResult> SimplifyStage(const JobSpec& spec, const Volume& image,
                                             TetMesh& original,
                                             const CheckpointOptions& checkpoints,
                                             const std::string& key, JobRun& run,
                                             std::optional<FeatureVertexCounts>* features) {
  DECIMA_ASSIGN_OR_RETURN(Stage stage, run.Stage("simplify"));
  const int64_t vertices_before = original.vertex_count();
  const SimplifyOptions options = SimplifyOptionsOf(spec);
  SimplifyResult simplified;
  std::optional<PsnrFloorSearch> search;
  int64_t resumed_windows = 0;
  std::optional<WindowCheckpoints> windows;  // a streamed run's window records
  if (auto saved = Resume(checkpoints, stage, key, &ParseSimplifyResult)) {
    simplified = std::move(*saved);
    run.Resumed("simplify");
  } else if (spec.levels_file) {
    // A level of an earlier job's record: one pass over the cells and the refit, so no
    // checkpoint (reading it back would cost about as much).
    stage.Report(0, absl::StrCat("level ", spec.target_reduction, " of ",
                                 spec.levels_file->filename().string()));
    DECIMA_ASSIGN_OR_RETURN(const SimplifyLevels levels, ReadLevels(*spec.levels_file));
    DECIMA_ASSIGN_OR_RETURN(simplified,
                            ExtractLevel(original, levels, spec.target_reduction, options.threads,
                                         stage.Forward(), stage.cancel()));
  } else {
    if (spec.min_psnr) {
      search.emplace();
      DECIMA_ASSIGN_OR_RETURN(simplified,
                              SimplifyToPsnrFloor(image, original, options, *spec.min_psnr,
                                                  /*refine=*/!Wants(spec, "levels"), &*search,
                                                  stage.Forward(), stage.cancel()));
    } else if (spec.stream_slab_voxels > 0) {
      // The windows compute their cells from the grid, so the original's stay dropped (the tetra
      // stage wrote none unless a later stage reads them: those are refused with streaming).
      DropGridCells(&original);
      windows.emplace(checkpoints, stage, key);
      DECIMA_ASSIGN_OR_RETURN(
          simplified, SimplifyStreamed(original, options, spec.stream_slab_voxels,
                                       windows->Forward(), stage.cancel(), &windows->journal));
      resumed_windows = windows->journal.resumed_windows;
      // Part of the stage came from its records: its time says nothing of the machine's speed.
      if (resumed_windows > 0) run.Resumed("simplify");
    } else {
      DECIMA_ASSIGN_OR_RETURN(
          simplified, SimplifyDroppingCells(&original, options, stage.Forward(), stage.cancel(),
                                            NeedsOriginalCells(spec)));
    }
    // Written as it is serialized: a copy would be ~25 B per voxel beside the mesh at a clinical
    // scan's simplify stage end (and nothing when the job keeps no checkpoints).
    const bool saved = SaveCheckpoint(checkpoints, stage, key,
                                      [&](ByteWriter& w) { PutSimplifyResult(w, simplified); });
    // Only once the stage's checkpoint is saved: a stop before still finds the records.
    if (windows && saved) windows->Remove(std::numeric_limits<int>::max());
  }
  if (!NeedsOriginalCells(spec)) {
    DECIMA_ASSIGN_OR_RETURN(*features,
                            CountFeatureVertices(original, simplified.vertex_map, simplified.mesh));
    original = TetMesh();
    std::vector<int32_t>().swap(simplified.vertex_map);
  }
  stage.End();
  run.metrics()["simplification"] = SimplifyResultToJson(simplified, options, vertices_before);
  if (spec.levels_file) run.metrics()["simplification"]["from_levels"] = true;
  // 0: in memory; else the slab depth, the server's choice when the spec left it open.
  run.metrics()["simplification"]["stream_slab_voxels"] = spec.stream_slab_voxels;
  if (resumed_windows > 0) run.metrics()["resumed_simplify_windows"] = resumed_windows;
  if (spec.min_psnr) {
    // A resumed stage has its mesh and stop message but not the probes of the search.
    run.metrics()["min_psnr"] =
        search ? PsnrFloorJson(*search)
               : Json{{"floor_db", *spec.min_psnr}, {"note", "resumed from checkpoint"}};
  }
  return simplified;
}

// The mesh files the spec asks for, in kOutputKinds order; the first one's size (fidelity
// reports it), 0 when none is asked for.
absl::StatusOr<int64_t> WriteMeshFiles(const JobSpec& spec, const TetMesh& mesh,
                                       const RegionTable& regions, const Stage& stage,
                                       JobRun& run) {
  struct MeshFile {
    const char* kind;
    const char* name;
  };
  std::vector<MeshFile> files;
  for (const MeshFile& f :
       {MeshFile{"vtu", "mesh.vtu"}, MeshFile{"msh", "mesh.msh"}, MeshFile{"medit", "mesh.mesh"}}) {
    if (Wants(spec, f.kind)) files.push_back(f);
  }
  int64_t first_bytes = 0;
  for (size_t i = 0; i < files.size(); ++i) {
    stage.Report(double(i) / files.size(), files[i].name);
    const std::filesystem::path p = run.OutputPath(files[i].name);
    if (std::string(files[i].kind) == "vtu") {
      VtuWriteOptions wo;
      wo.compress = spec.vtu_compression_level > 0;
      wo.level = std::max(1, spec.vtu_compression_level);
      wo.compressor = spec.mesh_compression;
      wo.regions = &regions;
      DECIMA_RETURN_IF_ERROR(WriteVtu(mesh, p, wo));
    } else if (std::string(files[i].kind) == "msh") {
      GmshWriteOptions go;
      go.regions = &regions;
      DECIMA_RETURN_IF_ERROR(WriteGmsh(mesh, p, go));
    } else {
      DECIMA_RETURN_IF_ERROR(WriteMedit(mesh, p));
    }
    run.AddArtifact(files[i].name);
    if (first_bytes == 0) first_bytes = static_cast<int64_t>(run.artifacts().back().size_bytes);
    DECIMA_RETURN_IF_ERROR(stage.CheckCancelled());
  }
  return first_bytes;
}

// One closed surface per region of the simplified mesh: STL files and/or one glTF.
absl::Status WriteRegionSurfaces(const JobSpec& spec, const TetMesh& mesh,
                                 const RegionTable& regions, const Stage& stage, JobRun& run) {
  stage.Report(1, "region surfaces");
  const std::vector<RegionSurface> surfaces = ExtractRegionSurfaces(mesh);
  const std::vector<std::string> files = SurfaceFileNames(regions);
  std::vector<RegionStyle> styles;
  std::vector<std::string> names;
  for (const RegionSurface& s : surfaces) {
    if (s.region < regions.regions.size()) {
      const RegionInfo& r = regions.regions[s.region];
      styles.push_back(StyleOf(r.name, r.rgb));
      names.push_back(files[s.region]);
    } else {  // a mesh region the table does not know: cannot happen for a job's own mesh
      styles.push_back(DefaultRegionStyle(s.region));
      names.push_back(absl::StrCat("surface-region_", s.region + 1, ".stl"));
    }
  }
  for (size_t i = 0; i < surfaces.size() && Wants(spec, "stl"); ++i) {
    const std::string& name = names[i];
    DECIMA_RETURN_IF_ERROR(WriteStl(surfaces[i], styles[i].name, run.OutputPath(name)));
    run.AddArtifact(name);
  }
  if (Wants(spec, "glb")) {
    DECIMA_RETURN_IF_ERROR(WriteGlb(surfaces, styles, run.OutputPath("surfaces.glb")));
    run.AddArtifact("surfaces.glb");
  }
  return stage.CheckCancelled();
}

// write: only the mesh formats the spec asks for, and the collapse record with "levels" (a
// resumed simplification is run again for it). Returns the size of the first mesh file.
absl::StatusOr<int64_t> WriteStage(const JobSpec& spec, const TetMesh& original,
                                   SimplifyResult& simplified, const RegionTable& regions,
                                   JobRun& run) {
  DECIMA_ASSIGN_OR_RETURN(const Stage stage, run.Stage("write"));
  DECIMA_ASSIGN_OR_RETURN(const int64_t mesh_bytes,
                          WriteMeshFiles(spec, simplified.mesh, regions, stage, run));
  if (Wants(spec, "stl") || Wants(spec, "glb")) {
    DECIMA_RETURN_IF_ERROR(WriteRegionSurfaces(spec, simplified.mesh, regions, stage, run));
  }
  DECIMA_ASSIGN_OR_RETURN(const LevelsOutput levels,
                          WriteLevelsOutput(spec, SimplifyOptionsOf(spec), original, &simplified,
                                            run.out_dir(), stage.cancel()));
  if (levels.artifact) run.AddArtifact(*levels.artifact);
  run.metrics()["levels"] = LevelsJson(levels);
  if (Wants(spec, "vtu")) {
    // How mesh.vtu is encoded (lossless either way): "none" at level 0, else the compressor.
    run.metrics()["mesh_compression"] =
        spec.vtu_compression_level == 0 ? "none" : VtuCompressorName(spec.mesh_compression);
  }
  const bool mesh_asked = Wants(spec, "vtu") || Wants(spec, "msh") || Wants(spec, "medit");
  stage.Report(1, mesh_asked ? "mesh written" : "no mesh file asked for");
  return mesh_bytes;
}

// Fidelity of the simplified mesh (field, labels, interfaces, quality), measured before rendering
// so that a render failure still leaves the field metrics in the log.
// The feature-vertex counts come from `features` when the simplify stage made them (and freed the
// original), else from the original and the vertex map.
absl::Status MeasureFidelityStep(const Volume& image, const SegmentResult& seg,
                                 const TetMesh& original, const SimplifyResult& simplified,
                                 const std::optional<FeatureVertexCounts>& features,
                                 int64_t mesh_bytes, Stage& stage, JobRun& run) {
  // Reported under "render": its seconds belong to the picture-and-numbers part of the job, and
  // a silent gap after "write 100%" looked like a hang.
  stage.Report(0, "measuring fidelity");
  FidelityOptions fo;
  fo.labels = &seg.labels;
  if (features) {
    fo.feature_counts = &*features;
  } else {
    fo.original = &original;
    fo.vertex_map = &simplified.vertex_map;
  }
  fo.mesh_bytes = mesh_bytes;
  DECIMA_ASSIGN_OR_RETURN(const FidelityMetrics fidelity,
                          MeasureFidelity(image, simplified.mesh, fo, stage.cancel()));
  run.metrics()["fidelity"] = FidelityToJson(fidelity);
  stage.SplitTiming("fidelity");
  return absl::OkStatus();
}

// The original in every view of the spec, from its renderable form (RenderableGrid or
// RenderableMesh, which render the same pixels): chooses the transfer function and the cameras
// (from the original's bounds, so the simplified pictures align pixel by pixel).
template <typename Renderable>
absl::Status RenderOriginalViews(const JobSpec& spec, const Volume& image,
                                 const Renderable& original_r, const Stage& stage, Rendered* out) {
  DECIMA_ASSIGN_OR_RETURN(
      out->transfer_function,
      ChooseTransferFunction(spec.transfer_function, image, original_r.scalar_range));
  out->caption.preset = ChosenPresetName(spec.transfer_function, image, original_r.scalar_range);
  ViewOptions vo;
  vo.width = vo.height = spec.image_size;
  const double steps = 2.0 * spec.views.size();
  for (size_t i = 0; i < spec.views.size(); ++i) {
    ViewRender v;
    v.name = spec.views[i];
    DECIMA_ASSIGN_OR_RETURN(const ViewDirection view, ParseView(v.name));
    DECIMA_ASSIGN_OR_RETURN(v.camera, MakeViewCamera(view, original_r.bounds, vo));
    DECIMA_ASSIGN_OR_RETURN(
        v.original, Render(original_r, v.camera, out->transfer_function, {}, stage.cancel()));
    stage.Report((i + 1.0) / (steps + 1), absl::StrCat(v.name, ": original rendered"));
    out->views.push_back(std::move(v));
  }
  return absl::OkStatus();
}

// Every view of the spec, original and simplified with the same camera and transfer function.
// Memory (issue 30): the original is rendered straight from the voxel grid (RenderableGrid:
// positions and scalars, 16 bytes per voxel; the cells and their neighbours are computed from
// the cell id), and with `release_original` (no later stage needs it) the original TetMesh is
// freed before that (the simplify stage already did, unless the levels need it), so no per-tet
// array of the original is resident while rendering. The original is rendered in every view first
// and its renderable form freed before the simplified one is built. With spec.original_from ==
// kMesh the earlier path: the original's RenderableMesh (8 int32 per tet plus positions, about 170
// bytes per voxel), built consuming the TetMesh when it may be released. The pictures do not depend
// on either choice.
// The simplified mesh is consumed (BuildRenderableMesh(TetMesh&&)): no stage after this one reads
// it (the report's surfaces are made before), so the mesh, its renderable form and the adjacency
// being built are never all resident (issue 30: about 20 bytes per cell off the stage's peak).
absl::Status RenderViews(const JobSpec& spec, const Volume& image, TetMesh& original,
                         bool release_original, TetMesh& simplified, const Stage& stage,
                         Rendered* out) {
  if (spec.original_from == JobSpec::OriginalSource::kGrid) {
    if (release_original) original = TetMesh();
    stage.Report(0, "preparing the original grid for rendering");
    DECIMA_ASSIGN_OR_RETURN(const RenderableGrid original_r,
                            BuildRenderableGrid(image, {}, stage.cancel()));
    DECIMA_RETURN_IF_ERROR(RenderOriginalViews(spec, image, original_r, stage, out));
  } else {
    stage.Report(0, "building the original's renderable mesh");
    std::optional<RenderableMesh> original_r;
    if (release_original) {
      DECIMA_ASSIGN_OR_RETURN(original_r,
                              BuildRenderableMesh(std::move(original), {}, stage.cancel()));
    } else {
      DECIMA_ASSIGN_OR_RETURN(original_r, BuildRenderableMesh(original, {}, stage.cancel()));
    }
    DECIMA_RETURN_IF_ERROR(RenderOriginalViews(spec, image, *original_r, stage, out));
  }
  const double steps = 2.0 * spec.views.size();
  stage.Report(spec.views.size() / (steps + 1), "building the simplified renderable mesh");
  DECIMA_ASSIGN_OR_RETURN(const RenderableMesh simplified_r,
                          BuildRenderableMesh(std::move(simplified), {}, stage.cancel()));
  for (size_t i = 0; i < out->views.size(); ++i) {
    ViewRender& v = out->views[i];
    DECIMA_ASSIGN_OR_RETURN(
        v.simplified, Render(simplified_r, v.camera, out->transfer_function, {}, stage.cancel()));
    DECIMA_ASSIGN_OR_RETURN(v.diff, Diff(v.original, v.simplified));
    stage.Report((spec.views.size() + i + 1.0) / (steps + 1),
                 absl::StrCat(v.name, ": simplified rendered"), {{"diff1", v.diff.diff1}});
  }
  out->heat.max_value = kHeatScaleMax;
  return absl::OkStatus();
}

// The pictures of each view: artifacts with "images"; with "report" alone only the comparison,
// in the scratch folder, for the page.
absl::Status WriteViewPicturesOf(const JobSpec& spec, const Rendered& rendered, JobRun& run,
                                 std::vector<ReportPicture>* report) {
  for (size_t i = 0; i < rendered.views.size(); ++i) {
    const ViewRender& v = rendered.views[i];
    const std::string comparison = ViewPictureName("comparison", v.name, i);
    std::filesystem::path comparison_path;
    if (Wants(spec, "images")) {
      DECIMA_RETURN_IF_ERROR(
          WriteViewPictures(v, i, rendered.caption, rendered.heat, run.out_dir()));
      for (const char* base : {"original", "simplified", "diff", "comparison"}) {
        run.AddArtifact(ViewPictureName(base, v.name, i));
      }
      comparison_path = run.OutputPath(comparison);
    } else if (Wants(spec, "report")) {
      comparison_path = run.ScratchPath(comparison);
      DECIMA_RETURN_IF_ERROR(
          WriteComparisonPicture(v, rendered.caption, rendered.heat, comparison_path));
    } else {
      continue;
    }
    report->push_back(
        {absl::StrCat("View ", v.name, ": original mesh, simplified mesh, difference"),
         comparison_path,
         absl::StrCat("Both meshes rendered with the same camera and colours; letters give the "
                      "patient's sides (R/L right/left, A/P anterior/posterior, S/I superior/"
                      "inferior) and the bar a length in mm. The difference is the colour "
                      "distance of each pixel between the two renders on a fixed scale: black is "
                      "no difference, pale yellow ",
                      FormatNumber(rendered.heat.max_value),
                      " or more (of at most 442), the same scale in every job.")});
  }
  return absl::OkStatus();
}

PictureCaption CaptionOf(const JobSpec& spec, const SegmentResult& seg,
                         const SimplifyResult& simplified) {
  PictureCaption c;
  c.input_name = spec.input_name.empty() ? spec.input.filename().string() : spec.input_name;
  c.job_name = spec.job_name;
  c.regions = seg.class_means.size();
  c.from_label_map = spec.label_map.has_value();
  c.target_reduction = spec.target_reduction;
  c.achieved_reduction = simplified.achieved_reduction;
  c.policy = SimplifyPolicyName(spec.policy);
  return c;
}

// render: fidelity, then every view rendered and measured (diff1 is part of metrics.json); the
// pictures are written when "images" or "report" is asked for.
// The simplified mesh is consumed (RenderViews): only its SimplifyResult figures are left after.
absl::StatusOr<Rendered> RenderStage(const JobSpec& spec, const Volume& image,
                                     const SegmentResult& seg, TetMesh& original,
                                     SimplifyResult& simplified,
                                     const std::optional<FeatureVertexCounts>& features,
                                     int64_t mesh_bytes, JobRun& run,
                                     std::vector<ReportPicture>* report) {
  DECIMA_ASSIGN_OR_RETURN(Stage stage, run.Stage("render"));
  DECIMA_RETURN_IF_ERROR(
      MeasureFidelityStep(image, seg, original, simplified, features, mesh_bytes, stage, run));
  Rendered rendered;
  if (Wants(spec, "report")) {
    rendered.view_surfaces =
        ViewSurfaces(simplified.mesh, kViewTriangleBudget, &rendered.view_surfaces_extracted);
  }
  rendered.caption = CaptionOf(spec, seg, simplified);
  // Only the curve simplifies the original again after this stage.
  const bool release_original = !Wants(spec, "curve");
  DECIMA_RETURN_IF_ERROR(
      RenderViews(spec, image, original, release_original, simplified.mesh, stage, &rendered));
  // (simplified.mesh is empty from here on.)
  Json views = Json::array();
  for (const ViewRender& v : rendered.views) {
    views.push_back({{"view", v.name},
                     {"diff1", v.diff.diff1},
                     {"max_diff2", v.diff.max_diff2},
                     {"changed_pixels", v.diff.changed_pixels}});
  }
  DECIMA_RETURN_IF_ERROR(WriteViewPicturesOf(spec, rendered, run, report));
  stage.End();
  run.metrics()["render"] = {{"size", spec.image_size},
                             {"transfer_function", spec.transfer_function},
                             {"preset", rendered.caption.preset},
                             {"heat_scale_max", rendered.heat.max_value},
                             {"views", views}};
  run.metrics()["diff1"] = views[0]["diff1"];
  run.metrics()["outputs"] = spec.outputs;
  return rendered;
}

// The paper's Fig. 5 for one job: diff1 of the first view against the cells removed, from
// separate simplifications of the original (same options, targets 10 %, 20 %, ... below the
// job's achieved reduction), rendered with the job's camera and transfer function. The job's
// own point is added by the caller.
absl::StatusOr<std::vector<CurvePoint>> DiffCurve(const TetMesh& original, SimplifyOptions options,
                                                  double job_reduction, const ViewRender& view,
                                                  const TransferFunction& tf, const Stage& stage) {
  std::vector<double> targets;
  for (int step = 1; step <= 9 && step * 0.1 < job_reduction - 0.05; ++step) {
    targets.push_back(step * 0.1);
  }
  std::vector<CurvePoint> points;
  for (size_t i = 0; i < targets.size(); ++i) {
    stage.Report(double(i) / (targets.size() + 1),
                 absl::StrCat("simplifying to ", FormatPercent(targets[i])));
    options.target_reduction = targets[i];
    options.error_tolerance = 0;
    options.record_levels_to = 0;  // a record would take each point's run down to the floor
    DECIMA_ASSIGN_OR_RETURN(const SimplifyResult s,
                            Simplify(original, options, nullptr, stage.cancel()));
    DECIMA_ASSIGN_OR_RETURN(const RenderableMesh r,
                            BuildRenderableMesh(s.mesh, {}, stage.cancel()));
    DECIMA_ASSIGN_OR_RETURN(const RenderedImage img,
                            Render(r, view.camera, tf, {}, stage.cancel()));
    DECIMA_ASSIGN_OR_RETURN(const DiffResult d, Diff(view.original, img));
    points.push_back({s.achieved_reduction, s.input_cells - s.output_cells, d.diff1});
  }
  return points;
}

// curve: the diff1 curve (metrics "curve" and curve.png), only when asked for.
absl::Status CurveStage(const JobSpec& spec, const TetMesh& original,
                        const SimplifyResult& simplified, const Rendered& rendered, JobRun& run,
                        std::vector<ReportPicture>* report) {
  DECIMA_ASSIGN_OR_RETURN(Stage stage, run.Stage("curve"));
  const ViewRender& first = rendered.views[0];
  DECIMA_ASSIGN_OR_RETURN(
      std::vector<CurvePoint> curve,
      DiffCurve(original, SimplifyOptionsOf(spec), simplified.achieved_reduction, first,
                rendered.transfer_function, stage));
  curve.push_back({simplified.achieved_reduction, simplified.input_cells - simplified.output_cells,
                   first.diff.diff1});
  PlotSeries series{absl::StrCat(SimplifyPolicyName(spec.policy), " policy"), {}};
  Json points = Json::array();
  for (const CurvePoint& c : curve) {
    series.points.push_back({double(c.cells_removed), c.diff1});
    points.push_back(
        {{"reduction", c.reduction}, {"cells_removed", c.cells_removed}, {"diff1", c.diff1}});
  }
  run.metrics()["curve"] = {{"view", first.name}, {"points", points}};
  DECIMA_RETURN_IF_ERROR(
      WriteCurvePicture(series, first.name, rendered.caption, run.OutputPath("curve.png")));
  run.AddArtifact("curve.png");
  report->push_back({"Mean colour difference against cells removed", run.OutputPath("curve.png"),
                     "The job simplified again to 10 %, 20 %, ... of the cells removed, each "
                     "rendered in the first view and compared with the original (the paper's "
                     "Fig. 5 for this job)."});
  stage.End();
  stage.Report(1, absl::StrCat(curve.size(), " points"));
  return absl::OkStatus();
}

// diff: segmentation.png, metrics.json and report.html. Not timed: its end is the job's total.
absl::Status DiffStage(const JobSpec& spec, const Volume& image, const SegmentResult& seg,
                       const RegionTable& regions, const Rendered& rendered,
                       const std::optional<DicomDescription>& dicom, JobRun& run,
                       std::vector<ReportPicture> report) {
  DECIMA_ASSIGN_OR_RETURN(Stage stage, run.Stage("diff", JobRun::Timing::kNotRecorded));
  // segmentation.png: what a clinician checks first, the labels over the slices.
  if (Wants(spec, "segmentation") || Wants(spec, "report")) {
    stage.Report(0.2, "segmentation.png");
    const bool artifact = Wants(spec, "segmentation");
    const std::filesystem::path path =
        artifact ? run.OutputPath("segmentation.png") : run.ScratchPath("segmentation.png");
    DECIMA_RETURN_IF_ERROR(
        WriteSegmentationPicture(image, seg.labels, regions, rendered.caption, path));
    if (artifact) run.AddArtifact("segmentation.png");
    report.insert(report.begin(),
                  ReportPicture{"Segmentation", path,
                                "The regions over the axial, coronal and sagittal slices through "
                                "the centre of the scan, with their names and colours below."});
  }
  stage.Report(0.5, "metrics.json");
  // The pictures and metrics.json so far count as the "diff" stage; report.html adds little.
  stage.End();
  DECIMA_RETURN_IF_ERROR(run.WriteMetrics());
  if (Wants(spec, "report")) {
    stage.Report(0.7, "report.html");
    ReportContext context;
    context.regions = &regions;
    context.view_surfaces = &rendered.view_surfaces;
    context.view_surfaces_extracted = rendered.view_surfaces_extracted;
    context.dicom = dicom;
    DECIMA_ASSIGN_OR_RETURN(const std::string html, ReportHtml(spec, rendered.caption.input_name,
                                                               run.metrics(), report, context));
    DECIMA_RETURN_IF_ERROR(WriteText(run.OutputPath("report.html"), html));
    run.AddArtifact("report.html");
  }
  stage.Report(1, absl::StrCat("diff1 ", rendered.views[0].diff.diff1));
  return absl::OkStatus();
}

}  // namespace

int64_t StreamRecordBytes(int64_t voxels, double target_reduction) {
  // Per voxel, with k = 1 - R the kept share (5 k cells a voxel of 16 bytes each): the written
  // cells 80 k, the windows' carried cells up to ~75 k (slabs of 4), the survivors 8; the
  // stage's checkpoint 85 k (cells and regions) + 10 (vertex map, vertices). Measured at 80 %:
  // 63 B/voxel on checkpoint_test's phantom in slabs of 4, at least 35 on the CT head 128 in
  // slabs of 16 (its simplify.ckpt alone 24); this gives 66.
  const double kept = 1.0 - std::clamp(target_reduction, 0.0, 1.0);
  return int64_t(double(voxels) * (240.0 * kept + 18.0));
}

std::string StreamingRefusal(const JobSpec& spec) {
  if (spec.policy != SimplifyPolicy::kField) {
    return absl::StrCat("streamed simplification runs the field policy only; the policy is ",
                        SimplifyPolicyName(spec.policy));
  }
  if (spec.min_psnr || spec.levels_file || Wants(spec, "levels") || Wants(spec, "curve")) {
    return "streamed simplification makes one mesh at target_reduction: no PSNR floor, level "
           "record, 'levels' or 'curve' output with it";
  }
  if (!(spec.target_reduction > 0) || spec.error_tolerance > 0) {
    return "streamed simplification needs a target_reduction > 0 and no error_tolerance";
  }
  return "";
}

absl::Status ValidateJobSpec(const JobSpec& spec, std::string* field) {
  // Each value goes through its module's validator on otherwise default options, so the
  // failing one is known by name and the ranges exist once, in the module that owns them.
  auto check = [field](const char* name, const absl::Status& s) {
    if (!s.ok() && field != nullptr) *field = name;
    return s;
  };
  SegmentOptions so;
  so.regions = spec.regions;
  DECIMA_RETURN_IF_ERROR(check("regions", ValidateSegmentOptions(so)));
  so.class_means = spec.class_means;
  DECIMA_RETURN_IF_ERROR(check("class_means", ValidateSegmentOptions(so)));
  if (!spec.region_names.empty()) {
    int index = -1;
    if (absl::Status s = ValidateRegionNames(spec.region_names, spec.regions, &index); !s.ok()) {
      const std::string name =
          index < 0 ? "region_names" : absl::StrCat("region_names[", index, "]");
      if (field != nullptr) *field = name;
      return s;
    }
  }

  auto simplify = [&](const char* name, auto set) {
    SimplifyOptions o;
    o.policy = SimplifyPolicy::kPaper;
    set(o);
    return check(name, ValidateSimplifyOptions(o));
  };
  DECIMA_RETURN_IF_ERROR(simplify(
      "target_reduction", [&](SimplifyOptions& o) { o.target_reduction = spec.target_reduction; }));
  DECIMA_RETURN_IF_ERROR(simplify("policy", [&](SimplifyOptions& o) { o.policy = spec.policy; }));
  DECIMA_RETURN_IF_ERROR(
      simplify("interfaces", [&](SimplifyOptions& o) { o.interfaces = spec.interfaces; }));
  DECIMA_RETURN_IF_ERROR(simplify(
      "error_tolerance", [&](SimplifyOptions& o) { o.error_tolerance = spec.error_tolerance; }));
  DECIMA_RETURN_IF_ERROR(simplify(
      "weights.regional", [&](SimplifyOptions& o) { o.weights.regional = spec.weights.regional; }));
  DECIMA_RETURN_IF_ERROR(simplify(
      "weights.gradient", [&](SimplifyOptions& o) { o.weights.gradient = spec.weights.gradient; }));
  DECIMA_RETURN_IF_ERROR(
      simplify("weights.shape", [&](SimplifyOptions& o) { o.weights.shape = spec.weights.shape; }));
  DECIMA_RETURN_IF_ERROR(simplify(
      "weights.volume", [&](SimplifyOptions& o) { o.weights.volume = spec.weights.volume; }));
  DECIMA_RETURN_IF_ERROR(simplify("weights.neighbour", [&](SimplifyOptions& o) {
    o.weights.neighbour = spec.weights.neighbour;
  }));
  if (!(spec.record_levels_to > 0 && spec.record_levels_to <= 0.99)) {
    return check("record_levels_to", absl::InvalidArgumentError(absl::StrCat(
                                         spec.record_levels_to,
                                         ": expected a reduction in (0, 0.99] down to which "
                                         "the levels are recorded")));
  }

  if (spec.levels_file) {
    if (spec.policy != SimplifyPolicy::kField) {
      return check("policy", absl::InvalidArgumentError(absl::StrCat(
                                 SimplifyPolicyName(spec.policy),
                                 ": a level record is made by the field policy only")));
    }
    if (Wants(spec, "levels")) {
      return check("outputs", absl::InvalidArgumentError(
                                  "'levels': this job's mesh comes from a level record; it "
                                  "records none of its own"));
    }
    if (spec.min_psnr) {
      return check("min_psnr", absl::InvalidArgumentError(
                                   "a level job takes its level at target_reduction; a PSNR "
                                   "floor is searched by a job of its own"));
    }
    if (!(spec.target_reduction > 0)) {
      return check("target_reduction",
                   absl::InvalidArgumentError(absl::StrCat(
                       spec.target_reduction, ": a level is taken at a reduction in (0, 0.99]")));
    }
  }
  if (spec.min_psnr) {
    const double db = *spec.min_psnr;
    if (!(std::isfinite(db) && db > 0)) {
      return check("min_psnr", absl::InvalidArgumentError(absl::StrCat(
                                   db,
                                   ": expected a PSNR floor in dB, finite and > 0 (unset: "
                                   "no floor)")));
    }
    if (spec.policy != SimplifyPolicy::kField) {
      return check("min_psnr", absl::InvalidArgumentError(absl::StrCat(
                                   "needs the field policy, whose recorded levels the floor is "
                                   "searched in; the policy is ",
                                   SimplifyPolicyName(spec.policy))));
    }
  }

  if (spec.stream_slab_voxels != 0) {
    auto refuse = [&](const std::string& why) {
      return check("stream_slab_voxels",
                   absl::InvalidArgumentError(absl::StrCat(spec.stream_slab_voxels, ": ", why)));
    };
    if (spec.stream_slab_voxels < kMinStreamSlabVoxels) {
      return refuse(absl::StrCat("expected 0 (in memory) or at least ", kMinStreamSlabVoxels,
                                 " voxel layers per slab"));
    }
    if (std::string why = StreamingRefusal(spec); !why.empty()) return refuse(why);
  }

  if (spec.views.empty() || spec.views.size() > 16) {
    return check("views", absl::InvalidArgumentError(
                              absl::StrCat(spec.views.size(), " views, expected 1..16")));
  }
  for (const auto& v : spec.views) {
    if (auto parsed = ParseView(v); !parsed.ok()) return check("views", parsed.status());
  }
  if (spec.image_size < 16 || spec.image_size > 4096) {
    return check("image_size", absl::InvalidArgumentError(
                                   absl::StrCat(spec.image_size, " pixels, expected 16..4096")));
  }
  if (spec.outputs.size() > std::size(kOutputKinds)) {
    return check("outputs",
                 absl::InvalidArgumentError(absl::StrCat(spec.outputs.size(), " outputs, at most ",
                                                         std::size(kOutputKinds))));
  }
  for (size_t i = 0; i < spec.outputs.size(); ++i) {
    const std::string& o = spec.outputs[i];
    if (std::find_if(std::begin(kOutputKinds), std::end(kOutputKinds),
                     [&](const char* k) { return o == k; }) == std::end(kOutputKinds)) {
      return check("outputs", absl::InvalidArgumentError(
                                  absl::StrCat("'", o.substr(0, 32), "' is not an output (",
                                               absl::StrJoin(kOutputKinds, ", "), ")")));
    }
    if (std::find(spec.outputs.begin(), spec.outputs.begin() + i, o) != spec.outputs.begin() + i) {
      return check("outputs", absl::InvalidArgumentError(absl::StrCat("'", o, "' appears twice")));
    }
  }
  if (spec.vtu_compression_level < 0 || spec.vtu_compression_level > 9) {
    return check("vtu_compression_level",
                 absl::InvalidArgumentError(
                     absl::StrCat(spec.vtu_compression_level, ", expected 0 (uncompressed) .. 9")));
  }
  // The data range is unknown before load; any valid range tells a bad name or document apart.
  const ScalarRange probe{0, 1};
  const std::string& tf = spec.transfer_function;
  if (!tf.empty() && tf.front() == '{') {
    if (auto t = ParseTransferFunction(tf, probe, "transfer_function"); !t.ok()) {
      return check("transfer_function", t.status());
    }
  } else if (tf != "auto") {
    if (auto t = TransferFunctionPreset(tf, probe); !t.ok()) {
      return check("transfer_function", t.status());
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<JobResult> RunJob(const JobSpec& spec, const std::filesystem::path& out_dir,
                                 const ProgressFn& progress, const CancelToken* cancel,
                                 const CheckpointOptions& checkpoints) {
  DECIMA_RETURN_IF_ERROR(ValidateJobSpec(spec));
  JobRun run(out_dir, progress, cancel);
  DECIMA_RETURN_IF_ERROR(run.Open());
  const std::string segment_key = SegmentKey(spec, checkpoints.key);
  const std::string simplify_key = SimplifyKey(spec, segment_key);
  std::vector<ReportPicture> report;  // the pictures report.html shows, as they are made

  std::optional<DicomDescription> dicom;
  DECIMA_ASSIGN_OR_RETURN(const Volume image, LoadStage(spec, run, &dicom));
  // Not const: its distance arrays are freed after the tetra stage.
  DECIMA_ASSIGN_OR_RETURN(SegmentResult seg,
                          SegmentStage(spec, image, checkpoints, segment_key, run));
  DECIMA_ASSIGN_OR_RETURN(const RegionTable regions, RegionTableOf(spec, image, seg, run));
  // Not const: the simplify stage frees it when no later stage reads it (NeedsOriginalCells), else
  // the render stage when only the curve's does not.
  DECIMA_ASSIGN_OR_RETURN(TetMesh original, TetrahedralizeStage(spec, image, seg, run));
  // The interface distances (voxels and mm, 8 bytes per voxel) are read only by the tetra stage,
  // which copies the first into the mesh's vertices (its checkpoint is written already): freed
  // here, they no longer sit under the simplify and render peaks.
  std::vector<float>().swap(seg.interface_distance_voxels);
  std::vector<float>().swap(seg.interface_distance_mm);
  // Set when the simplify stage freed the original (no later stage reads it).
  std::optional<FeatureVertexCounts> features;
  DECIMA_ASSIGN_OR_RETURN(
      SimplifyResult simplified,
      SimplifyStage(spec, image, original, checkpoints, simplify_key, run, &features));
  DECIMA_ASSIGN_OR_RETURN(const int64_t mesh_bytes,
                          WriteStage(spec, original, simplified, regions, run));
  DECIMA_ASSIGN_OR_RETURN(
      const Rendered rendered,
      RenderStage(spec, image, seg, original, simplified, features, mesh_bytes, run, &report));
  if (Wants(spec, "curve")) {
    DECIMA_RETURN_IF_ERROR(CurveStage(spec, original, simplified, rendered, run, &report));
  }
  DECIMA_RETURN_IF_ERROR(
      DiffStage(spec, image, seg, regions, rendered, dicom, run, std::move(report)));
  JobResult result = run.TakeResult();
  result.regions = regions;
  return result;
}

}  // namespace decima::pipeline
