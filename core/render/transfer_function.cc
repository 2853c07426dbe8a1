#include "core/render/transfer_function.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"

namespace decima {

void TransferFunction::Evaluate(double s, float rgb[3], float* opacity) const {
  const auto& p = points;
  if (s <= p.front().value || p.size() == 1) {
    const TransferPoint& q = s <= p.front().value ? p.front() : p.back();
    std::copy_n(q.rgb.begin(), 3, rgb);
    *opacity = q.opacity;
    return;
  }
  if (s >= p.back().value) {
    std::copy_n(p.back().rgb.begin(), 3, rgb);
    *opacity = p.back().opacity;
    return;
  }
  // First point with value > s; s lies in [hi - 1, hi).
  const size_t hi = std::upper_bound(p.begin(), p.end(), s,
                                     [](double v, const TransferPoint& q) { return v < q.value; }) -
                    p.begin();
  const TransferPoint& a = p[hi - 1];
  const TransferPoint& b = p[hi];
  const float f = static_cast<float>((s - a.value) / (b.value - a.value));
  for (int c = 0; c < 3; ++c) rgb[c] = a.rgb[c] + f * (b.rgb[c] - a.rgb[c]);
  *opacity = a.opacity + f * (b.opacity - a.opacity);
}

absl::Status TransferFunction::Validate() const {
  if (points.empty() || points.size() > 256) {
    return absl::InvalidArgumentError(absl::StrCat("transfer function '", name, "': has ",
                                                   points.size(), " points, expected 1..256"));
  }
  for (size_t i = 0; i < points.size(); ++i) {
    const TransferPoint& p = points[i];
    const std::string where = absl::StrCat("transfer function '", name, "': point ", i);
    if (!std::isfinite(p.value)) return absl::InvalidArgumentError(where + ": value not finite");
    if (i > 0 && !(p.value > points[i - 1].value)) {
      return absl::InvalidArgumentError(absl::StrCat(
          where, ": value ", p.value, " is not greater than the previous ", points[i - 1].value));
    }
    for (float c : p.rgb) {
      if (!(c >= 0 && c <= 1)) {
        return absl::InvalidArgumentError(where + ": rgb components must be in 0..1");
      }
    }
    if (!(p.opacity >= 0) || !std::isfinite(p.opacity)) {
      return absl::InvalidArgumentError(where + ": opacity must be finite and >= 0 (per mm)");
    }
  }
  return absl::OkStatus();
}

namespace {

// Shift for presets defined in Hounsfield units: data without air values is stored as HU + 1024.
double HuOffset(const ScalarRange& r) { return r.min > -500 ? 1024.0 : 0.0; }

TransferFunction Shifted(std::string name, std::vector<TransferPoint> pts, double offset) {
  for (auto& p : pts) p.value += offset;
  return {std::move(name), std::move(pts)};
}

}  // namespace

absl::StatusOr<TransferFunction> TransferFunctionPreset(absl::string_view name,
                                                        const ScalarRange& data_range) {
  const std::string n = absl::AsciiStrToLower(name);
  if (n == "ct") {
    // HU: air transparent; skin and fat (-250..-50) faint orange so the face's outline shows;
    // soft tissue and brain faint red; bone from ~250 HU ivory with an extinction that keeps
    // growing with density, so thin bone (orbits, sinus walls) stays translucent and thick
    // bone (teeth, skull base) reads brighter - without shading this is what shows shape.
    return Shifted("ct",
                   {{-1024, {0, 0, 0}, 0},
                    {-500, {0.85f, 0.60f, 0.50f}, 0},
                    {-250, {0.90f, 0.62f, 0.50f}, 0.030f},
                    {-50, {0.85f, 0.50f, 0.42f}, 0.015f},
                    {100, {0.75f, 0.35f, 0.30f}, 0.006f},
                    {250, {0.90f, 0.85f, 0.75f}, 0.030f},
                    {600, {1.00f, 0.97f, 0.90f}, 0.12f},
                    {2000, {1.00f, 1.00f, 1.00f}, 0.30f}},
                   HuOffset(data_range));
  }
  if (n == "ct-bone") {
    return Shifted(
        "ct-bone",
        {{150, {0.9f, 0.8f, 0.7f}, 0}, {400, {1.0f, 0.96f, 0.88f}, 0.5f}, {2000, {1, 1, 1}, 1.0f}},
        HuOffset(data_range));
  }
  if (n == "mri-t1") {
    if (!std::isfinite(data_range.min) || !std::isfinite(data_range.max) ||
        !(data_range.max > data_range.min)) {
      return absl::InvalidArgumentError(absl::StrCat("transfer function 'mri-t1': data range [",
                                                     data_range.min, ", ", data_range.max,
                                                     "] is empty or not finite"));
    }
    const double lo = data_range.min, span = data_range.max - data_range.min;
    std::vector<TransferPoint> pts = {{0.00, {0, 0, 0}, 0},
                                      {0.10, {0.20f, 0.20f, 0.30f}, 0},
                                      {0.25, {0.35f, 0.35f, 0.45f}, 0.004f},
                                      {0.45, {0.75f, 0.60f, 0.55f}, 0.015f},
                                      {0.60, {0.95f, 0.90f, 0.85f}, 0.040f},
                                      {0.85, {1.00f, 1.00f, 0.80f}, 0.080f},
                                      {1.00, {1.00f, 1.00f, 0.85f}, 0.080f}};
    for (auto& p : pts) p.value = lo + p.value * span;
    return TransferFunction{"mri-t1", std::move(pts)};
  }
  return absl::InvalidArgumentError(absl::StrCat("transfer function preset '", name,
                                                 "' is unknown: expected ct, ct-bone or mri-t1"));
}

absl::StatusOr<TransferFunction> ParseTransferFunction(absl::string_view json,
                                                       const ScalarRange& data_range,
                                                       absl::string_view what) {
  using Json = nlohmann::json;
  const std::string w(what);
  Json doc = Json::parse(json.begin(), json.end(), /*cb=*/nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded()) {
    return absl::InvalidArgumentError(w + ": not valid JSON");
  }
  if (!doc.is_object()) return absl::InvalidArgumentError(w + ": expected a JSON object");
  TransferFunction tf;
  tf.name = "custom";
  if (doc.contains("name")) {
    if (!doc["name"].is_string())
      return absl::InvalidArgumentError(w + ": 'name' must be a string");
    tf.name = doc["name"].get<std::string>();
  }
  bool relative = false;
  if (doc.contains("domain")) {
    const Json& d = doc["domain"];
    if (!d.is_string() || (d != "absolute" && d != "relative")) {
      return absl::InvalidArgumentError(w + ": 'domain' must be \"absolute\" or \"relative\"");
    }
    relative = d == "relative";
  }
  if (!doc.contains("points")) return absl::InvalidArgumentError(w + ": missing key 'points'");
  const Json& pts = doc["points"];
  if (!pts.is_array()) return absl::InvalidArgumentError(w + ": 'points' must be an array");
  if (pts.empty() || pts.size() > 256) {
    return absl::InvalidArgumentError(
        absl::StrCat(w, ": 'points' has ", pts.size(), " entries, expected 1..256"));
  }
  if (relative && (!std::isfinite(data_range.min) || !std::isfinite(data_range.max) ||
                   !(data_range.max > data_range.min))) {
    return absl::InvalidArgumentError(w + ": relative domain needs a non-empty data range");
  }
  for (size_t i = 0; i < pts.size(); ++i) {
    const Json& p = pts[i];
    const std::string where = absl::StrCat(w, ": points[", i, "]");
    if (!p.is_object()) return absl::InvalidArgumentError(where + " must be an object");
    for (const char* key : {"value", "rgb", "opacity"}) {
      if (!p.contains(key)) {
        return absl::InvalidArgumentError(absl::StrCat(where, ": missing key '", key, "'"));
      }
    }
    if (!p["value"].is_number()) {
      return absl::InvalidArgumentError(where + ": 'value' must be a number");
    }
    if (!p["opacity"].is_number()) {
      return absl::InvalidArgumentError(where + ": 'opacity' must be a number (per mm)");
    }
    const Json& rgb = p["rgb"];
    if (!rgb.is_array() || rgb.size() != 3 || !rgb[0].is_number() || !rgb[1].is_number() ||
        !rgb[2].is_number()) {
      return absl::InvalidArgumentError(where + ": 'rgb' must be an array of 3 numbers in 0..1");
    }
    TransferPoint q;
    q.value = p["value"].get<double>();
    if (relative) q.value = data_range.min + q.value * (data_range.max - data_range.min);
    for (int c = 0; c < 3; ++c) q.rgb[c] = rgb[c].get<float>();
    q.opacity = p["opacity"].get<float>();
    tf.points.push_back(q);
  }
  absl::Status s = tf.Validate();
  if (!s.ok()) return absl::InvalidArgumentError(absl::StrCat(w, ": ", s.message()));
  return tf;
}

absl::StatusOr<TransferFunction> LoadTransferFunction(const std::filesystem::path& path,
                                                      const ScalarRange& data_range) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("transfer function ", path.string(), ": no such file"));
  }
  const auto size = std::filesystem::file_size(path, ec);
  if (ec || size > (1u << 20)) {
    return absl::InvalidArgumentError(
        absl::StrCat("transfer function ", path.string(), ": larger than 1 MiB or unreadable"));
  }
  std::ifstream in(path, std::ios::binary);
  std::stringstream text;
  text << in.rdbuf();
  if (!in) {
    return absl::InvalidArgumentError(
        absl::StrCat("transfer function ", path.string(), ": cannot read"));
  }
  return ParseTransferFunction(text.str(), data_range, path.string());
}

std::string TransferFunctionToJson(const TransferFunction& tf) {
  nlohmann::ordered_json doc;
  doc["name"] = tf.name;
  doc["domain"] = "absolute";
  doc["points"] = nlohmann::ordered_json::array();
  for (const TransferPoint& p : tf.points) {
    doc["points"].push_back(
        {{"value", p.value}, {"rgb", {p.rgb[0], p.rgb[1], p.rgb[2]}}, {"opacity", p.opacity}});
  }
  return doc.dump(2);
}

}  // namespace decima
