#include "core/pipeline/report.h"

#include <cstdint>
#include <cstdio>
#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "core/pipeline/pictures.h"
#include "core/simplify/simplify.h"

namespace decima::pipeline {
namespace {

using Json = nlohmann::ordered_json;

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

}  // namespace

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
      "border:1px solid #888}.swatch{display:inline-block;width:1em;height:1em;"
      "vertical-align:middle;border:1px solid #444}figure{margin:0 0 "
      "1.5em}.warn{color:#a00;font-weight:bold}"
      "</style></head><body>\n<h1>",
      Html(title), "</h1>\n");
  const Json& simp = metrics["simplification"];
  const double achieved = simp["achieved_reduction"].get<double>();
  absl::StrAppend(&h, "<p>", FormatPercent(achieved), " of the ", simp["cells_before"].dump(),
                  " cells removed (target ", FormatPercent(spec.target_reduction), ", policy ",
                  Html(simp["policy"].get<std::string>()),
                  "); mean colour difference of the renders (diff1) ", JsonCell(metrics["diff1"]),
                  " on 0-442.</p>\n");
  if (simp["stop_reason"] == StopReasonName(StopReason::kPsnrFloor)) {
    // What the job asked for (JobSpec::min_psnr), not a missed target.
    absl::StrAppend(&h,
                    "<p>Stopped by the PSNR floor: ", Html(simp["stop_message"].get<std::string>()),
                    "</p>\n");
  } else if (!simp["reached_target"].get<bool>()) {
    absl::StrAppend(&h, "<p class=\"warn\">The reduction target was not reached: ",
                    Html(simp["stop_message"].get<std::string>()), "</p>\n");
  }
  // The regions: the names and colours every artifact of the job uses (metrics "regions").
  if (metrics.contains("regions") && metrics["regions"].is_array()) {
    h += "<h2>Regions</h2>\n<table>\n<tr><th>Colour</th><th>Label</th><th>Name</th><th>Voxels"
         "</th><th>Volume (mL)</th><th>Mean intensity</th><th>In the DICOM SEG as</th></tr>\n";
    for (const Json& r : metrics["regions"]) {
      const std::string colour = r.value("colour", std::string("#808080"));
      char ml[32] = "";
      if (r.contains("volume_mm3")) {
        std::snprintf(ml, sizeof ml, "%.1f", r["volume_mm3"].get<double>() / 1000);
      }
      absl::StrAppend(
          &h, "<tr class=\"region\"><td><span class=\"swatch\" style=\"background:", Html(colour),
          "\"></span> ", Html(colour), "</td><td>", r.value("label", 0), "</td><td>",
          Html(r.value("name", std::string())), "</td><td>", r.value("voxels", int64_t{0}),
          "</td><td>", ml, "</td><td>", JsonCell(r.value("mean", Json(0.0))), "</td><td>",
          r.value("dicom_seg", true) ? Html(r.value("dicom_type", std::string()))
                                     : std::string("left out (air)"),
          "</td></tr>\n");
    }
    h += "</table>\n";
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
  params["region_names"] = spec.region_names;
  params["label_map"] = spec.label_map.has_value();
  params["target_reduction"] = spec.target_reduction;
  params["policy"] = SimplifyPolicyName(spec.policy);
  if (spec.policy == SimplifyPolicy::kField)
    params["interfaces"] = InterfaceModeName(spec.interfaces);
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

}  // namespace decima::pipeline
