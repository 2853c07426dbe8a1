#include "server/jobs/job_spec.h"

#include <algorithm>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
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
  if (spec.has_min_psnr()) {
    p.min_psnr = spec.min_psnr();
    // A floor alone asks for "as far as the floor allows", not for the default 50 %.
    if (!spec.has_target_reduction()) p.target_reduction = 0;
  }

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
  out.set_target_reduction(p->target_reduction);
  out.set_policy(PolicyToProto(p->policy));
  out.set_error_tolerance(p->error_tolerance);
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
  if (p->min_psnr) out.set_min_psnr(*p->min_psnr);
  return out;
}

}  // namespace decima::server
