#include "server/jobs/job_spec.h"

#include <algorithm>
#include <cmath>
#include <filesystem>

#include <nlohmann/json.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/mesh/mesh_io.h"
#include "core/pipeline/levels_output.h"
#include "core/volume/regions.h"
#include "server/store/job_store.h"

namespace decima::server {
namespace {

constexpr int kMaxViews = 16;
constexpr size_t kMaxViewNameBytes = 64;
// A transfer function in JSON has at most 256 points (core/render); 64 KiB holds them with room.
constexpr size_t kMaxTransferFunctionBytes = 64 << 10;
constexpr int kMaxClassMeans = 8;
constexpr int kMaxOutputs = 16;

absl::Status Invalid(std::string* field, const std::string& name, const std::string& message) {
  if (field != nullptr) *field = name;
  return absl::InvalidArgumentError(absl::StrCat(name, ": ", message));
}

}  // namespace

v1::SimplifyPolicy PolicyToProto(SimplifyPolicy policy) {
  switch (policy) {
    case SimplifyPolicy::kPaper:
      return v1::PAPER;
    case SimplifyPolicy::kTetFusion:
      return v1::TETFUSION;
    case SimplifyPolicy::kField:
      return v1::FIELD;
  }
  return v1::SIMPLIFY_POLICY_UNSPECIFIED;
}

absl::StatusOr<pipeline::JobSpec> JobSpecFromProto(const v1::JobSpec& spec, std::string* field) {
  // Names only; whether the volumes exist is the store's answer (NOT_FOUND), asked by CreateJob.
  if (auto id = ParseName(spec.volume(), "volumes", "spec.volume"); !id.ok()) {
    if (field != nullptr) *field = "spec.volume";
    return id.status();
  }
  if (!spec.label_map().empty()) {
    if (auto id = ParseName(spec.label_map(), "volumes", "spec.label_map"); !id.ok()) {
      if (field != nullptr) *field = "spec.label_map";
      return id.status();
    }
  }
  pipeline::JobSpec p;
  if (!spec.levels_of().empty()) {
    if (auto id = ParseName(spec.levels_of(), "jobs", "spec.levels_of"); !id.ok()) {
      if (field != nullptr) *field = "spec.levels_of";
      return id.status();
    }
    // Stands for the record until the job runner resolves it, so the validator checks what a
    // level job may not ask for (another policy, a "levels" output of its own).
    p.levels_file = std::filesystem::path(spec.levels_of()) / "mesh.levels";
  }
  // Defaults: pipeline::JobSpec's member initializers are the documented ones; only fields the
  // client set override them.
  if (spec.has_regions()) p.regions = spec.regions();
  // Bounded before copying so a huge repeated field costs nothing; the count rule is core's.
  if (spec.class_means_size() > kMaxClassMeans) {
    return Invalid(field, "spec.class_means",
                   absl::StrCat(spec.class_means_size(), " values, at most one per region (",
                                kMaxClassMeans, ")"));
  }
  p.class_means.assign(spec.class_means().begin(), spec.class_means().end());
  // Bounded before copying, as class_means; each name's rule is core's (ValidateRegionNames).
  if (spec.region_names_size() > kMaxClassMeans) {
    return Invalid(field, "spec.region_names",
                   absl::StrCat(spec.region_names_size(), " names, at most one per region (",
                                kMaxClassMeans, ")"));
  }
  for (const auto& n : spec.region_names()) {
    if (n.size() > 4 * kMaxRegionNameBytes) {
      return Invalid(field, "spec.region_names", absl::StrCat("a name of ", n.size(), " bytes"));
    }
    p.region_names.push_back(n);
  }
  if (spec.has_target_reduction()) p.target_reduction = spec.target_reduction();
  switch (spec.policy()) {
    case v1::SIMPLIFY_POLICY_UNSPECIFIED:
      break;  // the default, pipeline::JobSpec::policy
    case v1::PAPER:
      p.policy = SimplifyPolicy::kPaper;
      break;
    case v1::TETFUSION:
      p.policy = SimplifyPolicy::kTetFusion;
      break;
    case v1::FIELD:
      p.policy = SimplifyPolicy::kField;
      break;
    default:
      // proto3 enums are open: an unknown number from a newer client arrives as is.
      return Invalid(field, "spec.policy",
                     absl::StrCat(static_cast<int>(spec.policy()),
                                  " is not a policy (PAPER, TETFUSION or FIELD)"));
  }
  if (spec.has_error_tolerance()) p.error_tolerance = spec.error_tolerance();
  if (!spec.interfaces().empty()) {
    const std::optional<InterfaceMode> mode = ParseInterfaceMode(spec.interfaces());
    if (!mode) {
      return Invalid(field, "spec.interfaces",
                     absl::StrCat("'", spec.interfaces().substr(0, 64),
                                  "' is not an interface mode (free or voxel-faces)"));
    }
    p.interfaces = *mode;
  }
  const v1::ErrorWeights& w = spec.weights();
  if (w.has_regional()) p.weights.regional = w.regional();
  if (w.has_gradient()) p.weights.gradient = w.gradient();
  if (w.has_shape()) p.weights.shape = w.shape();
  if (w.has_volume()) p.weights.volume = w.volume();
  if (w.has_neighbour()) p.weights.neighbour = w.neighbour();
  if (spec.views_size() > kMaxViews) {
    return Invalid(field, "spec.views",
                   absl::StrCat(spec.views_size(), " views, at most ", kMaxViews));
  }
  if (!spec.views().empty()) {
    p.views.clear();
    for (const auto& v : spec.views()) {
      if (v.size() > kMaxViewNameBytes) {
        return Invalid(field, "spec.views", absl::StrCat("a view name of ", v.size(), " bytes"));
      }
      p.views.push_back(v);
    }
  }
  if (spec.has_image_size()) p.image_size = spec.image_size();
  if (spec.transfer_function().size() > kMaxTransferFunctionBytes) {
    return Invalid(field, "spec.transfer_function",
                   absl::StrCat(spec.transfer_function().size(), " bytes, at most ",
                                kMaxTransferFunctionBytes));
  }
  if (!spec.transfer_function().empty()) p.transfer_function = spec.transfer_function();
  if (spec.outputs_size() > kMaxOutputs) {
    return Invalid(field, "spec.outputs",
                   absl::StrCat(spec.outputs_size(), " outputs, at most ", kMaxOutputs));
  }
  if (!spec.outputs().empty()) {
    // Case-insensitive names, stored lower case in the order RunJob writes them; duplicates and
    // unknown names are refused by ValidateJobSpec with the name.
    std::vector<std::string> asked;
    for (const auto& o : spec.outputs()) asked.push_back(absl::AsciiStrToLower(o.substr(0, 64)));
    p.outputs.clear();
    for (const char* kind : pipeline::kOutputKinds) {
      if (std::find(asked.begin(), asked.end(), kind) != asked.end()) p.outputs.push_back(kind);
    }
    for (const auto& o : asked) {
      if (std::find(p.outputs.begin(), p.outputs.end(), o) == p.outputs.end() ||
          std::count(asked.begin(), asked.end(), o) > 1) {
        p.outputs.push_back(o);  // unknown or repeated: let the validator name it
      }
    }
  }
  if (spec.has_vtu_compression_level()) p.vtu_compression_level = spec.vtu_compression_level();
  if (!spec.mesh_compression().empty()) {
    const std::optional<VtuCompressor> compressor = ParseVtuCompressor(spec.mesh_compression());
    if (!compressor) {
      return Invalid(field, "spec.mesh_compression",
                     absl::StrCat("'", spec.mesh_compression().substr(0, 64),
                                  "' is not a mesh compression (zlib or lzma)"));
    }
    p.mesh_compression = *compressor;
  }
  if (spec.has_min_psnr()) {
    p.min_psnr = spec.min_psnr();
    // A floor alone asks for "as far as the floor allows", not for the default 50 %.
    if (!spec.has_target_reduction()) p.target_reduction = 0;
  }

  if (spec.has_stream_slab_voxels()) p.stream_slab_voxels = spec.stream_slab_voxels();

  std::string bad;
  absl::Status st = pipeline::ValidateJobSpec(p, &bad);
  if (!st.ok()) return Invalid(field, absl::StrCat("spec.", bad), std::string(st.message()));
  return p;
}

absl::StatusOr<v1::JobSpec> NormalizeJobSpec(const v1::JobSpec& spec, std::string* field) {
  auto p = JobSpecFromProto(spec, field);
  if (!p.ok()) return p.status();
  v1::JobSpec out;
  out.set_volume(spec.volume());
  out.set_label_map(spec.label_map());
  out.set_regions(p->regions);
  for (double m : p->class_means) out.add_class_means(m);
  for (const auto& n : p->region_names) out.add_region_names(n);
  out.set_target_reduction(p->target_reduction);
  out.set_policy(PolicyToProto(p->policy));
  out.set_error_tolerance(p->error_tolerance);
  out.set_interfaces(InterfaceModeName(p->interfaces));
  v1::ErrorWeights* w = out.mutable_weights();
  w->set_regional(p->weights.regional);
  w->set_gradient(p->weights.gradient);
  w->set_shape(p->weights.shape);
  w->set_volume(p->weights.volume);
  w->set_neighbour(p->weights.neighbour);
  for (const auto& v : p->views) out.add_views(v);
  out.set_image_size(p->image_size);
  out.set_transfer_function(p->transfer_function);
  for (const auto& o : p->outputs) out.add_outputs(o);
  out.set_vtu_compression_level(p->vtu_compression_level);
  out.set_mesh_compression(VtuCompressorName(p->mesh_compression));
  if (p->min_psnr) out.set_min_psnr(*p->min_psnr);
  // Left unset for CreateJob to choose once it knows the volume (PlanJobMemory).
  if (spec.has_stream_slab_voxels()) out.set_stream_slab_voxels(p->stream_slab_voxels);
  out.set_levels_of(spec.levels_of());
  return out;
}

absl::StatusOr<v1::JobSpec> LevelJobSpec(const v1::JobSpec& spec, const v1::Job& parent,
                                         std::string* field) {
  const std::string& of = spec.levels_of();
  if (parent.state() != v1::SUCCEEDED) {
    if (field != nullptr) *field = "spec.levels_of";
    return absl::FailedPreconditionError(
        absl::StrCat("spec.levels_of: ", of, " is ", v1::JobState_Name(parent.state()),
                     "; a level is taken from the record of a job that succeeded"));
  }
  bool has_levels = false, has_labels = false;
  for (const auto& a : parent.artifacts()) {
    has_levels = has_levels || a.file_name() == pipeline::kLevelsFileName;
    has_labels = has_labels || a.file_name() == "labels.nii.gz";
  }
  if (!has_levels || !has_labels) {
    if (field != nullptr) *field = "spec.levels_of";
    return absl::FailedPreconditionError(absl::StrCat(
        "spec.levels_of: ", of, " kept no level record (", !has_levels ? "mesh.levels" : "",
        !has_levels && !has_labels ? " and " : "", !has_labels ? "labels.nii.gz" : "",
        "); submit the volume again with the \"levels\" output (decima submit --outputs "
        "vtu,levels ...), then take any level from that job"));
  }
  if (!spec.volume().empty() && spec.volume() != parent.spec().volume()) {
    return Invalid(field, "spec.volume",
                   absl::StrCat(spec.volume(), " is not the volume of ", of, " (",
                                parent.spec().volume(), "); leave it empty"));
  }
  if (!spec.label_map().empty()) {
    return Invalid(field, "spec.label_map",
                   absl::StrCat("a level job uses the segmentation of ", of, "; leave it empty"));
  }
  if (spec.has_regions() || spec.class_means_size() > 0) {
    return Invalid(field, spec.has_regions() ? "spec.regions" : "spec.class_means",
                   absl::StrCat("a level job uses the segmentation of ", of, "; leave it unset"));
  }
  if (spec.policy() != v1::SIMPLIFY_POLICY_UNSPECIFIED && spec.policy() != v1::FIELD) {
    return Invalid(field, "spec.policy", "a level record is made by the FIELD policy only");
  }
  // The range the parent recorded (metrics.json "levels", written with the record).
  const double target =
      spec.has_target_reduction() ? spec.target_reduction() : pipeline::JobSpec{}.target_reduction;
  const auto metrics = nlohmann::json::parse(parent.metrics_json(), nullptr, false);
  const auto levels = metrics.is_object() ? metrics.value("levels", nlohmann::json::object())
                                          : nlohmann::json::object();
  const double deepest = levels.value("deepest_reduction", 0.0);
  const bool exhausted = levels.value("exhausted", false);
  if (std::isfinite(target) && target > deepest && !exhausted) {
    return Invalid(
        field, "spec.target_reduction",
        absl::StrFormat("%g is outside the range %s recorded, (0, %.4f]", target, of, deepest));
  }
  v1::JobSpec out = spec;
  out.set_volume(parent.spec().volume());
  out.set_regions(parent.spec().regions());
  *out.mutable_class_means() = parent.spec().class_means();
  // The same regions under the same names, unless the caller names them anew.
  if (out.region_names().empty()) *out.mutable_region_names() = parent.spec().region_names();
  out.set_policy(v1::FIELD);
  return out;
}

}  // namespace decima::server
