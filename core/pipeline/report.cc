#include "core/pipeline/report.h"

#include <zlib.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <limits>
#include <sstream>
#include <unordered_map>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_replace.h"
#include "core/mesh/mesh_io.h"
#include "core/pipeline/pictures.h"
#include "core/pipeline/report_viewer.h"
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
      case '\'':
        out += "&#39;";
        break;
      default:
        out.push_back(c);
    }
  }
  return out;
}

// JSON inside a <script> element: '<', '>' and '&' only occur in its strings, where \u escapes
// mean the same, so no "</script>" in a region name can end the element.
std::string ScriptJson(const Json& j) {
  return absl::StrReplaceAll(j.dump(-1, ' ', false, Json::error_handler_t::replace),
                             {{"<", "\\u003c"}, {">", "\\u003e"}, {"&", "\\u0026"}});
}

std::string Number(double v, int digits = 4) {
  if (!std::isfinite(v)) return "not finite";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*g", digits, v);
  return buf;
}

// 1234567 -> "1,234,567".
std::string Count(int64_t n) {
  std::string digits = std::to_string(n < 0 ? -n : n), out;
  for (size_t i = 0; i < digits.size(); ++i) {
    if (i > 0 && (digits.size() - i) % 3 == 0) out += ',';
    out += digits[i];
  }
  return n < 0 ? "-" + out : out;
}

std::string Duration(double seconds) {
  if (!(seconds >= 0)) return "an unknown time";
  if (seconds < 90) return absl::StrCat(Number(seconds, 3), " s");
  const int64_t s = std::llround(seconds);
  return absl::StrCat(s / 60, " min ", s % 60, " s");
}

// A metrics.json key in words: the keys people meet most, else the key with spaces and its
// unit suffix spelled out.
std::string Words(const std::string& key) {
  static const std::unordered_map<std::string, std::string> kWords = {
      {"dims", "Grid (voxels along x, y, z)"},
      {"spacing_mm", "Voxel spacing (mm)"},
      {"type", "Stored value type"},
      {"modality", "Modality"},
      {"voxels", "Voxels"},
      {"source", "Segmented by"},
      {"iterations", "Level-set iterations"},
      {"converged", "Converged"},
      {"class_means", "Mean intensity per region"},
      {"region_voxels", "Voxels per region"},
      {"region_volumes_mm3", "Volume per region (mm³)"},
      {"policy", "Simplification policy"},
      {"target_reduction", "Reduction asked for"},
      {"achieved_reduction", "Reduction reached"},
      {"reached_target", "Target reached"},
      {"stop_reason", "Why it stopped"},
      {"stop_message", "Stop message"},
      {"passes", "Passes"},
      {"cells_before", "Cells (tetrahedra) before"},
      {"cells_after", "Cells (tetrahedra) after"},
      {"vertices_before", "Vertices before"},
      {"vertices_after", "Vertices after"},
      {"vertices", "Vertices"},
      {"cells", "Cells (tetrahedra)"},
      {"coverage", "Share of voxel centres inside the mesh"},
      {"rmse", "Root-mean-square error of the field (image units)"},
      {"psnr_db", "Peak signal-to-noise ratio (dB)"},
      {"max_abs_error", "Largest error of the field (image units)"},
      {"value_range", "Value range of the scan (image units)"},
      {"dice", "Dice overlap"},
      {"mean_dice", "Mean Dice overlap"},
      {"label_mismatch", "Share of voxels whose region changed"},
      {"interface_rmse", "Field error next to region borders (image units)"},
      {"interface_distance_max_voxels",
       "Largest distance of a region border from the segmentation's zero level (voxels)"},
      {"interface_distance_mean_voxels",
       "Mean distance of a region border from the segmentation's zero level (voxels)"},
      {"interface_vertices", "Vertices on region borders"},
      {"interfaces", "Region borders"},
      {"feature_vertices", "Feature vertices (corners and edges of regions)"},
      {"feature_vertices_moved", "Feature vertices moved"},
      {"feature_vertices_removed", "Feature vertices removed"},
      {"inverted_cells", "Inverted cells"},
      {"degenerate_cells", "Degenerate (flat) cells"},
      {"min_dihedral_deg", "Smallest dihedral angle (degrees)"},
      {"boundary_faces", "Faces on the mesh boundary"},
      {"interior_faces", "Interior faces"},
      {"nonmanifold_faces", "Non-manifold faces"},
      {"folded_faces", "Folded faces"},
      {"boundary_area_mm2", "Boundary area (mm²)"},
      {"manifold", "Manifold"},
      {"mesh_bytes", "Mesh file size (bytes)"},
      {"voxel_bytes", "Scan size (bytes)"},
      {"bytes_ratio", "Mesh size / scan size"},
      {"size", "Picture size (pixels)"},
      {"transfer_function", "Transfer function"},
      {"preset", "Colour preset used"},
      {"heat_scale_max", "Top of the difference scale (RGB distance)"},
      {"view", "View"},
      {"diff1", "Mean colour difference (RGB distance, 0-442)"},
      {"max_diff2", "Largest colour difference of a pixel"},
      {"changed_pixels", "Pixels that differ"},
      {"load", "Loading the scan"},
      {"segment", "Segmentation"},
      {"tetra", "Tetrahedralization"},
      {"simplify", "Simplification"},
      {"write", "Writing the files"},
      {"render", "Rendering and measuring"},
      {"fidelity", "Measuring fidelity"},
      {"curve", "Difference curve"},
      {"diff", "Pictures and metrics"},
      {"total", "Whole job"},
      {"floor_db", "PSNR floor (dB)"},
  };
  if (auto it = kWords.find(key); it != kWords.end()) return it->second;
  std::string k = key, unit;
  for (const auto& [suffix, name] :
       std::vector<std::pair<std::string, std::string>>{{"_mm3", "mm³"},
                                                        {"_mm2", "mm²"},
                                                        {"_mm", "mm"},
                                                        {"_db", "dB"},
                                                        {"_deg", "degrees"},
                                                        {"_mb", "MB"},
                                                        {"_seconds", "s"},
                                                        {"_bytes", "bytes"}}) {
    if (k.size() > suffix.size() &&
        k.compare(k.size() - suffix.size(), suffix.size(), suffix) == 0) {
      k.resize(k.size() - suffix.size());
      unit = absl::StrCat(" (", name, ")");
      break;
    }
  }
  std::replace(k.begin(), k.end(), '_', ' ');
  if (!k.empty()) k[0] = static_cast<char>(std::toupper(static_cast<unsigned char>(k[0])));
  return k + unit;
}

std::string Value(const Json& v) {
  if (v.is_boolean()) return v.get<bool>() ? "yes" : "no";
  if (v.is_number_integer() || v.is_number_unsigned()) return Count(v.get<int64_t>());
  if (v.is_number_float()) return Number(v.get<double>(), 6);
  if (v.is_string()) return Html(v.get<std::string>());
  if (v.is_null()) return "none";
  if (v.is_array() &&
      std::all_of(v.begin(), v.end(), [](const Json& e) { return e.is_primitive(); })) {
    std::vector<std::string> parts;
    for (const Json& e : v) parts.push_back(Value(e));
    return parts.empty() ? "none" : absl::StrJoin(parts, ", ");
  }
  if (v.is_array()) {  // e.g. the views of "render", the probes of "min_psnr"
    std::vector<std::string> parts;
    for (const Json& e : v) {
      if (!e.is_object()) {
        parts.push_back(Html(e.dump()));
        continue;
      }
      std::vector<std::string> fields;
      for (auto it = e.begin(); it != e.end(); ++it) {
        fields.push_back(absl::StrCat(Html(Words(it.key())), ": ", Value(*it)));
      }
      parts.push_back(absl::StrJoin(fields, "; "));
    }
    return absl::StrJoin(parts, "<br>");
  }
  return Html(v.dump());
}

// Rows "what | value" of a metrics section (nested objects under their parent's words).
void Rows(const Json& j, const std::string& prefix, std::string* out) {
  for (auto it = j.begin(); it != j.end(); ++it) {
    const std::string what =
        prefix.empty() ? Words(it.key()) : absl::StrCat(prefix, ": ", Words(it.key()));
    if (it->is_object()) {
      Rows(*it, what, out);
    } else if (it->is_number() && it.key().size() > 10 &&
               it.key().compare(it.key().size() - 10, 10, "_reduction") == 0) {
      absl::StrAppend(out, "<tr><th>", Html(what), "</th><td>", FormatPercent(it->get<double>()),
                      "</td></tr>\n");
    } else {
      absl::StrAppend(out, "<tr><th>", Html(what), "</th><td>", Value(*it), "</td></tr>\n");
    }
  }
}

double Get(const Json& j, const char* section, const char* key, double fallback) {
  if (!j.contains(section) || !j[section].is_object()) return fallback;
  const Json& s = j[section];
  return s.contains(key) && s[key].is_number() ? s[key].get<double>() : fallback;
}

// Vertex clustering of one surface on a grid of `cell` mm anchored at `origin`.
RegionSurface Cluster(const RegionSurface& s, double cell, const std::array<double, 3>& origin) {
  RegionSurface out;
  out.region = s.region;
  std::unordered_map<uint64_t, int32_t> index;
  std::vector<int32_t> remap(s.vertex_count());
  std::vector<double> sum;
  std::vector<int32_t> members;
  for (int64_t v = 0; v < s.vertex_count(); ++v) {
    uint64_t key = 0;
    for (int a = 0; a < 3; ++a) {
      const auto q =
          static_cast<uint64_t>(std::max(0.0, (s.positions[3 * v + a] - origin[a]) / cell));
      key = (key << 21) | (q & 0x1FFFFF);
    }
    auto [it, fresh] = index.try_emplace(key, static_cast<int32_t>(members.size()));
    if (fresh) {
      sum.insert(sum.end(), {0.0, 0.0, 0.0});
      members.push_back(0);
    }
    remap[v] = it->second;
    for (int a = 0; a < 3; ++a) sum[3 * it->second + a] += s.positions[3 * v + a];
    ++members[it->second];
  }
  out.positions.resize(sum.size());
  for (size_t i = 0; i < sum.size(); ++i) {
    out.positions[i] = static_cast<float>(sum[i] / members[i / 3]);
  }
  for (int64_t t = 0; t < s.triangle_count(); ++t) {
    const int32_t a = remap[s.triangles[3 * t]], b = remap[s.triangles[3 * t + 1]],
                  c = remap[s.triangles[3 * t + 2]];
    if (a != b && b != c && a != c) out.triangles.insert(out.triangles.end(), {a, b, c});
  }
  return out;
}

int64_t Triangles(const std::vector<RegionSurface>& surfaces) {
  int64_t n = 0;
  for (const RegionSurface& s : surfaces) n += s.triangle_count();
  return n;
}

void PutVarint(uint32_t v, std::string* out) {
  while (v >= 0x80) {
    out->push_back(static_cast<char>((v & 0x7F) | 0x80));
    v >>= 7;
  }
  out->push_back(static_cast<char>(v));
}

std::string Deflate(const std::string& in) {
  uLongf size = compressBound(in.size());
  std::string out(size, '\0');
  if (compress2(reinterpret_cast<Bytef*>(out.data()), &size,
                reinterpret_cast<const Bytef*>(in.data()), in.size(), 9) != Z_OK) {
    return {};
  }
  out.resize(size);
  return out;
}

// The 3D view's section: the surfaces as web/viewer.js reads them (its header comment), then
// the bundled script; or a note saying why there is none.
std::string ViewSection(const ReportContext& context) {
  std::string h = "<h2>3D view of the regions</h2>\n";
  const std::string_view script = ReportViewerScript();
  if (script.empty()) {
    absl::StrAppend(&h, "<p class=\"warn\">No 3D view: this build of decima could not bundle it (",
                    Html(std::string(ReportViewerMissingReason())), ").</p>\n");
    return h;
  }
  if (context.view_surfaces == nullptr || context.regions == nullptr) {
    return h + "<p>No 3D view: the job has no region surfaces.</p>\n";
  }
  const int64_t extracted = context.view_surfaces_extracted;
  const std::vector<RegionSurface>& surfaces = *context.view_surfaces;
  std::array<double, 6> bounds = {
      std::numeric_limits<double>::max(),    std::numeric_limits<double>::max(),
      std::numeric_limits<double>::max(),    std::numeric_limits<double>::lowest(),
      std::numeric_limits<double>::lowest(), std::numeric_limits<double>::lowest()};
  for (const RegionSurface& s : surfaces) {
    for (size_t i = 0; i < s.positions.size(); ++i) {
      bounds[i % 3] = std::min<double>(bounds[i % 3], s.positions[i]);
      bounds[3 + i % 3] = std::max<double>(bounds[3 + i % 3], s.positions[i]);
    }
  }
  if (surfaces.empty() || bounds[0] > bounds[3]) {
    return h + "<p>No 3D view: the simplified mesh has no region surfaces.</p>\n";
  }
  // Which regions show at first: all but the space around the patient (air, or without tissue
  // classes the darkest region), whose surface is a box that hides the rest.
  const std::vector<RegionInfo>& infos = context.regions->regions;
  const bool any_class = std::any_of(infos.begin(), infos.end(), [](const RegionInfo& r) {
    return r.tissue != TissueClass::kUnknown;
  });
  int darkest = -1;
  for (const RegionInfo& r : infos) {
    if (darkest < 0 || r.mean < infos[darkest].mean) darkest = r.label;
  }
  std::string data;
  Json regions = Json::array();
  for (const RegionSurface& s : surfaces) {
    const RegionInfo* info = s.region < infos.size() ? &infos[s.region] : nullptr;
    char colour[8] = "#808080";
    if (info != nullptr) {
      std::snprintf(colour, sizeof colour, "#%02x%02x%02x", info->rgb[0], info->rgb[1],
                    info->rgb[2]);
    }
    const bool hidden =
        info != nullptr && (any_class ? info->tissue == TissueClass::kAir : info->label == darkest);
    regions.push_back(
        {{"label", s.region},
         {"name", info != nullptr ? info->name : absl::StrCat("region ", s.region + 1)},
         {"colour", colour},
         {"vertices", s.vertex_count()},
         {"triangles", s.triangle_count()},
         {"shown", !hidden}});
    for (size_t i = 0; i < s.positions.size(); ++i) {
      const double lo = bounds[i % 3], span = bounds[3 + i % 3] - lo;
      const auto q = static_cast<uint16_t>(
          span > 0 ? std::lround(std::clamp((s.positions[i] - lo) / span, 0.0, 1.0) * 65535) : 0);
      data.push_back(static_cast<char>(q & 0xFF));
      data.push_back(static_cast<char>(q >> 8));
    }
    int32_t previous = 0;
    for (const int32_t v : s.triangles) {
      const int32_t d = v - previous;
      previous = v;
      PutVarint((static_cast<uint32_t>(d) << 1) ^ static_cast<uint32_t>(d >> 31), &data);
    }
  }
  const std::string packed = Deflate(data);
  if (packed.empty())
    return h + "<p class=\"warn\">No 3D view: the surfaces could not be packed.</p>\n";
  const Json meta = {{"bounds_mm", bounds}, {"regions", regions}};
  absl::StrAppend(
      &h, "<p>The surfaces of the regions of the simplified mesh (", Count(Triangles(surfaces)),
      " triangles",
      extracted > Triangles(surfaces)
          ? absl::StrCat(", merged for display from the ", Count(extracted), " of the mesh")
          : "",
      "). Drag to turn, scroll to zoom, right-drag to move; tick a region to show or hide it. It "
      "opens facing the patient (anterior view), head up. The letters on its edges give the "
      "patient's sides as it turns, and the bar a length in mm at the depth of the point it turns "
      "about.</p>\n"
      "<div id=\"decima-3d\" data-state=\"loading\"><p>Loading the 3D view (needs JavaScript and "
      "WebGL)...</p></div>\n<script type=\"application/json\" id=\"decima-surfaces-meta\">",
      ScriptJson(meta),
      "</script>\n<script type=\"application/octet-stream\" id=\"decima-surfaces-data\">",
      Base64(packed), "</script>\n<script>", absl::string_view(script.data(), script.size()),
      "</script>\n");
  return h;
}

std::string DicomSection(const DicomDescription& d) {
  std::string rows;
  auto row = [&](const char* what, const std::string& v) {
    if (!v.empty()) absl::StrAppend(&rows, "<tr><th>", what, "</th><td>", Html(v), "</td></tr>\n");
  };
  row("Patient", FormatPersonName(d.patient_name));
  row("Patient ID", d.patient_id);
  std::string date = d.study_date;
  if (date.size() == 8 &&
      std::all_of(date.begin(), date.end(), [](unsigned char c) { return std::isdigit(c); })) {
    date = absl::StrCat(date.substr(0, 4), "-", date.substr(4, 2), "-", date.substr(6, 2));
  }
  row("Study date", date);
  row("Study", d.study_description);
  row("Series", d.series_description);
  row("Modality", d.modality);
  if (rows.empty()) return "";
  return absl::StrCat("<table class=\"patient\">\n", rows, "</table>\n");
}

// The opening paragraph: what a reader needs to trust (or not) the mesh, in words.
std::string Verdict(const JobSpec& spec, const Json& metrics) {
  const Json& simp = metrics["simplification"];
  std::vector<std::string> items;
  const double achieved = simp.value("achieved_reduction", 0.0);
  items.push_back(absl::StrCat("<strong>", FormatPercent(achieved),
                               " fewer cells</strong> than the original mesh (",
                               Count(simp.value("cells_before", int64_t{0})), " &rarr; ",
                               Count(simp.value("cells_after", int64_t{0})), " tetrahedra; ",
                               FormatPercent(spec.target_reduction), " asked for)."));
  if (metrics.contains("fidelity")) {
    const Json& f = metrics["fidelity"];
    const Json psnr = f.value("psnr_db", Json(nullptr));
    items.push_back(
        psnr.is_number()
            ? absl::StrCat("The mesh reproduces the scan's intensities with a <strong>PSNR of ",
                           Number(psnr.get<double>(), 3), " dB</strong> (root-mean-square error ",
                           Number(f.value("rmse", 0.0)), " on a value range of ",
                           Number(f.value("value_range", 0.0)), ").")
            : std::string("The mesh reproduces the scan's intensities exactly (no error)."));
    const double mismatch = f.value("label_mismatch", 1.0), coverage = f.value("coverage", 0.0);
    const double voxels = Get(metrics, "input", "voxels", 0);
    if (mismatch == 0 && coverage == 1) {
      items.push_back("<strong>Every voxel keeps its region.</strong>");
    } else {
      const int64_t changed = std::llround(mismatch * voxels);
      items.push_back(absl::StrCat(
          "<strong class=\"warn\">", Count(changed), " of ", Count(std::llround(voxels)),
          " voxels (", Number(100 * mismatch, 3), " %) changed region</strong>",
          coverage < 1 ? absl::StrCat(", ", Number(100 * (1 - coverage), 3),
                                      " % of the voxels lie outside the mesh")
                       : "",
          "."));
    }
  }
  items.push_back(absl::StrCat("The job took <strong>",
                               Duration(Get(metrics, "seconds", "total", -1)), "</strong>."));
  std::string h = "<div class=\"verdict\"><ul>\n";
  for (const std::string& i : items) absl::StrAppend(&h, "<li>", i, "</li>\n");
  h += "</ul>\n";
  if (simp.value("stop_reason", std::string()) == StopReasonName(StopReason::kPsnrFloor)) {
    // What the job asked for (JobSpec::min_psnr), not a missed target.
    absl::StrAppend(&h, "<p>Stopped by the PSNR floor: ",
                    Html(simp.value("stop_message", std::string())), "</p>\n");
  } else if (!simp.value("reached_target", true)) {
    absl::StrAppend(&h, "<p class=\"warn\">The reduction target was not reached: ",
                    Html(simp.value("stop_message", std::string())), "</p>\n");
  }
  return h + "</div>\n";
}

}  // namespace

std::vector<RegionSurface> ViewSurfaces(const TetMesh& mesh, int64_t budget, int64_t* extracted) {
  std::vector<RegionSurface> surfaces = ExtractRegionSurfaces(mesh);
  if (extracted != nullptr) *extracted = Triangles(surfaces);
  if (Triangles(surfaces) <= budget) return surfaces;
  std::array<double, 3> lo = {std::numeric_limits<double>::max(),
                              std::numeric_limits<double>::max(),
                              std::numeric_limits<double>::max()};
  std::array<double, 3> hi = {std::numeric_limits<double>::lowest(),
                              std::numeric_limits<double>::lowest(),
                              std::numeric_limits<double>::lowest()};
  for (const RegionSurface& s : surfaces) {
    for (size_t i = 0; i < s.positions.size(); ++i) {
      lo[i % 3] = std::min<double>(lo[i % 3], s.positions[i]);
      hi[i % 3] = std::max<double>(hi[i % 3], s.positions[i]);
    }
  }
  const double extent = std::max({hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 1e-6});
  // Grids from 1/1024 of the extent, 1.25 times coarser each step, until the budget is met
  // (the cap of 1/8 keeps a picture of the shapes whatever the budget).
  std::vector<RegionSurface> merged;
  for (double cell = extent / 1024; cell <= extent / 8; cell *= 1.25) {
    merged.clear();
    for (const RegionSurface& s : surfaces) merged.push_back(Cluster(s, cell, lo));
    if (Triangles(merged) <= budget) break;
  }
  return merged;
}

// report.html: one self-contained page (pictures inline as data: URIs, the 3D view's script
// inline, no outside resource) that any browser opens from a mail attachment or a PACS note.
absl::StatusOr<std::string> ReportHtml(const JobSpec& spec, const std::string& input_name,
                                       const Json& metrics,
                                       const std::vector<ReportPicture>& pictures,
                                       const ReportContext& context) {
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
      ".2em .6em;text-align:left;font-size:.9em;vertical-align:top}th{background:#f3f3f3;"
      "font-weight:normal}img{max-width:100%;border:1px solid #888}.swatch{display:inline-block;"
      "width:1em;height:1em;vertical-align:middle;border:1px solid #444}figure{margin:0 0 1.5em}"
      "figcaption{font-weight:bold}.note{margin:.2em 0;max-width:60em}.warn{color:#a00;"
      "font-weight:bold}.verdict{font-size:1.15em;background:#f6f6f0;border-left:.4em solid "
      "#0072b2;padding:.3em 1em;margin:0 0 1.5em}.verdict li{margin:.3em 0}"
      "#decima-3d canvas{border:1px solid #888;display:block;max-width:100%}"
      ".toggles label{margin-right:1.5em;white-space:nowrap}.toggles{margin:.5em 0 1.5em}"
      "</style></head><body>\n<h1>",
      Html(title), "</h1>\n");
  if (context.dicom) h += DicomSection(*context.dicom);
  h += Verdict(spec, metrics);

  // The regions: the names and colours every artifact of the job uses (metrics "regions").
  if (metrics.contains("regions") && metrics["regions"].is_array()) {
    const bool hu = !metrics["regions"].empty() && metrics["regions"][0].contains("mean_hu");
    absl::StrAppend(&h,
                    "<h2>Regions</h2>\n<table>\n<tr><th>Colour</th><th>Name</th><th>Label"
                    "</th><th>Voxels</th><th>Volume (mL)</th><th>Mean intensity",
                    hu ? " (HU)" : "", "</th><th>In the DICOM SEG as</th></tr>\n");
    for (const Json& r : metrics["regions"]) {
      const std::string colour = r.value("colour", std::string("#808080"));
      const double mean = hu ? r.value("mean_hu", 0.0) : r.value("mean", 0.0);
      absl::StrAppend(
          &h, "<tr class=\"region\"><td><span class=\"swatch\" style=\"background:", Html(colour),
          "\"></span> ", Html(colour), "</td><td>", Html(r.value("name", std::string())),
          "</td><td>", r.value("label", 0), "</td><td>", Count(r.value("voxels", int64_t{0})),
          "</td><td>",
          r.contains("volume_mm3") ? Number(r["volume_mm3"].get<double>() / 1000, 4) : "",
          "</td><td>", Number(mean, 4), "</td><td>",
          r.value("dicom_seg", true) ? Html(r.value("dicom_type", std::string()))
                                     : std::string("left out (air)"),
          "</td></tr>\n");
    }
    h += "</table>\n<p class=\"note\">Colours from the Okabe-Ito palette, told apart with the "
         "common colour-vision deficiencies; the same in every picture, the 3D view and the "
         "surface files.</p>\n";
  }
  h += ViewSection(context);

  h += "<h2>Pictures</h2>\n";
  for (const auto& pic : pictures) {
    std::ifstream in(pic.path, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    if (!in)
      return absl::InternalError(absl::StrCat(pic.path.string(), ": cannot read for the report"));
    absl::StrAppend(
        &h, "<figure><figcaption>", Html(pic.caption), "</figcaption>",
        pic.note.empty() ? "" : absl::StrCat("<p class=\"note\">", Html(pic.note), "</p>"),
        "<img alt=\"", Html(pic.caption), "\" src=\"data:image/png;base64,", Base64(ss.str()),
        "\"></figure>\n");
  }

  h += "<h2>All figures</h2>\n";
  Json params;
  params["Input"] = input_name;
  if (!spec.job_name.empty()) params["Job name"] = spec.job_name;
  params["Regions asked for"] = spec.regions;
  if (!spec.class_means.empty()) params["Region means given"] = spec.class_means;
  if (!spec.region_names.empty()) params["Region names given"] = spec.region_names;
  params["Segmentation from a label map"] = spec.label_map.has_value();
  params["Reduction asked for"] = FormatPercent(spec.target_reduction);
  params["Simplification policy"] = SimplifyPolicyName(spec.policy);
  if (spec.policy == SimplifyPolicy::kField) {
    params["Region borders"] = InterfaceModeName(spec.interfaces);
  }
  params["Error tolerance"] = spec.error_tolerance;
  params["Views"] = spec.views;
  params["Picture size (pixels)"] = spec.image_size;
  params["Transfer function"] =
      spec.transfer_function.size() > 80 ? "custom JSON" : spec.transfer_function;
  params["Outputs"] = spec.outputs;
  params["VTU compression"] = spec.vtu_compression_level == 0
                                  ? std::string("none")
                                  : absl::StrCat(VtuCompressorName(spec.mesh_compression),
                                                 " level ", spec.vtu_compression_level);
  std::string rows;
  for (auto it = params.begin(); it != params.end(); ++it) {
    absl::StrAppend(&rows, "<tr><th>", Html(it.key()), "</th><td>", Value(*it), "</td></tr>\n");
  }
  absl::StrAppend(&h, "<h3>What the job was asked</h3>\n<table>\n", rows, "</table>\n");
  const std::pair<const char*, const char*> sections[] = {
      {"input", "The scan"},
      {"segmentation", "Segmentation"},
      {"simplification", "Simplification"},
      {"min_psnr", "PSNR floor search"},
      {"levels", "Recorded levels"},
      {"fidelity", "Fidelity of the simplified mesh"},
      {"render", "Pictures"}};
  for (const auto& [key, heading] : sections) {
    if (!metrics.contains(key) || !metrics[key].is_object()) continue;
    rows.clear();
    Rows(metrics[key], "", &rows);
    absl::StrAppend(&h, "<h3>", heading, "</h3>\n<table>\n", rows, "</table>\n");
  }
  rows.clear();
  if (metrics.contains("seconds")) Rows(metrics["seconds"], "", &rows);
  if (metrics.contains("peak_rss_mb")) {
    absl::StrAppend(&rows, "<tr><th>Peak memory (MB)</th><td>", Value(metrics["peak_rss_mb"]),
                    "</td></tr>\n");
  }
  absl::StrAppend(&h, "<h3>Time per stage (seconds)</h3>\n<table>\n", rows, "</table>\n");
  h += "<p class=\"note\">Written by decima. Every figure is also in metrics.json, with the keys "
       "the documentation uses.</p>\n</body></html>\n";
  return h;
}

}  // namespace decima::pipeline
