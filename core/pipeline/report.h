// report.html (internal to core/pipeline): one self-contained page of a job for the radiologist
// who reads it, its pictures and its interactive 3D view inline, for a mail attachment or a PACS
// note (README "Outputs").
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/status/statusor.h"
#include "core/io/dicom.h"
#include "core/mesh/region_surface.h"
#include "core/mesh/tet_mesh.h"
#include "core/pipeline/pipeline.h"
#include "core/volume/regions.h"

namespace decima::pipeline {

// A picture shown in the report, read from `path` when the page is made; `note` says how to
// read it (a sentence under the caption, may be empty).
struct ReportPicture {
  std::string caption;
  std::filesystem::path path;
  std::string note;
};

// What the page shows besides metrics.json.
struct ReportContext {
  const RegionTable* regions = nullptr;  // the job's names and colours
  // The 3D view: the simplified mesh's region surfaces as ViewSurfaces makes them, with the
  // triangle count before merging (none without them). Made by the caller, which frees the mesh
  // before the page is written (a job, issue 30).
  const std::vector<RegionSurface>* view_surfaces = nullptr;
  int64_t view_surfaces_extracted = 0;
  std::optional<DicomDescription> dicom;  // for a DICOM input
};

// Most triangles the 3D view embeds; more are merged by vertex clustering (ViewSurfaces), so
// the page stays small (about 6.3 bytes per triangle in the page: CT head figures in
// core/pipeline/README.md, "The report's 3D view").
inline constexpr int64_t kViewTriangleBudget = 120000;

// The region surfaces of `mesh` as the 3D view shows them: at most `budget` triangles in all,
// reduced by vertex clustering (Rossignac & Borrel 1993: the vertices in one cube of a grid
// become their mean, triangles left with fewer than three corners go) on the coarsest grid
// needed. For display only; the STL and glTF outputs keep the mesh's own surfaces.
// `extracted` (when given) receives the triangle count before merging.
std::vector<RegionSurface> ViewSurfaces(const TetMesh& mesh, int64_t budget = kViewTriangleBudget,
                                        int64_t* extracted = nullptr);

// The page:
//  - a verdict in words: the reduction, the PSNR, whether every voxel keeps its region (else
//    how many changed), the job's time, and a warning when the target was missed;
//  - patient, study and series of a DICOM input, where present;
//  - the regions with their names and colours;
//  - the 3D view of the region surfaces (three.js bundled inline; regions toggled by checkbox),
//    or a note saying why the build had none;
//  - `pictures` in order as data: URIs, each with its caption and note;
//  - the parameters and every figure of `metrics` (metrics.json, with at least
//    "simplification", "diff1" and "seconds") in words.
// Everything from outside (names, DICOM text, messages) is HTML-escaped. Internal error naming
// a picture that cannot be read.
absl::StatusOr<std::string> ReportHtml(const JobSpec& spec, const std::string& input_name,
                                       const nlohmann::ordered_json& metrics,
                                       const std::vector<ReportPicture>& pictures,
                                       const ReportContext& context = {});

}  // namespace decima::pipeline
