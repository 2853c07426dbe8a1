#include "server/jobs/dicom_results.h"

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "core/io/dicom_export.h"
#include "core/io/volume_io.h"
#include "core/volume/regions.h"

namespace decima::server {
namespace fs = std::filesystem;

absl::Status AddDicomResults(const pipeline::JobSpec& spec, const fs::path& out_dir,
                             pipeline::JobResult* result) {
  std::error_code ec;
  if (!fs::is_directory(spec.input, ec)) return absl::OkStatus();
  const fs::path labels_path = out_dir / "labels.nii.gz";
  // The SEG is made from the label map: a job whose outputs leave out "labels" gets none.
  if (!fs::exists(labels_path, ec)) return absl::OkStatus();
  auto labels = io::ReadVolume(labels_path);
  if (!labels.ok()) {
    return absl::Status(labels.status().code(), absl::StrCat("dicom: ", labels.status().message()));
  }
  io::DicomExportOptions o;
  o.source_dir = spec.input;
  o.series_instance_uid = spec.series_instance_uid;
  o.labels = &*labels;
  // The job's names, colours and codes, so the SEG says what every other artifact says.
  if (!result->regions.regions.empty()) o.regions = &result->regions;
  o.out_dir = out_dir;
  for (const auto& a : result->artifacts) {
    if ((absl::StartsWith(a.name, "comparison") || absl::StartsWith(a.name, "diff")) &&
        absl::EndsWith(a.name, ".png")) {
      o.renders.push_back(a.path);
    }
    // surface-<name>.stl: the region surfaces the job wrote ("stl" output), as models named
    // as the region table names them (the file name is its file-safe form).
    if (absl::StartsWith(a.name, "surface-") && absl::EndsWith(a.name, ".stl")) {
      std::string name = a.name.substr(8, a.name.size() - 12);
      const std::vector<std::string> files = SurfaceFileNames(result->regions);
      for (size_t r = 0; r < files.size(); ++r) {
        if (files[r] == a.name) name = result->regions.regions[r].name;
      }
      o.surfaces.push_back({name, a.path});
    }
  }
  auto written = io::WriteDicomResults(o);
  if (!written.ok()) {
    return absl::Status(written.status().code(),
                        absl::StrCat("dicom: ", written.status().message()));
  }
  auto add = [&](const fs::path& p) {
    result->artifacts.push_back({p.filename().string(), p, fs::file_size(p, ec)});
  };
  if (!written->segmentation.empty()) add(written->segmentation);
  for (const auto& p : written->secondary) add(p);
  for (const auto& p : written->models) add(p);
  return absl::OkStatus();
}

}  // namespace decima::server
