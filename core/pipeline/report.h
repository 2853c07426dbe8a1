// report.html (internal to core/pipeline): one self-contained page of a job, its pictures
// inline, for a mail attachment or a PACS note (README "Outputs").
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/status/statusor.h"
#include "core/pipeline/pipeline.h"

namespace decima::pipeline {

// A picture shown in the report, read from `path` when the page is made.
struct ReportPicture {
  std::string caption;
  std::filesystem::path path;
};

// The page: summary (and a warning when the target was missed), `pictures` in order as data:
// URIs, the parameters, every metrics section and the timings of `metrics` (metrics.json, with
// at least "simplification", "diff1" and "seconds"). Internal error naming a picture that cannot
// be read.
absl::StatusOr<std::string> ReportHtml(const JobSpec& spec, const std::string& input_name,
                                       const nlohmann::ordered_json& metrics,
                                       const std::vector<ReportPicture>& pictures);

}  // namespace decima::pipeline
