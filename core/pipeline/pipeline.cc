#include "core/pipeline/pipeline.h"

#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <limits>
#include <optional>
#include <sstream>
#include <utility>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/common/status.h"
#include "core/io/dicom.h"
#include "core/io/png.h"
#include "core/io/volume_io.h"
#include "core/mesh/mesh_io.h"
#include "core/mesh/region_surface.h"
#include "core/mesh/tetrahedralize.h"
#include "core/metrics/fidelity.h"
#include "core/metrics/fidelity_json.h"
#include "core/pipeline/checkpoint.h"
#include "core/pipeline/levels_output.h"
#include "core/render/annotate.h"
#include "core/render/camera.h"
#include "core/render/canvas.h"
#include "core/render/diff.h"
#include "core/render/plot.h"
#include "core/render/renderer.h"
#include "core/render/transfer_function.h"
#include "core/segment/montage.h"
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

// The preset a transfer-function spec resolves to, for captions ("ct", "mri-t1", "custom").
std::string ChosenPresetName(const std::string& tf, const Volume& image, const ScalarRange& range) {
  if (!tf.empty() && tf.front() == '{') return "custom";
  if (tf != "auto") return tf;
  const bool ct = image.modality == "CT" || (image.modality.empty() && range.max > 1500);
  return ct ? "ct" : "mri-t1";
}

// File-name part of a view: named views as they are, "30:20" / "30,20" as "az30_el20".
std::string ViewFileSuffix(const std::string& view) {
  const size_t sep = view.find_first_of(",:");
  std::string out = sep == std::string::npos
                        ? view
                        : absl::StrCat("az", view.substr(0, sep), "_el", view.substr(sep + 1));
  for (char& c : out) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_' && c != '-' && c != '.') c = '_';
  }
  return out;
}

std::string FormatPercent(double f) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f%%", 100 * f);
  return buf;
}

struct ReportPicture {
  std::string caption;
  std::filesystem::path path;
};

std::string Base64(const std::string& in) {
  static const char kAlphabet[] =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((in.size() + 2) / 3 * 4);
  size_t i = 0;
  for (; i + 2 < in.size(); i += 3) {
    const uint32_t v = (uint8_t(in[i]) << 16) | (uint8_t(in[i + 1]) << 8) | uint8_t(in[i + 2]);
    for (int k = 18; k >= 0; k -= 6) out.push_back(kAlphabet[(v >> k) & 63]);
  }
  if (i < in.size()) {
    uint32_t v = uint8_t(in[i]) << 16;
    if (i + 1 < in.size()) v |= uint8_t(in[i + 1]) << 8;
    out.push_back(kAlphabet[(v >> 18) & 63]);
    out.push_back(kAlphabet[(v >> 12) & 63]);
    out.push_back(i + 1 < in.size() ? kAlphabet[(v >> 6) & 63] : '=');
    out.push_back('=');
  }
  return out;
}

std::string Html(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      default:
        out.push_back(c);
    }
  }
  return out;
}

std::string JsonCell(const Json& v) {
  if (v.is_number_float()) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.6g", v.get<double>());
    return buf;
  }
  if (v.is_string()) return Html(v.get<std::string>());
  return Html(v.dump());
}

// Rows "key | value" of a JSON object (nested objects flattened with dots).
void JsonRows(const Json& j, const std::string& prefix, std::string* out) {
  for (auto it = j.begin(); it != j.end(); ++it) {
    const std::string key = prefix.empty() ? it.key() : absl::StrCat(prefix, ".", it.key());
    if (it->is_object()) {
      JsonRows(*it, key, out);
    } else {
      absl::StrAppend(out, "<tr><th>", Html(key), "</th><td>", JsonCell(*it), "</td></tr>\n");
    }
  }
}

// One point of the diff1 curve: a simplification of the original to `reduction`.
struct CurvePoint {
  double reduction = 0;
  int64_t cells_removed = 0;
  double diff1 = 0;
};

// The paper's Fig. 5 for one job: diff1 of the first view against the cells removed, from
// separate simplifications of the original (same options, targets 10 %, 20 %, ... below the
// job's achieved reduction), rendered with the job's camera and transfer function. The job's
// own point is added by the caller. Progress under its own stage, "curve".
absl::StatusOr<std::vector<CurvePoint>> DiffCurve(const TetMesh& original, SimplifyOptions options,
                                                  double job_reduction, const Camera& camera,
                                                  const TransferFunction& tf,
                                                  const RenderedImage& original_render,
                                                  const ProgressFn& progress,
                                                  const CancelToken* cancel) {
  std::vector<double> targets;
  for (int step = 1; step <= 9 && step * 0.1 < job_reduction - 0.05; ++step) {
    targets.push_back(step * 0.1);
  }
  std::vector<CurvePoint> points;
  for (size_t i = 0; i < targets.size(); ++i) {
    Report(progress, {"curve",
                      double(i) / (targets.size() + 1),
                      absl::StrCat("simplifying to ", FormatPercent(targets[i])),
                      {}});
    options.target_reduction = targets[i];
    options.error_tolerance = 0;
    options.record_levels_to = 0;  // a record would take each point's run down to the floor
    DECIMA_ASSIGN_OR_RETURN(const SimplifyResult s, Simplify(original, options, nullptr, cancel));
    DECIMA_ASSIGN_OR_RETURN(const RenderableMesh r, BuildRenderableMesh(s.mesh, {}, cancel));
    DECIMA_ASSIGN_OR_RETURN(const RenderedImage img, Render(r, camera, tf, {}, cancel));
    DECIMA_ASSIGN_OR_RETURN(const DiffResult d, Diff(original_render, img));
    points.push_back({s.achieved_reduction, s.input_cells - s.output_cells, d.diff1});
  }
  return points;
}

// report.html: one self-contained page (pictures inline as data: URIs, no script, no outside
// resource) that any browser opens from a mail attachment or a PACS note.
absl::StatusOr<std::string> ReportHtml(const JobSpec& spec, const std::string& input_name,
                                       const Json& metrics,
                                       const std::vector<ReportPicture>& pictures) {
  const std::string title =
      absl::StrCat("Decima report: ", input_name, spec.job_name.empty() ? "" : " (", spec.job_name,
                   spec.job_name.empty() ? "" : ")");
  std::string h = absl::StrCat(
      "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n"
      "<meta name=\"viewport\" content=\"width=device-width\">\n"
      "<link rel=\"icon\" href=\"data:,\">\n<title>",
      Html(title),
      "</title>\n<style>body{font-family:sans-serif;margin:2em;max-width:80em;color:#222}"
      "table{border-collapse:collapse;margin:0 0 1.5em}th,td{border:1px solid #ccc;padding:"
      ".2em .6em;text-align:left;font-size:.9em}th{background:#f3f3f3}img{max-width:100%;"
      "border:1px solid #888}figure{margin:0 0 1.5em}.warn{color:#a00;font-weight:bold}"
      "</style></head><body>\n<h1>",
      Html(title), "</h1>\n");
  const Json& simp = metrics["simplification"];
  const double achieved = simp["achieved_reduction"].get<double>();
  absl::StrAppend(&h, "<p>", FormatPercent(achieved), " of the ", simp["cells_before"].dump(),
                  " cells removed (target ", FormatPercent(spec.target_reduction), ", policy ",
                  Html(simp["policy"].get<std::string>()),
                  "); mean colour difference of the renders (diff1) ", JsonCell(metrics["diff1"]),
                  " on 0-442.</p>\n");
  if (!simp["reached_target"].get<bool>()) {
    absl::StrAppend(&h, "<p class=\"warn\">The reduction target was not reached: ",
                    Html(simp["stop_message"].get<std::string>()), "</p>\n");
  }
  h += "<h2>Pictures</h2>\n";
  for (const auto& pic : pictures) {
    std::ifstream in(pic.path, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    if (!in)
      return absl::InternalError(absl::StrCat(pic.path.string(), ": cannot read for the report"));
    absl::StrAppend(&h, "<figure><img alt=\"", Html(pic.caption), "\" src=\"data:image/png;base64,",
                    Base64(ss.str()), "\"><figcaption>", Html(pic.caption),
                    "</figcaption></figure>\n");
  }
  Json params;
  params["input"] = input_name;
  params["job"] = spec.job_name;
  params["regions"] = spec.regions;
  params["class_means"] = spec.class_means;
  params["label_map"] = spec.label_map.has_value();
  params["target_reduction"] = spec.target_reduction;
  params["policy"] = SimplifyPolicyName(spec.policy);
  params["error_tolerance"] = spec.error_tolerance;
  params["views"] = spec.views;
  params["image_size"] = spec.image_size;
  params["transfer_function"] =
      spec.transfer_function.size() > 80 ? "custom JSON" : spec.transfer_function;
  params["outputs"] = spec.outputs;
  params["vtu_compression_level"] = spec.vtu_compression_level;
  std::string rows;
  JsonRows(params, "", &rows);
  absl::StrAppend(&h, "<h2>Parameters</h2>\n<table>\n", rows, "</table>\n");
  for (const char* section : {"input", "segmentation", "simplification", "fidelity", "render"}) {
    if (!metrics.contains(section)) continue;
    rows.clear();
    JsonRows(metrics[section], "", &rows);
    absl::StrAppend(&h, "<h2>", section, "</h2>\n<table>\n", rows, "</table>\n");
  }
  rows.clear();
  JsonRows(metrics["seconds"], "", &rows);
  absl::StrAppend(&h, "<h2>Timings (seconds)</h2>\n<table>\n", rows, "</table>\n");
  h += "<p>Written by decima. Meanings of the metrics: core/metrics/README.md; diff1 and the "
       "colour difference: core/render/README.md.</p>\n</body></html>\n";
  return h;
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

// Peak resident memory of the process, in MiB: overall (getrusage, never reset) and per stage
// (the kernel's VmHWM, which writing "5" to /proc/self/clear_refs resets to the current RSS, so
// each stage's figure is the highest RSS reached during that stage). Where the reset is refused
// (not Linux, a restricted /proc), a stage's figure is the peak so far and `resettable` says so.
class PeakRss {
 public:
  PeakRss() { resettable_ = Reset(); }
  void EndStage(const std::string& stage) {
    const double mb = HighWaterMb();
    if (mb > 0) stages_[stage] = std::max(stages_.value(stage, 0.0), mb);
    if (resettable_) resettable_ = Reset();
  }
  Json ToJson() const { return stages_; }
  // The kernel keeps ru_maxrss and VmHWM slightly apart (they are sampled at different
  // moments): the larger of the process's figure and every stage's is the peak.
  double PeakMb() const {
    double peak = ProcessPeakMb();
    for (const auto& [stage, mb] : stages_.items()) peak = std::max(peak, mb.get<double>());
    return peak;
  }
  bool resettable() const { return resettable_; }
  static double ProcessPeakMb() {
    rusage ru{};
    if (getrusage(RUSAGE_SELF, &ru) != 0) return 0;
    return static_cast<double>(ru.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB on Linux
  }

 private:
  static bool Reset() {
    std::ofstream out("/proc/self/clear_refs");
    out << "5";
    out.flush();
    return out.good();
  }
  static double HighWaterMb() {
    std::ifstream in("/proc/self/status");
    std::string line;
    while (std::getline(in, line)) {
      if (line.rfind("VmHWM:", 0) == 0) return std::atof(line.c_str() + 6) / 1024.0;
    }
    return ProcessPeakMb();
  }
  Json stages_ = Json::object();
  bool resettable_ = false;
};

// The key of a stage's checkpoint: the caller's (the input) plus every spec parameter the
// stage's output depends on, so a checkpoint made for other parameters is never resumed.
std::string SegmentKey(const JobSpec& spec, const std::string& input_key) {
  return absl::StrCat(input_key, "|segment regions=", spec.regions,
                      " means=", absl::StrJoin(spec.class_means, ","),
                      " label_map=", spec.label_map ? spec.label_map->string() : "",
                      " series=", spec.series_instance_uid);
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

std::string SimplifyKey(const JobSpec& spec, const std::string& segment_key) {
  char buf[256];
  std::snprintf(buf, sizeof buf,
                "|simplify policy=%s target=%.17g tolerance=%.17g w=%.17g,%.17g,%.17g levels=%.17g",
                SimplifyPolicyName(spec.policy), spec.target_reduction, spec.error_tolerance,
                spec.weights.shape, spec.weights.volume, spec.weights.neighbour, LevelFloor(spec));
  return segment_key + buf;
}

// The stage's output from its checkpoint, or nothing (no checkpoints, none saved yet, or one
// that is damaged or of other inputs: reported, and the stage runs again).
template <typename T>
std::optional<T> Resume(const CheckpointOptions& c, const std::string& stage,
                        const std::string& key, absl::StatusOr<T> (*parse)(const std::string&),
                        const ProgressFn& progress) {
  if (c.dir.empty()) return std::nullopt;
  auto payload = ReadCheckpoint(c.dir / (stage + ".ckpt"), key);
  absl::StatusOr<T> value = payload.ok() ? parse(*payload) : absl::StatusOr<T>(payload.status());
  if (!value.ok()) {
    if (!absl::IsNotFound(value.status())) {
      Report(progress,
             {stage, 0, absl::StrCat("checkpoint ignored: ", value.status().message()), {}});
    }
    return std::nullopt;
  }
  Report(progress, {stage, 1, "resumed from checkpoint", {}});
  return std::move(*value);
}

void SaveCheckpoint(const CheckpointOptions& c, const std::string& stage, const std::string& key,
                    const std::string& payload, const ProgressFn& progress) {
  if (c.dir.empty()) return;
  if (absl::Status st = WriteCheckpoint(c.dir / (stage + ".ckpt"), key, payload); !st.ok()) {
    Report(progress, {stage, 1, absl::StrCat("checkpoint not saved: ", st.message()), {}});
    return;
  }
  if (c.on_saved) c.on_saved(stage);
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
  if (!(spec.record_levels_to > 0 && spec.record_levels_to <= 0.99)) {
    return check("record_levels_to", absl::InvalidArgumentError(absl::StrCat(
                                         spec.record_levels_to,
                                         ": expected a reduction in (0, 0.99] down to which "
                                         "the levels are recorded")));
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
  const auto job_start = Clock::now();
  PeakRss rss;
  Json resumed = Json::array();
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
  rss.EndStage("load");
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
  const std::string segment_key = SegmentKey(spec, checkpoints.key);
  if (auto saved = Resume(checkpoints, "segment", segment_key, &ParseSegmentResult, progress)) {
    seg = std::move(*saved);
    resumed.push_back("segment");
  } else {
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
    SaveCheckpoint(checkpoints, "segment", segment_key, SerializeSegmentResult(seg), progress);
  }
  timings["segment"] = Seconds(t);
  rss.EndStage("segment");
  metrics["segmentation"] = SegmentJson(seg, spec.label_map.has_value());
  if (std::find(spec.outputs.begin(), spec.outputs.end(), "labels") != spec.outputs.end()) {
    DECIMA_RETURN_IF_ERROR(io::WriteNifti(seg.labels, out_dir / "labels.nii.gz"));
    add_artifact("labels.nii.gz");
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));

  // tetra
  t = Clock::now();
  TetrahedralizeOptions to;
  to.labels = &seg.labels;
  to.interface_distance = seg.interface_distance_voxels.data();
  DECIMA_ASSIGN_OR_RETURN(const TetMesh original,
                          Tetrahedralize(image, to, Forward(progress, "tetra"), cancel));
  timings["tetra"] = Seconds(t);
  rss.EndStage("tetra");

  // simplify
  t = Clock::now();
  SimplifyOptions simplify_options;
  simplify_options.policy = spec.policy;
  simplify_options.target_reduction = spec.target_reduction;
  simplify_options.error_tolerance = spec.error_tolerance;
  simplify_options.weights = spec.weights;
  simplify_options.record_levels_to = LevelFloor(spec);
  const std::string simplify_key = SimplifyKey(spec, segment_key);
  SimplifyResult simplified;
  if (auto saved = Resume(checkpoints, "simplify", simplify_key, &ParseSimplifyResult, progress)) {
    simplified = std::move(*saved);
    resumed.push_back("simplify");
  } else {
    DECIMA_ASSIGN_OR_RETURN(
        simplified, Simplify(original, simplify_options, Forward(progress, "simplify"), cancel));
    SaveCheckpoint(checkpoints, "simplify", simplify_key, SerializeSimplifyResult(simplified),
                   progress);
  }
  timings["simplify"] = Seconds(t);
  rss.EndStage("simplify");
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

  // write: only the mesh formats the spec asks for
  t = Clock::now();
  const auto wants = [&](const char* kind) {
    return std::find(spec.outputs.begin(), spec.outputs.end(), kind) != spec.outputs.end();
  };
  struct MeshFile {
    const char* kind;
    const char* name;
  };
  std::vector<MeshFile> mesh_files;
  for (const MeshFile& f :
       {MeshFile{"vtu", "mesh.vtu"}, MeshFile{"msh", "mesh.msh"}, MeshFile{"medit", "mesh.mesh"}}) {
    if (wants(f.kind)) mesh_files.push_back(f);
  }
  int64_t mesh_bytes = 0;
  for (size_t i = 0; i < mesh_files.size(); ++i) {
    Report(progress, {"write", double(i) / mesh_files.size(), mesh_files[i].name, {}});
    const std::filesystem::path p = out_dir / mesh_files[i].name;
    if (std::string(mesh_files[i].kind) == "vtu") {
      VtuWriteOptions wo;
      wo.compress = spec.vtu_compression_level > 0;
      wo.level = std::max(1, spec.vtu_compression_level);
      DECIMA_RETURN_IF_ERROR(WriteVtu(simplified.mesh, p, wo));
    } else if (std::string(mesh_files[i].kind) == "msh") {
      DECIMA_RETURN_IF_ERROR(WriteGmsh(simplified.mesh, p));
    } else {
      DECIMA_RETURN_IF_ERROR(WriteMedit(simplified.mesh, p));
    }
    add_artifact(mesh_files[i].name);
    if (mesh_bytes == 0) mesh_bytes = static_cast<int64_t>(result.artifacts.back().size_bytes);
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "write"));
  }
  if (wants("stl") || wants("glb")) {
    Report(progress, {"write", 1, "region surfaces", {}});
    const std::vector<RegionSurface> surfaces = ExtractRegionSurfaces(simplified.mesh);
    std::vector<RegionStyle> styles;
    for (const RegionSurface& s : surfaces) styles.push_back(DefaultRegionStyle(s.region));
    for (size_t i = 0; i < surfaces.size() && wants("stl"); ++i) {
      const std::string name = absl::StrCat("surface-", styles[i].name, ".stl");
      DECIMA_RETURN_IF_ERROR(WriteStl(surfaces[i], styles[i].name, out_dir / name));
      add_artifact(name);
    }
    if (wants("glb")) {
      DECIMA_RETURN_IF_ERROR(WriteGlb(surfaces, styles, out_dir / "surfaces.glb"));
      add_artifact("surfaces.glb");
    }
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "write"));
  }
  DECIMA_ASSIGN_OR_RETURN(
      const LevelsOutput levels,
      WriteLevelsOutput(spec, simplify_options, original, &simplified, out_dir, cancel));
  if (levels.artifact) add_artifact(*levels.artifact);
  metrics["levels"] = LevelsJson(levels);
  timings["write"] = Seconds(t);
  rss.EndStage("write");
  Report(progress,
         {"write", 1, mesh_files.empty() ? "no mesh file asked for" : "mesh written", {}});

  // fidelity (part of the diff stage's numbers, measured before rendering so a render failure
  // still leaves the field metrics in the log)
  t = Clock::now();
  // Reported under "render" (the next stage): its seconds belong to the picture-and-numbers
  // part of the job, and a silent gap after "write 100%" looked like a hang.
  Report(progress, {"render", 0, "measuring fidelity", {}});
  FidelityOptions fo;
  fo.labels = &seg.labels;
  fo.original = &original;
  fo.vertex_map = &simplified.vertex_map;
  fo.mesh_bytes = mesh_bytes;
  DECIMA_ASSIGN_OR_RETURN(const FidelityMetrics fidelity,
                          MeasureFidelity(image, simplified.mesh, fo, cancel));
  metrics["fidelity"] = FidelityToJson(fidelity);
  timings["fidelity"] = Seconds(t);

  // render: every view is rendered and measured (diff1 is part of metrics.json); the pictures
  // are written when "images" or "report" is asked for.
  t = Clock::now();
  Report(progress, {"render", 0, "building renderable meshes", {}});
  DECIMA_ASSIGN_OR_RETURN(const RenderableMesh original_r,
                          BuildRenderableMesh(original, {}, cancel));
  DECIMA_ASSIGN_OR_RETURN(const RenderableMesh simplified_r,
                          BuildRenderableMesh(simplified.mesh, {}, cancel));
  DECIMA_ASSIGN_OR_RETURN(
      const TransferFunction tf,
      ChooseTransferFunction(spec.transfer_function, image, original_r.scalar_range));
  const std::string preset =
      ChosenPresetName(spec.transfer_function, image, original_r.scalar_range);
  ViewOptions vo;
  vo.width = vo.height = spec.image_size;
  struct ViewRenders {
    std::string name;
    Camera camera;
    RenderedImage a, b;
    DiffResult diff;
  };
  std::vector<ViewRenders> renders;
  const double steps = 2.0 * spec.views.size();
  for (size_t i = 0; i < spec.views.size(); ++i) {
    ViewRenders v;
    v.name = spec.views[i];
    DECIMA_ASSIGN_OR_RETURN(const ViewDirection view, ParseView(v.name));
    // Both renders use the original's bounds so the pictures align pixel by pixel.
    DECIMA_ASSIGN_OR_RETURN(v.camera, MakeViewCamera(view, original_r.bounds, vo));
    DECIMA_ASSIGN_OR_RETURN(v.a, Render(original_r, v.camera, tf, {}, cancel));
    Report(
        progress,
        {"render", (2.0 * i + 1) / (steps + 1), absl::StrCat(v.name, ": original rendered"), {}});
    DECIMA_ASSIGN_OR_RETURN(v.b, Render(simplified_r, v.camera, tf, {}, cancel));
    DECIMA_ASSIGN_OR_RETURN(v.diff, Diff(v.a, v.b));
    Report(progress, {"render",
                      (2.0 * i + 2) / (steps + 1),
                      absl::StrCat(v.name, ": simplified rendered"),
                      {{"diff1", v.diff.diff1}}});
    renders.push_back(std::move(v));
  }
  // One heat-map scale for every view of the job, stated on the pictures, so colours compare.
  double heat_top = 0;
  for (const auto& v : renders) heat_top = std::max(heat_top, v.diff.max_diff2);
  DiffImageOptions dio;
  dio.max_value = heat_top > 0 ? heat_top : 1;
  const std::string input_name =
      spec.input_name.empty() ? spec.input.filename().string() : spec.input_name;
  const bool write_pictures = wants("images") || wants("report");
  Json views = Json::array();
  std::vector<ReportPicture> pictures;
  for (size_t i = 0; i < renders.size(); ++i) {
    const ViewRenders& v = renders[i];
    const std::string suffix = i == 0 ? "" : absl::StrCat("-", ViewFileSuffix(v.name));
    views.push_back({{"view", v.name},
                     {"diff1", v.diff.diff1},
                     {"max_diff2", v.diff.max_diff2},
                     {"changed_pixels", v.diff.changed_pixels}});
    if (!write_pictures) continue;
    const std::vector<std::string> footer = {
        absl::StrCat("INPUT ", input_name, spec.job_name.empty() ? "" : "  JOB ", spec.job_name),
        absl::StrCat("K ", seg.class_means.size(), "  REDUCTION ",
                     FormatPercent(simplified.achieved_reduction), " OF ",
                     FormatPercent(spec.target_reduction), "  POLICY ",
                     SimplifyPolicyName(spec.policy), "  PRESET ", preset, "  VIEW ", v.name)};
    const std::vector<std::pair<std::string, std::string>> text = {
        {"Software", "decima"},
        {"Source", input_name},
        {"decima:job", spec.job_name},
        {"decima:view", v.name},
        {"decima:regions", absl::StrCat(seg.class_means.size())},
        {"decima:target_reduction", absl::StrCat(spec.target_reduction)},
        {"decima:achieved_reduction", absl::StrCat(simplified.achieved_reduction)},
        {"decima:policy", std::string(SimplifyPolicyName(spec.policy))},
        {"decima:transfer_function", preset},
        {"decima:diff1", absl::StrCat(v.diff.diff1)},
        {"decima:heat_scale_max", absl::StrCat(dio.max_value)}};
    const std::string names[4] = {
        absl::StrCat("original", suffix, ".png"), absl::StrCat("simplified", suffix, ".png"),
        absl::StrCat("diff", suffix, ".png"), absl::StrCat("comparison", suffix, ".png")};
    std::vector<std::string> fo_orig = footer, fo_simp = footer, fo_diff = footer;
    fo_orig.insert(fo_orig.begin(), "ORIGINAL MESH");
    fo_simp.insert(fo_simp.begin(), "SIMPLIFIED MESH");
    fo_diff.insert(fo_diff.begin(),
                   absl::StrCat("COLOUR DIFFERENCE PER PIXEL (RGB DISTANCE 0-442), SCALE 0-",
                                FormatNumber(dio.max_value), " FOR ALL VIEWS OF THIS JOB"));
    DECIMA_RETURN_IF_ERROR(
        WritePng(out_dir / names[0], AnnotateRender(v.a.ToImage(), v.camera, fo_orig), text));
    DECIMA_RETURN_IF_ERROR(
        WritePng(out_dir / names[1], AnnotateRender(v.b.ToImage(), v.camera, fo_simp), text));
    DECIMA_RETURN_IF_ERROR(
        WritePng(out_dir / names[2], AddFooter(DiffHeatMap(v.diff, dio), fo_diff), text));
    DECIMA_ASSIGN_OR_RETURN(const Image comparison, ComparisonImage(v.a, v.b, v.diff, dio));
    DECIMA_RETURN_IF_ERROR(WritePng(out_dir / names[3], AddFooter(comparison, footer), text));
    if (wants("images")) {
      for (const auto& n : names) add_artifact(n);
    }
    pictures.push_back(
        {absl::StrCat("View ", v.name, ": original, simplified, difference"), out_dir / names[3]});
  }
  timings["render"] = Seconds(t);
  rss.EndStage("render");
  metrics["render"] = {{"size", spec.image_size},
                       {"transfer_function", spec.transfer_function},
                       {"preset", preset},
                       {"heat_scale_max", dio.max_value},
                       {"views", views}};
  metrics["diff1"] = views[0]["diff1"];
  metrics["outputs"] = spec.outputs;

  if (wants("curve")) {
    t = Clock::now();
    DECIMA_ASSIGN_OR_RETURN(std::vector<CurvePoint> curve,
                            DiffCurve(original, simplify_options, simplified.achieved_reduction,
                                      renders[0].camera, tf, renders[0].a, progress, cancel));
    curve.push_back({simplified.achieved_reduction,
                     simplified.input_cells - simplified.output_cells, renders[0].diff.diff1});
    PlotSeries series{absl::StrCat(SimplifyPolicyName(spec.policy), " policy"), {}};
    Json points = Json::array();
    for (const CurvePoint& c : curve) {
      series.points.push_back({double(c.cells_removed), c.diff1});
      points.push_back(
          {{"reduction", c.reduction}, {"cells_removed", c.cells_removed}, {"diff1", c.diff1}});
    }
    metrics["curve"] = {{"view", renders[0].name}, {"points", points}};
    PlotOptions po;
    po.title = absl::StrCat("diff1 vs cells removed, view ", renders[0].name);
    po.y_label = "diff1 (RGB distance 0-442)";
    DECIMA_ASSIGN_OR_RETURN(const Image plot, DiffPlotImage({series}, po));
    DECIMA_RETURN_IF_ERROR(WritePng(
        out_dir / "curve.png",
        AddFooter(plot,
                  {absl::StrCat("INPUT ", input_name, "  POLICY ", SimplifyPolicyName(spec.policy),
                                "  VIEW ", renders[0].name)}),
        {{"Software", "decima"}, {"Source", input_name}, {"decima:job", spec.job_name}}));
    add_artifact("curve.png");
    pictures.push_back(
        {"diff1 against cells removed (the paper's Fig. 5 for this job)", out_dir / "curve.png"});
    timings["curve"] = Seconds(t);
    rss.EndStage("curve");
    Report(progress, {"curve", 1, absl::StrCat(curve.size(), " points"), {}});
  }

  // segmentation.png: what a clinician checks first, the labels over the slices.
  if (wants("segmentation") || wants("report")) {
    Report(progress, {"diff", 0.2, "segmentation.png", {}});
    const std::filesystem::path seg_png = out_dir / "segmentation.png";
    DECIMA_RETURN_IF_ERROR(WriteSegmentationMontage(image, seg.labels, seg_png));
    DECIMA_ASSIGN_OR_RETURN(Image montage, ReadPng(seg_png));
    DECIMA_RETURN_IF_ERROR(WritePng(
        seg_png,
        AddFooter(montage, {"SEGMENTATION: AXIAL | CORONAL | SAGITTAL THROUGH THE CENTRE",
                            absl::StrCat("INPUT ", input_name, "  K ", seg.class_means.size(),
                                         spec.label_map ? "  FROM LABEL MAP" : "  LEVEL SET")}),
        {{"Software", "decima"},
         {"Source", input_name},
         {"decima:job", spec.job_name},
         {"decima:regions", absl::StrCat(seg.class_means.size())}}));
    if (wants("segmentation")) add_artifact("segmentation.png");
    pictures.insert(pictures.begin(), ReportPicture{"Segmentation", seg_png});
  }

  // diff: the summary file and the report page
  Report(progress, {"diff", 0.5, "metrics.json", {}});
  result.seconds = Seconds(job_start);
  timings["total"] = result.seconds;
  metrics["seconds"] = timings;
  // The pictures and metrics.json so far count as the "diff" stage; report.html adds little.
  rss.EndStage("diff");
  metrics["peak_rss_mb"] = rss.PeakMb();
  metrics["stage_peak_rss_mb"] = rss.ToJson();
  metrics["stage_peak_rss_per_stage"] = rss.resettable();
  metrics["resumed_stages"] = resumed;
  result.metrics_json = metrics.dump(2);
  DECIMA_RETURN_IF_ERROR(WriteText(out_dir / "metrics.json", result.metrics_json));
  add_artifact("metrics.json");
  if (wants("report")) {
    DECIMA_ASSIGN_OR_RETURN(const std::string html,
                            ReportHtml(spec, input_name, metrics, pictures));
    DECIMA_RETURN_IF_ERROR(WriteText(out_dir / "report.html", html));
    add_artifact("report.html");
  }
  // Pictures written only for the report are not artifacts: remove them.
  std::vector<std::filesystem::path> keep;
  for (const auto& a : result.artifacts) keep.push_back(a.path);
  for (const auto& pic : pictures) {
    if (std::find(keep.begin(), keep.end(), pic.path) == keep.end()) {
      std::filesystem::remove(pic.path, ec);
    }
  }
  if (write_pictures && !wants("images")) {
    for (size_t i = 0; i < renders.size(); ++i) {
      const std::string suffix = i == 0 ? "" : absl::StrCat("-", ViewFileSuffix(renders[i].name));
      for (const char* base : {"original", "simplified", "diff", "comparison"}) {
        std::filesystem::remove(out_dir / absl::StrCat(base, suffix, ".png"), ec);
      }
    }
  }
  Report(progress, {"diff", 1, absl::StrCat("diff1 ", views[0]["diff1"].get<double>()), {}});
  return result;
}

}  // namespace decima::pipeline
