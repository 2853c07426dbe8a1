// RunJob end to end on a small phantom: every documented artifact and metrics key, the
// ValidateJobSpec ranges naming their field, and cancel at a stage boundary.
#include "core/pipeline/pipeline.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <set>

#include "core/io/png.h"
#include "core/io/volume_io.h"
#include "core/mesh/mesh_io.h"
#include "core/simplify/levels_io.h"
#include "core/simplify/stream.h"
#include "core/volume/phantom.h"
#include "tests/core/pipeline/hu_phantom.h"
#include "tests/testing/test_data.h"

namespace decima::pipeline {
namespace {

using testing::HuPhantomFile;

namespace fs = std::filesystem;
using ::testing::Contains;
using ::testing::HasSubstr;

// A three-region head phantom (24x24x20 at 2 mm unless asked otherwise) written as NIfTI: the
// pipeline reads files, not Volumes.
fs::path PhantomFile(const fs::path& dir, std::array<int64_t, 3> dims = {24, 24, 20},
                     std::array<double, 3> spacing = {2, 2, 2}) {
  HeadPhantomOptions o;
  o.dims = dims;
  o.spacing = Eigen::Vector3d(spacing[0], spacing[1], spacing[2]);
  o.noise_sigma = 20;
  auto p = MakeHeadPhantom(o);
  EXPECT_TRUE(p.ok()) << p.status();
  const fs::path path = dir / "phantom.nii.gz";
  EXPECT_TRUE(io::WriteNifti(p->image, path).ok());
  return path;
}

JobSpec SmallSpec(const fs::path& input) {
  JobSpec s;
  s.input = input;
  s.image_size = 48;
  return s;
}

// A progress callback that records each stage once, in order.
ProgressFn StageRecorder(std::vector<std::string>* stages) {
  return [stages](const Progress& p) {
    if (stages->empty() || stages->back() != p.stage) stages->push_back(p.stage);
  };
}

TEST(RunJob, WritesEveryArtifactAndTheDocumentedMetricsKeys) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.views = {"anterior", "lateral"};
  std::vector<std::string> stages;
  auto result = RunJob(spec, dir / "out", StageRecorder(&stages), nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  std::set<std::string> names;
  for (const auto& a : result->artifacts) {
    names.insert(a.name);
    EXPECT_TRUE(fs::is_regular_file(a.path)) << a.name;
    EXPECT_EQ(a.path.parent_path(), dir / "out") << a.name;
    EXPECT_GT(a.size_bytes, 0u) << a.name;
  }
  // The default set: no .msh (six times the .vtu) unless asked for.
  EXPECT_EQ(names, (std::set<std::string>{"labels.nii.gz", "mesh.vtu", "original.png",
                                          "simplified.png", "diff.png", "comparison.png",
                                          "original-lateral.png", "simplified-lateral.png",
                                          "diff-lateral.png", "comparison-lateral.png",
                                          "segmentation.png", "metrics.json", "report.html"}));
  EXPECT_EQ(stages, (std::vector<std::string>{"load", "segment", "tetra", "simplify", "write",
                                              "render", "diff"}));
  auto m = nlohmann::json::parse(result->metrics_json);
  for (const char* key :
       {"input", "segmentation", "simplification", "fidelity", "render", "diff1", "seconds"}) {
    EXPECT_TRUE(m.contains(key)) << key;
  }
  EXPECT_EQ(m["simplification"]["policy"], "field");
  EXPECT_DOUBLE_EQ(m["simplification"]["target_reduction"].get<double>(), 0.5);
  EXPECT_EQ(m["render"]["views"].size(), 2u);
  EXPECT_GT(m["seconds"]["total"].get<double>(), 0);
}

TEST(RunJob, StlOutputWritesOneClosedSurfacePerRegion) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.outputs = {"stl", "glb"};
  auto result = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  std::set<std::string> names;
  for (const auto& a : result->artifacts) names.insert(a.name);
  // Not CT-like (no value below -500): neutral names by intensity rank.
  EXPECT_EQ(names, (std::set<std::string>{"surface-region_1_darkest.stl", "surface-region_2.stl",
                                          "surface-region_3_brightest.stl", "surfaces.glb",
                                          "metrics.json"}));
  for (const auto& a : result->artifacts) {
    if (a.name == "metrics.json" || a.name == "surfaces.glb") continue;
    // 84 bytes of header and count, 50 per triangle, and a closed surface has some.
    EXPECT_GT(a.size_bytes, 84u + 50u * 4u) << a.name;
    EXPECT_EQ((a.size_bytes - 84) % 50, 0u) << a.name;
  }
}

std::string FileText(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// True if `image` holds a solid n x n block of colour `c` (a legend swatch: the montage's tints
// are blends and its interface lines one pixel wide).
bool HasSolidBlock(const Image& image, const std::array<uint8_t, 3>& c, int n) {
  auto is = [&](int x, int y) {
    const uint8_t* p = &image.pixels[(static_cast<size_t>(y) * image.width + x) * image.channels];
    return p[0] == c[0] && p[1] == c[1] && p[2] == c[2];
  };
  for (int y = 0; y + n <= image.height; ++y) {
    for (int x = 0; x + n <= image.width; ++x) {
      bool all = true;
      for (int dy = 0; dy < n && all; ++dy) {
        for (int dx = 0; dx < n && all; ++dx) all = is(x + dx, y + dy);
      }
      if (all) return true;
    }
  }
  return false;
}

// One region table per job: the CT rule's names and the Okabe-Ito colours are the same in
// metrics.json, mesh.vtu's field data, mesh.msh's physical names, the STL file names, the glTF's
// nodes and segmentation.png's legend.
TEST(RunJob, HuLikeRegionsAreNamedAirSoftTissueBoneInEveryArtifact) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(HuPhantomFile(dir));
  spec.outputs = {"vtu", "msh", "stl", "glb", "segmentation", "report"};
  auto result = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  const std::vector<std::string> want = {"air", "soft tissue", "bone"};
  auto m = nlohmann::json::parse(result->metrics_json);
  EXPECT_EQ(m["region_naming"], "ct-hu");
  ASSERT_EQ(m["regions"].size(), 3u);
  ASSERT_EQ(result->regions.regions.size(), 3u);
  for (size_t r = 0; r < 3; ++r) {
    EXPECT_EQ(m["regions"][r]["name"], want[r]);
    EXPECT_EQ(m["regions"][r]["label"], r);
    EXPECT_EQ(result->regions.regions[r].name, want[r]);
  }
  EXPECT_EQ(m["regions"][0]["dicom_seg"], false);  // air is left out of a SEG
  std::set<std::string> names;
  for (const auto& a : result->artifacts) names.insert(a.name);
  for (const char* f : {"surface-air.stl", "surface-soft_tissue.stl", "surface-bone.stl"}) {
    EXPECT_TRUE(names.count(f)) << f;
  }
  // STL headers hold the names too.
  EXPECT_EQ(FileText(dir / "out" / "surface-soft_tissue.stl").substr(0, 34),
            "decima region surface: soft tissue");
  const std::string msh = FileText(dir / "out" / "mesh.msh");
  const std::string vtu = FileText(dir / "out" / "mesh.vtu");
  const std::string glb = FileText(dir / "out" / "surfaces.glb");
  const std::string html = FileText(dir / "out" / "report.html");
  for (size_t r = 0; r < 3; ++r) {
    EXPECT_THAT(msh, HasSubstr("3 " + std::to_string(r + 1) + " \"" + want[r] + "\"\n"));
    std::string codes;
    for (char c : want[r]) codes += std::to_string(int(c)) + " ";
    EXPECT_THAT(vtu, HasSubstr(codes + "0 ")) << want[r];
    EXPECT_THAT(glb, HasSubstr("{\"name\":\"" + want[r] + "\",\"mesh\":")) << want[r];
    EXPECT_THAT(html, HasSubstr("<td>" + want[r] + "</td>"));
  }
  EXPECT_THAT(vtu, HasSubstr("Name=\"region_names\""));
  auto png = ReadPng(dir / "out" / "segmentation.png");
  ASSERT_TRUE(png.ok()) << png.status();
  for (const RegionInfo& r : result->regions.regions) {
    EXPECT_TRUE(HasSolidBlock(*png, r.rgb, 16 /* pictures.h kLegendSwatch */))
        << r.name << ": no swatch";
  }
  auto text = ReadPngText(dir / "out" / "segmentation.png");
  ASSERT_TRUE(text.ok());
  bool listed = false;
  for (const auto& [k, v] : *text)
    listed |= k == "decima:region_names" && v == "air\nsoft tissue\nbone";
  EXPECT_TRUE(listed);
}

// The user's names replace the rule's everywhere; the rule's colours stay.
TEST(RunJob, UserRegionNamesNameTheSurfacesAndPhysicalGroups) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(HuPhantomFile(dir));
  spec.outputs = {"msh", "stl"};
  spec.region_names = {"outside", "Brain", "skull/bone"};
  auto result = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  std::set<std::string> names;
  for (const auto& a : result->artifacts) names.insert(a.name);
  EXPECT_EQ(names, (std::set<std::string>{"surface-outside.stl", "surface-brain.stl",
                                          "surface-skull_bone.stl", "mesh.msh", "metrics.json"}));
  const std::string msh = FileText(dir / "out" / "mesh.msh");
  EXPECT_THAT(msh, HasSubstr("3 2 \"Brain\"\n"));
  auto m = nlohmann::json::parse(result->metrics_json);
  EXPECT_EQ(m["region_naming"], "user");
  EXPECT_EQ(m["regions"][2]["name"], "skull/bone");
}

// The levels output: mesh.levels is the record of a run down to the floor, the same for every
// target up to it (so a level fetched from one job is the mesh of a job at that level), and the
// job's mesh is that record's level at its target.
TEST(RunJob, LevelsOutputIsOneRecordWhateverTheTarget) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.outputs = {"vtu", "levels"};
  spec.record_levels_to = 0.7;
  std::vector<std::string> levels_bytes;
  for (double target : {0.3, 0.6}) {
    spec.target_reduction = target;
    const fs::path out = dir / ("out-" + std::to_string(target));
    auto result = RunJob(spec, out, nullptr, nullptr);
    ASSERT_TRUE(result.ok()) << result.status();
    std::set<std::string> names;
    for (const auto& a : result->artifacts) names.insert(a.name);
    // The labels come along: the record is only applied to the mesh of this segmentation.
    EXPECT_EQ(names,
              (std::set<std::string>{"mesh.vtu", "mesh.levels", "labels.nii.gz", "metrics.json"}));
    auto levels = ReadLevels(out / "mesh.levels");
    ASSERT_TRUE(levels.ok()) << levels.status();
    EXPECT_TRUE(levels->exhausted || levels->deepest_reduction() >= 0.7);
    auto m = nlohmann::json::parse(result->metrics_json);
    EXPECT_EQ(m["levels"]["file"], "mesh.levels");
    EXPECT_EQ(m["levels"]["collapses"].get<int64_t>(), levels->collapses());
    EXPECT_NEAR(m["simplification"]["achieved_reduction"].get<double>(), target, 0.01);
    std::ifstream in(out / "mesh.levels", std::ios::binary);
    levels_bytes.emplace_back(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  EXPECT_EQ(levels_bytes[0], levels_bytes[1]);
  // The paper policy records no levels: said in the metrics, no file, the job still runs.
  spec.policy = SimplifyPolicy::kPaper;
  auto paper = RunJob(spec, dir / "paper", nullptr, nullptr);
  ASSERT_TRUE(paper.ok()) << paper.status();
  EXPECT_FALSE(fs::exists(dir / "paper" / "mesh.levels"));
  EXPECT_THAT(nlohmann::json::parse(paper->metrics_json)["levels"]["note"].get<std::string>(),
              HasSubstr("the paper policy does not record them"));
  spec.record_levels_to = 0;
  std::string field;
  EXPECT_FALSE(ValidateJobSpec(spec, &field).ok());
  EXPECT_EQ(field, "record_levels_to");
}

std::string FileBytes(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// A job on an earlier job's record (its labels as the label map, its mesh.levels): the mesh at
// another reduction without simplifying again, byte for byte the mesh of a job run there with
// the same floor, and its fidelity the same. Past the record's range, or on another
// segmentation, it is refused with the reason.
TEST(RunJob, ALevelOfAnEarlierJobIsTheMeshOfAJobAtThatReduction) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.outputs = {"vtu", "levels"};
  spec.record_levels_to = 0.7;
  spec.target_reduction = 0.3;
  auto first = RunJob(spec, dir / "first", nullptr, nullptr);
  ASSERT_TRUE(first.ok()) << first.status();
  spec.target_reduction = 0.6;
  auto direct = RunJob(spec, dir / "direct", nullptr, nullptr);
  ASSERT_TRUE(direct.ok()) << direct.status();

  JobSpec level = SmallSpec(spec.input);
  level.outputs = {"vtu"};
  level.label_map = dir / "first" / "labels.nii.gz";
  level.levels_file = dir / "first" / "mesh.levels";
  level.target_reduction = 0.6;
  std::vector<std::string> stages;
  auto fetched = RunJob(level, dir / "level", StageRecorder(&stages), nullptr);
  ASSERT_TRUE(fetched.ok()) << fetched.status();
  EXPECT_EQ(FileBytes(dir / "level" / "mesh.vtu"), FileBytes(dir / "direct" / "mesh.vtu"));
  auto a = nlohmann::json::parse(fetched->metrics_json);
  auto b = nlohmann::json::parse(direct->metrics_json);
  EXPECT_EQ(a["simplification"]["cells"], b["simplification"]["cells"]);
  EXPECT_EQ(a["simplification"]["from_levels"], true);
  EXPECT_EQ(a["fidelity"]["psnr_db"], b["fidelity"]["psnr_db"]) << a["fidelity"].dump();
  EXPECT_EQ(a["fidelity"]["label_mismatch"], b["fidelity"]["label_mismatch"]);

  // Deeper than the record (which stopped at its floor, not for want of collapses): refused
  // with the range.
  auto record = ReadLevels(level.levels_file.value());
  ASSERT_TRUE(record.ok()) << record.status();
  ASSERT_FALSE(record->exhausted);
  level.target_reduction = 0.95;
  auto deep = RunJob(level, dir / "deep", nullptr, nullptr);
  ASSERT_FALSE(deep.ok());
  EXPECT_THAT(deep.status().message(), HasSubstr("outside the recorded range (0, 0.7"))
      << deep.status();
  // Another segmentation (two regions): another base mesh, refused by the record's digest.
  JobSpec two = SmallSpec(spec.input);
  two.regions = 2;
  two.outputs = {"labels"};
  ASSERT_TRUE(RunJob(two, dir / "two", nullptr, nullptr).ok());
  level.target_reduction = 0.5;
  level.label_map = dir / "two" / "labels.nii.gz";
  auto other = RunJob(level, dir / "other", nullptr, nullptr);
  ASSERT_FALSE(other.ok());
  EXPECT_THAT(other.status().message(), HasSubstr("digest")) << other.status();

  // A record comes from the field policy, and a level job records none of its own.
  std::string field;
  level.policy = SimplifyPolicy::kPaper;
  EXPECT_FALSE(ValidateJobSpec(level, &field).ok());
  EXPECT_EQ(field, "policy");
  level.policy = SimplifyPolicy::kField;
  level.outputs = {"vtu", "levels"};
  EXPECT_FALSE(ValidateJobSpec(level, &field).ok());
  EXPECT_EQ(field, "outputs");
}

// Issue 31 item 4: a job with a PSNR floor says where it stopped and why, in metrics.json and in
// the simplify stage's last message, and its fidelity figure is the one the search kept.
TEST(RunJob, APsnrFloorIsReportedWhereItStoppedTheJob) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.outputs = {"vtu"};
  spec.target_reduction = 0.9;
  spec.min_psnr = 1e6;  // no level keeps it: the job keeps the unsimplified mesh
  std::string last_simplify_message;
  auto result = RunJob(
      spec, dir / "out",
      [&](const Progress& p) {
        if (p.stage == "simplify") last_simplify_message = p.message;
      },
      nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  auto m = nlohmann::json::parse(result->metrics_json);
  ASSERT_TRUE(m.contains("min_psnr")) << m.dump(1);
  EXPECT_EQ(m["min_psnr"]["floor_db"].get<double>(), 1e6);
  EXPECT_TRUE(m["min_psnr"]["stopped_by_floor"].get<bool>());
  EXPECT_EQ(m["simplification"]["stop_reason"], "min_psnr");
  EXPECT_FALSE(m["simplification"]["reached_target"].get<bool>());
  EXPECT_EQ(m["simplification"]["achieved_reduction"].get<double>(), 0);
  EXPECT_THAT(last_simplify_message, HasSubstr("PSNR floor"));
  EXPECT_EQ(m["simplification"]["stop_message"].get<std::string>(), last_simplify_message);

  // A reachable floor: the kept level's PSNR is metrics.json's fidelity figure, >= the floor.
  spec.min_psnr = 20;
  result = RunJob(spec, dir / "out2", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  m = nlohmann::json::parse(result->metrics_json);
  const double psnr = m["fidelity"]["psnr_db"].get<double>();
  EXPECT_GE(psnr, 20);
  EXPECT_EQ(psnr, m["min_psnr"]["kept_psnr_db"].get<double>());
  EXPECT_GT(m["simplification"]["achieved_reduction"].get<double>(), 0);
}

TEST(RunJob, WritesOnlyTheOutputsAskedFor) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.outputs = {"msh", "medit", "report"};
  auto result = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  std::set<std::string> names;
  for (const auto& a : result->artifacts) names.insert(a.name);
  EXPECT_EQ(names, (std::set<std::string>{"mesh.msh", "mesh.mesh", "metrics.json", "report.html"}));
  // Pictures made for the report only are not left behind.
  std::set<std::string> on_disk;
  for (const auto& e : fs::directory_iterator(dir / "out")) on_disk.insert(e.path().filename());
  EXPECT_EQ(on_disk, names);
  auto m = nlohmann::json::parse(result->metrics_json);
  EXPECT_TRUE(m.contains("diff1"));  // measured even without pictures
  JobSpec bad;
  bad.outputs = {"vtu", "obj"};  // not (yet) a kind
  std::string field;
  EXPECT_EQ(ValidateJobSpec(bad, &field).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(field, "outputs");
  bad.outputs = {"vtu", "vtu"};
  EXPECT_FALSE(ValidateJobSpec(bad).ok());
  bad.outputs = {"vtu"};
  bad.vtu_compression_level = 10;
  EXPECT_EQ(ValidateJobSpec(bad, &field).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(field, "vtu_compression_level");
}

// The field policy's simplify stage frees the original's cells while it runs (issue 30,
// SimplifyDroppingCells) and writes them back: the render stage after it draws the same original
// as a job whose policy keeps them (paper), pixel for pixel (the render, the picture's top
// image_size rows; the caption below it names the policy and the reduction).
TEST(RunJob, StagesAfterSimplifySeeTheOriginalCellsTheFieldRunDropped) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  const fs::path input = PhantomFile(dir);
  std::map<std::string, Image> original_png;
  for (const char* policy : {"field", "paper"}) {
    JobSpec spec = SmallSpec(input);
    spec.policy = *ParseSimplifyPolicy(policy);
    spec.target_reduction = 0.3;
    auto result = RunJob(spec, dir / policy, nullptr, nullptr);
    ASSERT_TRUE(result.ok()) << policy << ": " << result.status();
    auto png = ReadPng(dir / policy / "original.png");
    ASSERT_TRUE(png.ok()) << policy << ": " << png.status();
    original_png[policy] = *std::move(png);
  }
  const Image& field = original_png["field"];
  const Image& paper = original_png["paper"];
  ASSERT_EQ(field.width, paper.width);
  ASSERT_EQ(field.channels, paper.channels);
  ASSERT_GE(field.height, SmallSpec(input).image_size);
  const size_t render_bytes = size_t(field.width) * field.channels * SmallSpec(input).image_size;
  const std::vector<uint8_t> field_render(field.pixels.begin(),
                                          field.pixels.begin() + render_bytes);
  const std::vector<uint8_t> paper_render(paper.pixels.begin(),
                                          paper.pixels.begin() + render_bytes);
  EXPECT_GT(
      std::count_if(field_render.begin(), field_render.end(), [](uint8_t c) { return c > 0; }),
      100);
  EXPECT_EQ(field_render, paper_render);
}

// metrics.json without what differs between two runs of the same job: times and memory.
nlohmann::json WithoutRunFigures(nlohmann::json j) {
  if (j.is_object()) {
    nlohmann::json out = nlohmann::json::object();
    for (auto& [key, value] : j.items()) {
      if (key.find("seconds") != std::string::npos || key.find("rss") != std::string::npos) {
        continue;
      }
      out[key] = WithoutRunFigures(value);
    }
    return out;
  }
  if (j.is_array()) {
    for (auto& v : j) v = WithoutRunFigures(v);
  }
  return j;
}

// Issue 30: the original rendered from the grid (the default) and from its materialized mesh
// give the same job: every picture byte for byte, and the same metrics.json but for times and
// memory. Two views, a phantom with odd and even dims.
TEST(RunJob, TheOriginalFromTheGridGivesTheSamePicturesAndMetricsAsFromTheMesh) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  const fs::path input = PhantomFile(dir, {25, 22, 19}, {1.9, 2.1, 2.3});
  std::map<std::string, JobResult> results;
  for (auto [name, source] : {std::pair{"grid", JobSpec::OriginalSource::kGrid},
                              std::pair{"mesh", JobSpec::OriginalSource::kMesh}}) {
    JobSpec spec = SmallSpec(input);
    spec.views = {"anterior", "-120,-35"};
    spec.original_from = source;
    auto result = RunJob(spec, dir / name, nullptr, nullptr);
    ASSERT_TRUE(result.ok()) << name << ": " << result.status();
    results[name] = *std::move(result);
  }
  int pictures = 0;
  for (const Artifact& a : results["grid"].artifacts) {
    if (a.path.extension() != ".png") continue;
    ++pictures;
    EXPECT_EQ(FileBytes(a.path), FileBytes(dir / "mesh" / a.name)) << a.name;
  }
  EXPECT_EQ(pictures, 9);  // 4 per view and the segmentation
  const auto grid = nlohmann::json::parse(results["grid"].metrics_json);
  const auto mesh = nlohmann::json::parse(results["mesh"].metrics_json);
  EXPECT_GT(grid["render"]["views"][0]["diff1"].get<double>(), 0);
  EXPECT_EQ(WithoutRunFigures(grid), WithoutRunFigures(mesh))
      << WithoutRunFigures(grid).dump(1) << "\n"
      << WithoutRunFigures(mesh).dump(1);
}

// Issue 30: a job simplified in slabs (JobSpec::stream_slab_voxels) measures as the in-memory
// job does: every voxel keeps its label, the cells and the PSNR within 0.5 %; a resumed job does
// not take the in-memory run's checkpoint for the streamed one.
TEST(RunJob, AStreamedJobKeepsTheLabelsCellsAndPsnrOfTheInMemoryJob) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  const fs::path input = PhantomFile(dir, {26, 24, 33});
  JobSpec spec = SmallSpec(input);
  spec.outputs = {"vtu"};
  spec.target_reduction = 0.7;
  CheckpointOptions checkpoints;
  checkpoints.dir = dir / "checkpoints";
  checkpoints.key = "phantom";
  auto in_memory = RunJob(spec, dir / "memory", nullptr, nullptr, checkpoints);
  ASSERT_TRUE(in_memory.ok()) << in_memory.status();
  spec.stream_slab_voxels = 8;
  std::vector<std::string> stages;
  auto streamed = RunJob(spec, dir / "streamed", StageRecorder(&stages), nullptr, checkpoints);
  ASSERT_TRUE(streamed.ok()) << streamed.status();
  EXPECT_THAT(stages, Contains("simplify"));
  const auto a = nlohmann::json::parse(in_memory->metrics_json);
  const auto b = nlohmann::json::parse(streamed->metrics_json);
  EXPECT_EQ(b["fidelity"]["label_mismatch"].get<int64_t>(), 0) << b["fidelity"].dump();
  EXPECT_EQ(b["fidelity"]["coverage"].get<double>(), 1.0);
  const double cells_a = a["simplification"]["cells_after"].get<double>();
  const double cells_b = b["simplification"]["cells_after"].get<double>();
  EXPECT_NEAR(cells_b, cells_a, 0.005 * cells_a);
  const double psnr_a = a["fidelity"]["psnr_db"].get<double>();
  const double psnr_b = b["fidelity"]["psnr_db"].get<double>();
  EXPECT_NEAR(psnr_b, psnr_a, 0.005 * psnr_a);
  // Several windows ran (one pass entry per window; the in-memory run has 1 here), so neither the
  // in-memory path nor its checkpoint made this mesh.
  EXPECT_EQ(a["simplification"]["passes"].get<int>(), 1) << a["simplification"].dump();
  EXPECT_GE(b["simplification"]["passes"].get<int>(), 4) << b["simplification"].dump();
  EXPECT_THAT(b["simplification"]["stop_message"].get<std::string>(), HasSubstr("windows"));
}

// The Python with VTK (Debian's python3-vtk9 is /usr/bin/python3), or "" if none.
std::string PythonWithVtk() {
  for (const char* py : {"/usr/bin/python3", "python3"}) {
    if (std::system((std::string(py) + " -c 'import vtk' >/dev/null 2>&1").c_str()) == 0) return py;
  }
  return "";
}

// Issue 32 part 5: JobSpec::mesh_compression reaches mesh.vtu's header (zlib by default, VTK's
// LZMA when asked), metrics.json says which, the file reads back as the job's mesh, and VTK's
// own reader opens the LZMA file (check_vtu.py stats fails on any VTK error).
TEST(RunJob, MeshCompressionChoosesTheVtuCompressorVtkReads) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.outputs = {"vtu"};
  auto zlib = RunJob(spec, dir / "zlib", nullptr, nullptr);
  ASSERT_TRUE(zlib.ok()) << zlib.status();
  spec.mesh_compression = VtuCompressor::kLzma;
  auto lzma = RunJob(spec, dir / "lzma", nullptr, nullptr);
  ASSERT_TRUE(lzma.ok()) << lzma.status();

  const std::string zlib_text = FileText(dir / "zlib" / "mesh.vtu");
  const std::string lzma_text = FileText(dir / "lzma" / "mesh.vtu");
  const std::string header = lzma_text.substr(0, lzma_text.find("<UnstructuredGrid>"));
  EXPECT_THAT(header, HasSubstr("compressor=\"vtkLZMADataCompressor\""));
  EXPECT_THAT(zlib_text.substr(0, zlib_text.find("<UnstructuredGrid>")),
              HasSubstr("compressor=\"vtkZLibDataCompressor\""));
  EXPECT_EQ(nlohmann::json::parse(zlib->metrics_json)["mesh_compression"], "zlib");
  const auto m = nlohmann::json::parse(lzma->metrics_json);
  EXPECT_EQ(m["mesh_compression"], "lzma");

  // Lossless: both files are the same mesh, the one the job measured.
  auto a = ReadVtu(dir / "zlib" / "mesh.vtu");
  auto b = ReadVtu(dir / "lzma" / "mesh.vtu");
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(b->tet_count(), m["simplification"]["cells_after"].get<int64_t>());
  EXPECT_EQ(a->tets, b->tets);
  EXPECT_EQ(a->scalars, b->scalars);

  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const std::string cmd = python + " '" DECIMA_MESH_TEST_DIR "/check_vtu.py' stats '" +
                          (dir / "lzma" / "mesh.vtu").string() + "' 2>&1";
  FILE* pipe = popen(cmd.c_str(), "r");
  ASSERT_NE(pipe, nullptr);
  std::string out;
  char buf[512];
  while (size_t n = fread(buf, 1, sizeof buf, pipe)) out.append(buf, n);
  ASSERT_EQ(pclose(pipe), 0) << out;
  EXPECT_THAT(out, HasSubstr("cells " + std::to_string(b->tet_count()) + "\n"));
}

// The paper's Fig. 5 for one job: a point per 10 % below the job's reduction plus the job's own,
// cells removed increasing, diff1 finite; the curve in the report, and only when asked for.
TEST(RunJob, TheCurveOutputPlotsDiff1AgainstCellsRemovedUpToTheJobsReduction) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  spec.target_reduction = 0.35;
  spec.outputs = {"curve", "report"};
  std::vector<std::string> stages;
  auto result = RunJob(spec, dir / "out", StageRecorder(&stages), nullptr);
  ASSERT_TRUE(result.ok()) << result.status();
  std::set<std::string> names;
  for (const auto& a : result->artifacts) names.insert(a.name);
  EXPECT_EQ(names, (std::set<std::string>{"curve.png", "metrics.json", "report.html"}));
  EXPECT_EQ(stages, (std::vector<std::string>{"load", "segment", "tetra", "simplify", "write",
                                              "render", "curve", "diff"}));
  auto png = decima::ReadPng(dir / "out" / "curve.png");
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_GE(png->width, 200);
  auto m = nlohmann::json::parse(result->metrics_json);
  const auto& points = m["curve"]["points"];
  ASSERT_EQ(points.size(), 4u);  // 10 %, 20 %, 30 % and the job's 35 %
  for (size_t i = 0; i < points.size(); ++i) {
    EXPECT_TRUE(std::isfinite(points[i]["diff1"].get<double>()));
    if (i > 0) {
      EXPECT_GT(points[i]["cells_removed"].get<int64_t>(),
                points[i - 1]["cells_removed"].get<int64_t>());
    }
  }
  EXPECT_DOUBLE_EQ(points.back()["diff1"].get<double>(), m["diff1"].get<double>());
  EXPECT_NEAR(points[0]["reduction"].get<double>(), 0.1, 0.01);
  std::ifstream in(dir / "out" / "report.html");
  const std::string html((std::istreambuf_iterator<char>(in)), {});
  EXPECT_NE(html.find("Fig. 5"), std::string::npos);
  // Without "curve" there is no curve, in the metrics or the report.
  spec.outputs = {"report"};
  auto plain = RunJob(spec, dir / "out2", nullptr, nullptr);
  ASSERT_TRUE(plain.ok()) << plain.status();
  EXPECT_FALSE(nlohmann::json::parse(plain->metrics_json).contains("curve"));
  EXPECT_FALSE(fs::exists(dir / "out2" / "curve.png"));
}

TEST(RunJob, ABadSpecIsInvalidArgumentBeforeAnyFileIsWritten) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  JobSpec spec = SmallSpec(dir / "never-read.nii");
  spec.target_reduction = std::numeric_limits<double>::quiet_NaN();
  auto r = RunJob(spec, dir / "out", nullptr, nullptr);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(dir / "out"));
}

TEST(ValidateJobSpec, NamesTheFieldOfEachBadValue) {
  struct Case {
    const char* field;
    std::function<void(JobSpec&)> set;
  };
  const double inf = std::numeric_limits<double>::infinity();
  const Case cases[] = {
      {"regions", [](JobSpec& s) { s.regions = 1; }},
      {"class_means",
       [](JobSpec& s) {
         s.class_means = {1, 2};
       }},
      {"target_reduction", [](JobSpec& s) { s.target_reduction = 1.5; }},
      {"policy", [](JobSpec& s) { s.policy = static_cast<SimplifyPolicy>(9); }},
      {"error_tolerance", [](JobSpec& s) { s.error_tolerance = -1; }},
      {"weights.gradient", [inf](JobSpec& s) { s.weights.gradient = inf; }},
      {"views", [](JobSpec& s) { s.views = {}; }},
      {"views", [](JobSpec& s) { s.views = {"upside-down"}; }},
      {"image_size", [](JobSpec& s) { s.image_size = 8; }},
      {"transfer_function", [](JobSpec& s) { s.transfer_function = "neon"; }},
      {"region_names",
       [](JobSpec& s) {
         s.region_names = {"air", "bone"};
       }},
      {"region_names[1]",
       [](JobSpec& s) {
         s.region_names = {"air", "", "bone"};
       }},
      {"region_names[2]",
       [](JobSpec& s) {
         s.region_names = {"air", "bone", "AIR"};
       }},
      {"region_names[0]",
       [](JobSpec& s) {
         s.region_names = {"a\x1b[31m", "b", "c"};
       }},
      {"min_psnr", [](JobSpec& s) { s.min_psnr = std::nan(""); }},
      {"min_psnr", [](JobSpec& s) { s.min_psnr = -3; }},
      {"min_psnr", [inf](JobSpec& s) { s.min_psnr = inf; }},
      {"min_psnr", [](JobSpec& s) { s.min_psnr = 0; }},
      {"min_psnr",
       [](JobSpec& s) {
         s.min_psnr = 40;
         s.policy = SimplifyPolicy::kPaper;
       }},
      {"stream_slab_voxels", [](JobSpec& s) { s.stream_slab_voxels = -1; }},
      {"stream_slab_voxels", [](JobSpec& s) { s.stream_slab_voxels = kMinStreamSlabVoxels - 1; }},
      {"stream_slab_voxels",
       [](JobSpec& s) {
         s.stream_slab_voxels = 8;
         s.policy = SimplifyPolicy::kPaper;
       }},
      {"stream_slab_voxels",
       [](JobSpec& s) {
         s.stream_slab_voxels = 8;
         s.min_psnr = 40;
       }},
      {"stream_slab_voxels",
       [](JobSpec& s) {
         s.stream_slab_voxels = 8;
         s.outputs = {"vtu", "levels"};
       }},
      {"stream_slab_voxels",
       [](JobSpec& s) {
         s.stream_slab_voxels = 8;
         s.target_reduction = 0;
       }},
  };
  for (const auto& c : cases) {
    JobSpec s;
    c.set(s);
    std::string field;
    const absl::Status st = ValidateJobSpec(s, &field);
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << c.field;
    EXPECT_EQ(field, c.field);
  }
  JobSpec ok;
  EXPECT_TRUE(ValidateJobSpec(ok).ok());
  ok.region_names = {"air", "brain", "bone"};
  EXPECT_TRUE(ValidateJobSpec(ok).ok());
  ok.target_reduction = 0;  // no target: a real value
  EXPECT_TRUE(ValidateJobSpec(ok).ok());
  EXPECT_STREQ(SimplifyPolicyName(SimplifyPolicy::kField), "field");
}

TEST(RunJob, CancelStopsAtTheNextCheckAndReturnsCancelled) {
  const fs::path dir = decima::testing::MakeScratchDir("pipeline");
  const JobSpec spec = SmallSpec(PhantomFile(dir));
  CancelToken cancel;
  std::set<std::string> stages;
  auto r = RunJob(
      spec, dir / "out",
      [&](const Progress& p) {
        stages.insert(p.stage);
        if (p.stage == "tetra") cancel.Cancel();  // fires inside the tetra stage
      },
      &cancel);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled) << r.status();
  EXPECT_FALSE(stages.count("write")) << "no stage after the next check ran";
  EXPECT_FALSE(fs::exists(dir / "out" / "mesh.vtu"));
}

}  // namespace
}  // namespace decima::pipeline
