// The script of report.html's 3D view: core/pipeline/web/viewer.js and the parts of three.js it
// uses, bundled at build time (cmake/BundleReportViewer.cmake) into a generated source.
#pragma once

#include <string_view>

namespace decima::pipeline {

// The minified script (an IIFE), or empty when the build could not bundle it.
std::string_view ReportViewerScript();
// Why the script is empty ("" when it is not): no npm, npm ci or esbuild failed.
std::string_view ReportViewerMissingReason();

}  // namespace decima::pipeline
