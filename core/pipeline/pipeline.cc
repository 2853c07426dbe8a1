#include "core/pipeline/pipeline.h"

#include <chrono>
#include <cmath>
#include <fstream>
#include <limits>
#include <utility>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "core/common/status.h"
#include "core/io/dicom.h"
#include "core/io/volume_io.h"
#include "core/mesh/mesh_io.h"
#include "core/mesh/tetrahedralize.h"
#include "core/metrics/fidelity.h"
#include "core/metrics/fidelity_json.h"
#include "core/render/camera.h"
#include "core/render/diff.h"
#include "core/render/renderer.h"
#include "core/render/transfer_function.h"
#include "core/segment/segment.h"
#include "core/simplify/simplify.h"

namespace decima::pipeline {
namespace {

using Json = nlohmann::ordered_json;
using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// Forwards a core module's progress under the pipeline's stage name.
ProgressFn Forward(const ProgressFn& progress, const char* stage) {
  if (!progress) return nullptr;
  return [progress, stage](const Progress& p) {
    Progress q = p;
    q.stage = stage;
    progress(q);
  };
}

absl::StatusOr<Volume> LoadInput(const JobSpec& spec) {
  std::error_code ec;
  if (std::filesystem::is_directory(spec.input, ec)) {
    return ReadDicomSeries(spec.input, spec.series_instance_uid);
  }
  return io::ReadVolume(spec.input);
}

// Transfer function: a preset name, "auto" (CT preset for CT or HU-like ranges, MRI T1 otherwise),
// or a JSON document.
absl::StatusOr<TransferFunction> ChooseTransferFunction(const std::string& tf, const Volume& image,
                                                        const ScalarRange& range) {
  if (!tf.empty() && tf.front() == '{')
    return ParseTransferFunction(tf, range, "transfer_function");
  if (tf != "auto") return TransferFunctionPreset(tf, range);
  const bool ct = image.modality == "CT" || (image.modality.empty() && range.max > 1500);
  return TransferFunctionPreset(ct ? "ct" : "mri-t1", range);
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

}  // namespace

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

  auto simplify = [&](const char* name, auto set) {
    SimplifyOptions o;
    o.policy = SimplifyPolicy::kPaper;
    set(o);
    return check(name, ValidateSimplifyOptions(o));
  };
  DECIMA_RETURN_IF_ERROR(simplify(
      "target_reduction", [&](SimplifyOptions& o) { o.target_reduction = spec.target_reduction; }));
  DECIMA_RETURN_IF_ERROR(simplify("policy", [&](SimplifyOptions& o) { o.policy = spec.policy; }));
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
                                 const ProgressFn& progress, const CancelToken* cancel) {
  const auto job_start = Clock::now();
  DECIMA_RETURN_IF_ERROR(ValidateJobSpec(spec));
  std::error_code ec;
  std::filesystem::create_directories(out_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat(out_dir.string(), ": ", ec.message()));

  Json metrics;
  Json timings;
  JobResult result;
  auto add_artifact = [&](const std::string& name) {
    const std::filesystem::path p = out_dir / name;
    std::error_code size_ec;
    result.artifacts.push_back({name, p, std::filesystem::file_size(p, size_ec)});
  };

  // load
  auto t = Clock::now();
  Report(progress, {"load", 0, spec.input.string(), {}});
  DECIMA_ASSIGN_OR_RETURN(const Volume image, LoadInput(spec));
  timings["load"] = Seconds(t);
  metrics["input"] = {{"dims", image.dims},
                      {"spacing_mm", {image.spacing[0], image.spacing[1], image.spacing[2]}},
                      {"type", std::string(VoxelTypeName(image.type))},
                      {"modality", image.modality},
                      {"voxels", image.voxel_count()}};
  Report(progress, {"load", 1, Describe(image), {}});
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "load"));

  // segment
  t = Clock::now();
  SegmentResult seg;
  if (spec.label_map) {
    Report(progress, {"segment", 0, absl::StrCat("label map ", spec.label_map->string()), {}});
    DECIMA_ASSIGN_OR_RETURN(const Volume label_map, io::ReadVolume(*spec.label_map));
    DECIMA_ASSIGN_OR_RETURN(seg, SegmentationFromLabelMap(image, label_map));
  } else {
    SegmentOptions so;
    so.regions = spec.regions;
    so.class_means = spec.class_means;
    DECIMA_ASSIGN_OR_RETURN(seg, Segment(image, so, Forward(progress, "segment"), cancel));
  }
  timings["segment"] = Seconds(t);
  metrics["segmentation"] = SegmentJson(seg, spec.label_map.has_value());
  DECIMA_RETURN_IF_ERROR(io::WriteNifti(seg.labels, out_dir / "labels.nii.gz"));
  add_artifact("labels.nii.gz");
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));

  // tetra
  t = Clock::now();
  TetrahedralizeOptions to;
  to.labels = &seg.labels;
  to.interface_distance = seg.interface_distance_voxels.data();
  DECIMA_ASSIGN_OR_RETURN(const TetMesh original,
                          Tetrahedralize(image, to, Forward(progress, "tetra"), cancel));
  timings["tetra"] = Seconds(t);

  // simplify
  t = Clock::now();
  SimplifyOptions simplify_options;
  simplify_options.policy = spec.policy;
  simplify_options.target_reduction = spec.target_reduction;
  simplify_options.error_tolerance = spec.error_tolerance;
  simplify_options.weights = spec.weights;
  DECIMA_ASSIGN_OR_RETURN(
      SimplifyResult simplified,
      Simplify(original, simplify_options, Forward(progress, "simplify"), cancel));
  timings["simplify"] = Seconds(t);
  metrics["simplification"] = {{"policy", SimplifyPolicyName(spec.policy)},
                               {"target_reduction", spec.target_reduction},
                               {"achieved_reduction", simplified.achieved_reduction},
                               {"reached_target", simplified.reached_target},
                               {"stop_reason", StopReasonName(simplified.stop_reason)},
                               {"stop_message", simplified.stop_message},
                               {"passes", simplified.passes},
                               {"cells_before", simplified.input_cells},
                               {"cells_after", simplified.output_cells},
                               {"vertices_before", original.vertex_count()},
                               {"vertices_after", simplified.mesh.vertex_count()}};

  // write
  t = Clock::now();
  Report(progress, {"write", 0, "mesh.vtu, mesh.msh", {}});
  DECIMA_RETURN_IF_ERROR(WriteVtu(simplified.mesh, out_dir / "mesh.vtu"));
  add_artifact("mesh.vtu");
  DECIMA_RETURN_IF_ERROR(WriteGmsh(simplified.mesh, out_dir / "mesh.msh"));
  add_artifact("mesh.msh");
  timings["write"] = Seconds(t);
  Report(progress, {"write", 1, "mesh written", {}});
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "write"));

  // fidelity (part of the diff stage's numbers, measured before rendering so a render failure
  // still leaves the field metrics in the log)
  t = Clock::now();
  FidelityOptions fo;
  fo.labels = &seg.labels;
  fo.original = &original;
  fo.vertex_map = &simplified.vertex_map;
  fo.mesh_bytes = static_cast<int64_t>(result.artifacts[1].size_bytes);
  DECIMA_ASSIGN_OR_RETURN(const FidelityMetrics fidelity,
                          MeasureFidelity(image, simplified.mesh, fo, cancel));
  metrics["fidelity"] = FidelityToJson(fidelity);
  timings["fidelity"] = Seconds(t);

  // render
  t = Clock::now();
  Report(progress, {"render", 0, "building renderable meshes", {}});
  DECIMA_ASSIGN_OR_RETURN(const RenderableMesh original_r,
                          BuildRenderableMesh(original, {}, cancel));
  DECIMA_ASSIGN_OR_RETURN(const RenderableMesh simplified_r,
                          BuildRenderableMesh(simplified.mesh, {}, cancel));
  DECIMA_ASSIGN_OR_RETURN(
      const TransferFunction tf,
      ChooseTransferFunction(spec.transfer_function, image, original_r.scalar_range));
  ViewOptions vo;
  vo.width = vo.height = spec.image_size;
  Json views = Json::array();
  for (size_t i = 0; i < spec.views.size(); ++i) {
    const std::string& view_name = spec.views[i];
    DECIMA_ASSIGN_OR_RETURN(const ViewDirection view, ParseView(view_name));
    // Both renders use the original's bounds so the pictures align pixel by pixel.
    DECIMA_ASSIGN_OR_RETURN(const Camera camera, MakeViewCamera(view, original_r.bounds, vo));
    DECIMA_ASSIGN_OR_RETURN(const RenderedImage a, Render(original_r, camera, tf, {}, cancel));
    DECIMA_ASSIGN_OR_RETURN(const RenderedImage b, Render(simplified_r, camera, tf, {}, cancel));
    DECIMA_ASSIGN_OR_RETURN(const DiffResult diff, Diff(a, b));
    // The first view gets the plain names the API documents; further views a suffix.
    const std::string suffix = i == 0 ? "" : absl::StrCat("-", view_name);
    const std::string names[4] = {
        absl::StrCat("original", suffix, ".png"), absl::StrCat("simplified", suffix, ".png"),
        absl::StrCat("diff", suffix, ".png"), absl::StrCat("comparison", suffix, ".png")};
    DECIMA_RETURN_IF_ERROR(WriteRenderedPng(a, out_dir / names[0]));
    DECIMA_RETURN_IF_ERROR(WriteRenderedPng(b, out_dir / names[1]));
    DECIMA_RETURN_IF_ERROR(WriteDiffImage(diff, out_dir / names[2]));
    DECIMA_RETURN_IF_ERROR(WriteComparison(a, b, diff, out_dir / names[3]));
    for (const auto& n : names) add_artifact(n);
    views.push_back({{"view", view_name},
                     {"diff1", diff.diff1},
                     {"max_diff2", diff.max_diff2},
                     {"changed_pixels", diff.changed_pixels}});
    Report(progress,
           {"render", double(i + 1) / spec.views.size(), view_name, {{"diff1", diff.diff1}}});
  }
  timings["render"] = Seconds(t);
  metrics["render"] = {
      {"size", spec.image_size}, {"transfer_function", spec.transfer_function}, {"views", views}};
  metrics["diff1"] = views[0]["diff1"];

  // diff: the summary file
  Report(progress, {"diff", 0, "metrics.json", {}});
  result.seconds = Seconds(job_start);
  timings["total"] = result.seconds;
  metrics["seconds"] = timings;
  result.metrics_json = metrics.dump(2);
  DECIMA_RETURN_IF_ERROR(WriteText(out_dir / "metrics.json", result.metrics_json));
  add_artifact("metrics.json");
  Report(progress, {"diff", 1, absl::StrCat("diff1 ", views[0]["diff1"].get<double>()), {}});
  return result;
}

}  // namespace decima::pipeline
