// report.html: the verdict and escaping of the page (ReportHtml on given metrics), the 3D view's
// triangle budget (ViewSurfaces), and the page of a real job opened in headless Chromium: its 3D
// canvas must show the surfaces (not one flat colour) and the page must log no error. Without the
// viewer script its "ready" line is missing; with nothing drawn, the canvas is its background
// only (as its corner is): either fails the test.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <regex>
#include <string>

#include "core/io/png.h"
#include "core/io/volume_io.h"
#include "core/mesh/tetrahedralize.h"
#include "core/pipeline/pictures.h"
#include "core/pipeline/pipeline.h"
#include "core/pipeline/report.h"
#include "core/pipeline/report_viewer.h"
#include "core/volume/phantom.h"
#include "tests/core/pipeline/hu_phantom.h"
#include "tests/testing/dicom_writer.h"
#include "tests/testing/process.h"
#include "tests/testing/test_data.h"

namespace decima::pipeline {
namespace {

using testing::HuPhantomFile;

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;
using Json = nlohmann::ordered_json;

std::string FileText(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

Json Metrics(double label_mismatch, double coverage) {
  Json m;
  m["input"] = {{"voxels", 10000}};
  m["simplification"] = {{"policy", "field"},      {"achieved_reduction", 0.8},
                         {"reached_target", true}, {"stop_reason", "target"},
                         {"stop_message", ""},     {"cells_before", 50000},
                         {"cells_after", 10000}};
  m["fidelity"] = {{"psnr_db", 47.25},
                   {"rmse", 3.5},
                   {"value_range", 800.0},
                   {"coverage", coverage},
                   {"label_mismatch", label_mismatch}};
  m["diff1"] = 1.5;
  m["seconds"] = {{"load", 0.5}, {"total", 12.5}};
  return m;
}

TEST(ReportHtml, OpensWithAVerdictInWords) {
  JobSpec spec;
  spec.target_reduction = 0.8;
  auto page = ReportHtml(spec, "head.nii.gz", Metrics(0, 1), {});
  ASSERT_TRUE(page.ok()) << page.status();
  const size_t verdict = page->find("class=\"verdict\"");
  ASSERT_NE(verdict, std::string::npos);
  EXPECT_LT(verdict, page->find("<h2>"));  // before any section
  EXPECT_THAT(*page, HasSubstr("80.0% fewer cells"));
  EXPECT_THAT(*page, HasSubstr("50,000 &rarr; 10,000"));
  EXPECT_THAT(*page, HasSubstr("PSNR of 47.2 dB"));
  EXPECT_THAT(*page, HasSubstr("Every voxel keeps its region."));
  EXPECT_THAT(*page, HasSubstr("The job took <strong>12.5 s</strong>"));
  // Figures in words, not keys.
  EXPECT_THAT(*page, HasSubstr("Reduction reached"));
  EXPECT_THAT(*page, Not(HasSubstr("achieved_reduction")));
  EXPECT_THAT(*page, Not(HasSubstr("label_mismatch")));

  // 1 % of 10,000 voxels changed region: said, and never "every voxel keeps its region".
  page = ReportHtml(spec, "head.nii.gz", Metrics(0.01, 1), {});
  ASSERT_TRUE(page.ok());
  EXPECT_THAT(*page, Not(HasSubstr("Every voxel keeps its region")));
  EXPECT_THAT(*page, HasSubstr("100 of 10,000 voxels (1 %) changed region"));
  // Voxels outside the mesh are no "every voxel keeps its region" either.
  page = ReportHtml(spec, "head.nii.gz", Metrics(0, 0.99), {});
  ASSERT_TRUE(page.ok());
  EXPECT_THAT(*page, Not(HasSubstr("Every voxel keeps its region")));
  EXPECT_THAT(*page, HasSubstr("lie outside the mesh"));
}

TEST(ReportHtml, ShowsDicomDescriptionsEscaped) {
  ReportContext context;
  context.dicom = DicomDescription{"DOE^JANE<script>", "ID&1",      "20240131",
                                   "CT HEAD \"W/O\"",  "Axial <b>", "CT"};
  auto page = ReportHtml({}, "series", Metrics(0, 1), {}, context);
  ASSERT_TRUE(page.ok()) << page.status();
  EXPECT_THAT(*page, HasSubstr("<th>Patient</th><td>DOE, JANE&lt;script&gt;</td>"));
  EXPECT_THAT(*page, HasSubstr("<td>ID&amp;1</td>"));
  EXPECT_THAT(*page, HasSubstr("<td>2024-01-31</td>"));
  EXPECT_THAT(*page, HasSubstr("<td>CT HEAD &quot;W/O&quot;</td>"));
  EXPECT_THAT(*page, HasSubstr("<td>Axial &lt;b&gt;</td>"));
  EXPECT_THAT(*page, Not(HasSubstr("<script>\"")));
  EXPECT_THAT(*page, Not(HasSubstr("JANE<script>")));
  // Absent fields leave no row; no DICOM, no table.
  context.dicom = DicomDescription{};
  context.dicom->series_description = "T1";
  page = ReportHtml({}, "series", Metrics(0, 1), {}, context);
  ASSERT_TRUE(page.ok());
  EXPECT_THAT(*page, Not(HasSubstr("<th>Patient</th>")));
  EXPECT_THAT(*page, HasSubstr("<th>Series</th><td>T1</td>"));
  page = ReportHtml({}, "head.nii.gz", Metrics(0, 1), {});
  EXPECT_THAT(*page, Not(HasSubstr("class=\"patient\"")));
}

TEST(ViewSurfaces, MergesDownToTheTriangleBudget) {
  HeadPhantomOptions o;
  o.dims = {24, 24, 20};
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok());
  TetrahedralizeOptions to;
  to.labels = &p->labels;
  auto mesh = Tetrahedralize(p->image, to);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  auto triangles = [](const std::vector<RegionSurface>& s) {
    int64_t n = 0;
    for (const auto& r : s) n += r.triangle_count();
    return n;
  };
  const std::vector<RegionSurface> full = ViewSurfaces(*mesh, int64_t{1} << 40);
  const int64_t all = triangles(full);
  ASSERT_GT(all, 4000);
  const std::vector<RegionSurface> merged = ViewSurfaces(*mesh, all / 4);
  EXPECT_LE(triangles(merged), all / 4);
  EXPECT_GT(triangles(merged), all / 40);  // still a picture of the shapes
  ASSERT_EQ(merged.size(), full.size());
  for (const RegionSurface& s : merged) {
    for (const int32_t v : s.triangles) ASSERT_LT(v, s.vertex_count());
  }
}

// A job on a DICOM series: its report names the patient, study and series (escaped), which
// metrics.json does not carry.
TEST(ReportHtml, ADicomJobsReportNamesPatientStudyAndSeries) {
  const fs::path dir = decima::testing::MakeScratchDir("report-dicom");
  decima::testing::SliceSpec slice;
  slice.rows = slice.columns = 24;
  slice.pixel_spacing = {2, 2};
  slice.patient_name = "O'NEIL^ANN<b>";
  slice.patient_id = "ID-7";
  slice.study_description = "HEAD & NECK";
  slice.description = "AX <T1>";
  slice.value = [](int i, int j) {
    return (i - 12) * (i - 12) + (j - 12) * (j - 12) < 49 ? 1000 : 0;
  };
  fs::create_directories(dir / "series");
  decima::testing::WriteSeries(dir / "series", slice, std::vector<double>(11, 2.0));
  JobSpec spec;
  spec.input = dir / "series";
  spec.regions = 2;
  spec.image_size = 32;
  spec.outputs = {"report"};
  auto result = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  const std::string html = FileText(dir / "out" / "report.html");
  EXPECT_THAT(html, HasSubstr("<th>Patient</th><td>O&#39;NEIL, ANN&lt;b&gt;</td>"));
  EXPECT_THAT(html, HasSubstr("<th>Patient ID</th><td>ID-7</td>"));
  EXPECT_THAT(html, HasSubstr("<th>Study</th><td>HEAD &amp; NECK</td>"));
  EXPECT_THAT(html, HasSubstr("<th>Series</th><td>AX &lt;T1&gt;</td>"));
  EXPECT_THAT(result->metrics_json, Not(HasSubstr("NEIL")));
}

std::string FindChromium() {
  if (const char* env = std::getenv("DECIMA_CHROMIUM"); env != nullptr && *env != '\0') return env;
  for (const char* p :
       {"/usr/bin/chromium", "/usr/bin/chromium-browser", "/usr/bin/google-chrome"}) {
    if (access(p, X_OK) == 0) return p;
  }
  return "";
}

// Headless Chromium's screenshot of `page`, its stderr (console lines included) in *log. WebGL
// in headless Chromium 120+ on a machine without a GPU: ANGLE on SwiftShader, which newer
// versions enable only with --enable-unsafe-swiftshader. --virtual-time-budget lets the page's
// asynchronous start (inflating the surfaces, the first frame) finish before the shot.
struct Shot {
  pid_t pid = -1;
  fs::path png, out, err;
};
Shot StartShot(const std::string& chromium, const fs::path& page, const fs::path& dir,
               const std::string& tag) {
  Shot s{-1, dir / (tag + ".png"), dir / (tag + ".out"), dir / (tag + ".err")};
  s.pid = decima::testing::Spawn(
      {chromium, "--headless", "--no-sandbox", "--use-angle=swiftshader",
       "--enable-unsafe-swiftshader", "--user-data-dir=" + (dir / (tag + "-profile")).string(),
       "--window-size=1000,1600", "--hide-scrollbars", "--virtual-time-budget=8000",
       "--enable-logging=stderr", "--v=0", "--screenshot=" + s.png.string(),
       "file://" + page.string()},
      s.out.string(), s.err.string(), {{"DBUS_SESSION_BUS_ADDRESS", "disabled:"}});
  return s;
}

// Standard deviation of the luminance in the rectangle, and the share of its pixels that differ
// from its top-left pixel (the scene's background).
struct Spread {
  double stddev = 0, changed = 0;
};
Spread MeasureRect(const Image& im, int x0, int y0, int w, int h) {
  double sum = 0, sum2 = 0;
  int64_t n = 0, changed = 0;
  const uint8_t* corner = &im.pixels[(size_t(y0) * im.width + x0) * im.channels];  // background
  for (int y = y0; y < std::min(y0 + h, im.height); ++y) {
    for (int x = x0; x < std::min(x0 + w, im.width); ++x) {
      const uint8_t* p = &im.pixels[(size_t(y) * im.width + x) * im.channels];
      const double l = 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2];
      sum += l;
      sum2 += l * l;
      ++n;
      changed +=
          std::abs(p[0] - corner[0]) + std::abs(p[1] - corner[1]) + std::abs(p[2] - corner[2]) > 12;
    }
  }
  if (n == 0) return {};
  const double mean = sum / n;
  return {std::sqrt(std::max(0.0, sum2 / n - mean * mean)), double(changed) / n};
}

TEST(ReportInBrowser, TheThreeDViewDrawsTheSurfacesWithoutErrors) {
  ASSERT_FALSE(ReportViewerScript().empty())
      << "this build has no 3D view (" << ReportViewerMissingReason()
      << "); deploy/install-deps.sh installs npm";
  const fs::path dir = decima::testing::MakeScratchDir("report-browser");
  JobSpec spec;
  spec.input = HuPhantomFile(dir);
  spec.image_size = 48;
  spec.outputs = {"report"};
  auto result = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  const fs::path page = dir / "out" / "report.html";
  const std::string html = FileText(page);
  ASSERT_THAT(html, HasSubstr("id=\"decima-surfaces-data\""));
  EXPECT_THAT(html, Not(HasSubstr("src=\"http")));  // self-contained: nothing from a network
  EXPECT_THAT(html, Not(HasSubstr("<script src")));
  // The heat maps' scale is the fixed one, whatever this job's largest difference, and stated.
  const auto metrics = nlohmann::json::parse(result->metrics_json);
  EXPECT_EQ(metrics["render"]["heat_scale_max"].get<double>(), kHeatScaleMax);
  EXPECT_NE(metrics["render"]["views"][0]["max_diff2"].get<double>(), kHeatScaleMax);
  EXPECT_THAT(html,
              HasSubstr("pale yellow 100 or more (of at most 442), the same scale in every job"));

  const std::string chromium = FindChromium();
  if (chromium.empty()) GTEST_SKIP() << "chromium is not installed (apt-get install chromium)";
  const auto started = std::chrono::steady_clock::now();
  Shot shot = StartShot(chromium, page, dir, "report");
  std::string state;
  ASSERT_EQ(decima::testing::WaitExit(shot.pid, std::chrono::seconds(90), &state), 0)
      << state << FileText(shot.err);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  const std::string log = FileText(shot.err);

  // No script error, and the viewer's own report of its first frame.
  EXPECT_THAT(log, Not(HasSubstr("Uncaught"))) << log;
  std::smatch m;
  ASSERT_TRUE(std::regex_search(
      log, m,
      std::regex(
          R"(decima-3d: ready; regions (\d+); shown (\d+); canvas (\d+),(\d+),(\d+),(\d+))")))
      << "the viewer never drew its first frame:\n"
      << log;
  EXPECT_EQ(m[1], "3");  // air, soft tissue, bone
  EXPECT_EQ(m[2], "2");  // air, a box around the rest, starts hidden
  const int x = std::stoi(m[3]), y = std::stoi(m[4]), w = std::stoi(m[5]), h = std::stoi(m[6]);
  ASSERT_GT(w, 100);
  ASSERT_GT(h, 100);
  // The view starts in front of the face, head up, as the anterior picture: the patient's left
  // on the right edge, superior at the top; and a scale bar of a round length in mm.
  std::smatch marks;
  ASSERT_TRUE(std::regex_search(
      log, marks, std::regex(R"(; right (\w+), left (\w+), up (\w+), down (\w+); scale (\d+) mm)")))
      << "the viewer reported no orientation letters or scale:\n"
      << log;
  EXPECT_EQ(marks[1], "L");
  EXPECT_EQ(marks[2], "R");
  EXPECT_EQ(marks[3], "S");
  EXPECT_EQ(marks[4], "I");
  EXPECT_GT(std::stoi(marks[5]), 0);

  auto image = ReadPng(shot.png);
  ASSERT_TRUE(image.ok()) << image.status();
  ASSERT_LE(y + h, image->height) << "the canvas is below the screenshot; make the window taller";
  // The rectangle is the canvas: inside its 1-pixel border, its corner shows the scene's
  // background (#18181c, web/viewer.js), so the check looks at the view and nothing else.
  const uint8_t* corner = &image->pixels[(size_t(y + 4) * image->width + x + 4) * image->channels];
  ASSERT_NEAR(corner[0], 0x18, 3);
  ASSERT_NEAR(corner[1], 0x18, 3);
  ASSERT_NEAR(corner[2], 0x1c, 3);
  // Measured inside the border: all background when nothing is drawn (changed 0, stddev 0).
  const Spread drawn = MeasureRect(*image, x + 2, y + 2, w - 4, h - 4);
  // The surfaces, lit: many pixels off the background and a wide spread of brightness.
  EXPECT_GT(drawn.changed, 0.05) << "3D canvas blank: " << drawn.stddev;
  EXPECT_GT(drawn.stddev, 8) << "3D canvas blank: " << drawn.changed;

  std::cerr << "chromium: " << seconds << " s\n";
}

}  // namespace
}  // namespace decima::pipeline
