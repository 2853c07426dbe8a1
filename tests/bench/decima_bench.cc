// decima-bench: reproducible figures for the pipeline stages.
//
//   decima-bench --input PATH|phantom:NxNxN --stages load,segment,tetra,simplify,render
//                [--regions K] [--reduction F] [--policy field|paper|tetfusion] [--size W]
//                [--record-levels-to F [--extract-levels R,...]] [--min-psnr DB] [--view NAME]
//                [--original-from grid|mesh|both] [--repeat N] --json
//   decima-bench --input PATH --job-out DIR [--regions K] [--reduction F] [--policy P]
//                [--interfaces M] [--min-psnr DB] [--mesh-compression zlib|lzma] [--size W]
//                [--view NAME] [--original-from grid|mesh|both]
//
// Every stage runs --repeat times on the output of the previous stage; `seconds` is the median
// and `seconds_all` every run. The process's peak resident memory after the stage is reported
// as `peak_rss_mb` (peak over the process so far, so it grows monotonically across stages).
// Without the segment stage, tetra uses the phantom's ground-truth labels (files: no labels).
// The top-level `bytes_per_voxel` is the process's peak over the input's voxels.
//
// With --job-out, the whole job (pipeline::RunJob with the server's default outputs) runs once in
// this process, writing its artifacts to DIR, and the JSON carries the job's own memory figures
// from its metrics.json (`peak_rss_mb`, `stage_peak_rss_mb`), bytes per voxel and per tet of
// the original mesh, and the stage seconds: the peak-memory regression benchmark of issue 30.
// It is the figure the server's job child reports, less the child's few MB of gRPC libraries.
//
// --original-from grid|mesh|both (default grid): where the original is rendered from, the voxel
// grid (RenderableGrid, the pipeline's default) or its materialized 5-tet mesh (RenderableMesh,
// the earlier path; issue 30). In the render stage, `both` renders the original both ways in this
// process and reports each one's build and render seconds under "grid" and "mesh" and whether
// the pixels are identical. With --job-out, `both` runs the job twice, each in a forked child (so
// each peak RSS is its own), into DIR/grid and DIR/mesh, prints both JSON objects and whether
// the PNGs are byte-identical and metrics.json is the same but for times and memory.
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "core/io/volume_io.h"
#include "core/mesh/mesh_io.h"
#include "core/mesh/tetrahedralize.h"
#include "core/metrics/fidelity.h"
#include "core/metrics/fidelity_json.h"
#include "core/pipeline/job_run.h"
#include "core/pipeline/pipeline.h"
#include "core/pipeline/psnr_floor.h"
#include "core/render/camera.h"
#include "core/render/diff.h"
#include "core/render/renderer.h"
#include "core/render/transfer_function.h"
#include "core/segment/segment.h"
#include "core/simplify/levels.h"
#include "core/simplify/levels_io.h"
#include "core/simplify/simplify.h"
#include "core/simplify/simplify_json.h"
#include "core/simplify/stream.h"
#include "core/volume/phantom.h"
#include "tests/bench/bench_util.h"

namespace decima {
namespace {

using bench::LoadAverage;
using bench::ParsePhantom;
using bench::PeakRssMb;

using Json = nlohmann::ordered_json;

// Runs `fn` `repeat` times and fills seconds (median) and seconds_all.
absl::Status Time(int repeat, Json& out, const std::function<absl::Status()>& fn) {
  std::vector<double> runs;
  for (int r = 0; r < repeat; ++r) {
    const auto start = std::chrono::steady_clock::now();
    absl::Status s = fn();
    if (!s.ok()) return s;
    runs.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  }
  out["seconds_all"] = runs;
  std::sort(runs.begin(), runs.end());
  out["seconds"] = runs[runs.size() / 2];
  out["peak_rss_mb"] = PeakRssMb();
  return absl::OkStatus();
}

struct BenchOptions {
  std::string input;
  int repeat = 3;
  int regions = 3;
  double reduction = 0.5;
  std::string policy = "field";
  double min_dihedral = SimplifyOptions().min_dihedral_degrees;
  std::string interfaces = InterfaceModeName(SimplifyOptions().interfaces);
  int refit_iterations = SimplifyOptions().refit_iterations;
  double record_levels_to = 0;
  std::vector<double> extract_levels;
  double min_psnr = 0;  // 0: no floor
  bool psnr_refine = true;
  std::string simplify_cells = "dropped";
  int stream_slab_voxels = 0;  // simplify: 0 = in memory, else SimplifyStreamed's slab
  std::string mesh_compression = VtuCompressorName(VtuWriteOptions().compressor);
  int size = 512;
  std::string view = "anterior";
  std::string original_from = "grid";  // grid, mesh or both
  std::string checkpoints;             // --job-out: RunJob's checkpoint folder (empty: none)
  bool progress = false;               // --job-out: the job's progress on stderr
};

struct BenchState {
  Volume image;
  std::optional<Volume> labels;           // segmentation or phantom truth
  std::vector<float> interface_distance;  // voxels, with labels
  std::optional<TetMesh> mesh;
  std::optional<SimplifyResult> simplified;
};

void DescribeVolume(const Volume& v, Json& out) {
  out["dims"] = v.dims;
  out["voxels"] = v.voxel_count();
  out["type"] = std::string(VoxelTypeName(v.type));
}

absl::Status RunLoad(const BenchOptions& o, BenchState& state, Json& out) {
  auto phantom_dims = ParsePhantom(o.input);
  if (!phantom_dims.ok()) return phantom_dims.status();
  absl::Status s = Time(o.repeat, out, [&]() -> absl::Status {
    if (phantom_dims->has_value()) {
      HeadPhantomOptions p;
      p.dims = **phantom_dims;
      p.region_means = {0, 1000, 400};
      p.noise_sigma = 50;
      auto phantom = MakeHeadPhantom(p);
      if (!phantom.ok()) return phantom.status();
      state.image = std::move(phantom->image);
      state.labels = std::move(phantom->labels);
      return ComputeInterfaceDistance(*state.labels, &state.interface_distance, nullptr);
    }
    auto v = io::ReadVolume(o.input);
    if (!v.ok()) return v.status();
    state.image = *std::move(v);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  DescribeVolume(state.image, out);
  return absl::OkStatus();
}

absl::Status RunSegment(const BenchOptions& o, BenchState& state, Json& out) {
  SegmentOptions so;
  so.regions = o.regions;
  std::optional<SegmentResult> seg;
  absl::Status s = Time(o.repeat, out, [&]() -> absl::Status {
    seg.reset();
    auto r = Segment(state.image, so, nullptr, nullptr);
    if (!r.ok()) return r.status();
    seg = *std::move(r);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  out["regions"] = o.regions;
  out["iterations"] = seg->iterations;
  out["converged"] = seg->converged;
  out["class_means"] = seg->class_means;
  out["region_voxels"] = seg->region_voxels;
  out["region_volumes_mm3"] = seg->region_volumes_mm3;
  out["bytes_per_voxel_output"] = 1 + 2 * sizeof(float);
  state.labels = std::move(seg->labels);
  state.interface_distance = std::move(seg->interface_distance_voxels);
  return absl::OkStatus();
}

absl::Status RunTetra(const BenchOptions& o, BenchState& state, Json& out) {
  TetrahedralizeOptions opts;
  if (state.labels) {
    opts.labels = &*state.labels;
    opts.interface_distance = state.interface_distance.data();
  }
  absl::Status s = Time(o.repeat, out, [&]() -> absl::Status {
    state.mesh.reset();  // one mesh alive at a time, as the pipeline holds it
    auto m = Tetrahedralize(state.image, opts);
    if (!m.ok()) return m.status();
    state.mesh = *std::move(m);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  out["vertices"] = state.mesh->vertex_count();
  out["tets"] = state.mesh->tet_count();
  int64_t features = 0;
  for (uint8_t f : state.mesh->vertex_flags) features += (f & kFeatureVertex) != 0;
  out["feature_vertices"] = features;
  return absl::OkStatus();
}

absl::Status RunSimplify(const BenchOptions& o, BenchState& state, Json& out) {
  SimplifyOptions so;
  so.policy = *ParseSimplifyPolicy(o.policy);  // the flag accepts only known names
  so.target_reduction = o.reduction;
  so.min_dihedral_degrees = o.min_dihedral;
  so.interfaces = *ParseInterfaceMode(o.interfaces);  // the flag accepts only known names
  so.refit_iterations = o.refit_iterations;
  so.record_levels_to = o.record_levels_to;
  pipeline::PsnrFloorSearch search;
  // The stage's own peak, as a job measures it (VmHWM reset before the stage), since ru_maxrss
  // keeps the earlier stages' peaks.
  pipeline::PeakRss stage_peak;
  // The grid's cells, when the run drops them, are written back after the stage's time and peak
  // are taken: a job whose later stages do not read them (the default outputs) never writes them
  // back, and the 17 B per tet written back at once counted in a streamed stage's peak.
  const bool had_cells = !state.mesh->cells_dropped;
  absl::Status s = Time(o.repeat, out, [&]() -> absl::Status {
    state.simplified.reset();
    if (o.stream_slab_voxels > 0) {
      // Streamed: the grid's cells are read from the grid (dropped), as the job's stage does.
      if (!state.mesh->cells_dropped) DropGridCells(&*state.mesh);
      auto r = SimplifyStreamed(*state.mesh, so, o.stream_slab_voxels);
      if (!r.ok()) return r.status();
      state.simplified = *std::move(r);
      return absl::OkStatus();
    }
    // With a floor, what a job with JobSpec::min_psnr runs: the search is part of the time.
    // Without, what the job's simplify stage runs: the cells dropped for the run.
    auto r = o.min_psnr > 0 ? pipeline::SimplifyToPsnrFloor(state.image, *state.mesh, so,
                                                            o.min_psnr, o.psnr_refine, &search)
             : o.simplify_cells == "kept" ? Simplify(*state.mesh, so)
                                          : SimplifyDroppingCells(&*state.mesh, so, nullptr,
                                                                  nullptr, /*restore_cells=*/false);
    if (!r.ok()) return r.status();
    state.simplified = *std::move(r);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  const SimplifyResult& r = *state.simplified;
  out.update(SimplifyResultToJson(r, so, state.mesh->vertex_count()));
  if (so.policy == SimplifyPolicy::kField) {
    out["min_dihedral_degrees"] = o.min_dihedral;
    out["refit_iterations"] = o.refit_iterations;
    out["record_levels_to"] = o.record_levels_to;
    if (r.levels) {
      out["levels_collapses"] = r.levels->collapses();
      out["levels_deepest_reduction"] = r.levels->deepest_reduction();
      out["levels_file_bytes"] = SerializeLevels(*r.levels).size();
    }
  }
  if (o.min_psnr > 0) {
    Json probes = Json::array();
    for (const pipeline::PsnrProbe& p : search.probes) {
      probes.push_back({{"kind", p.run ? "run" : "level"},
                        {"requested", p.requested},
                        {"reduction", p.reduction},
                        {"cells", p.cells},
                        {"psnr_db", p.psnr_db}});
    }
    out["min_psnr"] = {{"floor_db", search.floor_db},
                       {"stopped_by_floor", search.floor_stopped},
                       {"kept_reduction", search.kept.reduction},
                       {"kept_psnr_db", search.kept.psnr_db},
                       {"search_seconds", search.seconds},
                       {"probes", probes}};
    if (search.deeper) {
      out["min_psnr"]["deeper_reduction"] = search.deeper->reduction;
      out["min_psnr"]["deeper_psnr_db"] = search.deeper->psnr_db;
    }
  }
  out["simplify_cells"] = o.min_psnr > 0 ? "kept" : o.simplify_cells;
  out["stream_slab_voxels"] = o.stream_slab_voxels;
  if (stage_peak.resettable()) {
    stage_peak.EndStage("simplify");
    const double mb = stage_peak.stages()["simplify"].get<double>();
    out["stage_peak_rss_mb"] = mb;
    out["stage_peak_bytes_per_voxel"] = mb * 1048576.0 / state.image.voxel_count();
  }
  if (had_cells && state.mesh->cells_dropped) RestoreGridCells(&*state.mesh, so.threads);
  out["cells_removed_per_second"] = (r.input_cells - r.output_cells) / out["seconds"].get<double>();

  FidelityOptions fo;
  fo.labels = state.labels ? &*state.labels : nullptr;
  fo.original = &*state.mesh;
  fo.vertex_map = &r.vertex_map;
  auto f = MeasureFidelity(state.image, r.mesh, fo);
  if (!f.ok()) return f.status();
  out["fidelity"] = FidelityToJson(*f);
  // Levels taken from the record: what a fetch at another reduction costs in the core (the
  // extraction and its refit), and what it keeps.
  if (r.levels && !o.extract_levels.empty()) {
    Json levels = Json::array();
    for (double reduction : o.extract_levels) {
      const auto start = std::chrono::steady_clock::now();
      auto level = ExtractLevel(*state.mesh, *r.levels, reduction, 0);
      if (!level.ok()) return level.status();
      const double seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      fo.vertex_map = &level->vertex_map;
      auto lf = MeasureFidelity(state.image, level->mesh, fo);
      if (!lf.ok()) return lf.status();
      levels.push_back({{"reduction", reduction},
                        {"seconds", seconds},
                        {"achieved_reduction", level->achieved_reduction},
                        {"cells", level->output_cells},
                        {"psnr_db", lf->psnr_db}});
    }
    out["extracted_levels"] = levels;
  }
  return absl::OkStatus();
}

// Renders the original from `renderable` (a RenderableGrid or RenderableMesh) --repeat times into
// out["seconds"...]; the last image in *image.
template <typename Renderable>
absl::Status TimeOriginal(const BenchOptions& o, const Renderable& renderable, const Camera& camera,
                          const TransferFunction& tf, Json& out,
                          std::optional<RenderedImage>* image) {
  return Time(o.repeat, out, [&]() -> absl::Status {
    auto r = Render(renderable, camera, tf);
    if (!r.ok()) return r.status();
    *image = *std::move(r);
    return absl::OkStatus();
  });
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

absl::Status RunRender(const BenchOptions& o, BenchState& state, Json& out) {
  auto view = ParseView(o.view);
  if (!view.ok()) return view.status();
  const bool grid = o.original_from != "mesh", mesh = o.original_from != "grid";
  std::optional<RenderableGrid> from_grid;
  std::optional<RenderableMesh> from_mesh;
  Json build;
  if (grid) {
    const auto start = std::chrono::steady_clock::now();
    auto r = BuildRenderableGrid(state.image);
    if (!r.ok()) return r.status();
    from_grid = *std::move(r);
    build["grid"] = SecondsSince(start);
  }
  if (mesh) {
    const auto start = std::chrono::steady_clock::now();
    auto r = BuildRenderableMesh(*state.mesh);
    if (!r.ok()) return r.status();
    from_mesh = *std::move(r);
    build["mesh"] = SecondsSince(start);
  }
  const Bounds bounds = grid ? from_grid->bounds : from_mesh->bounds;
  const ScalarRange range = grid ? from_grid->scalar_range : from_mesh->scalar_range;
  const int64_t tets = grid ? from_grid->tet_count() : from_mesh->tet_count();
  ViewOptions vo;
  vo.width = vo.height = o.size;
  auto camera = MakeViewCamera(*view, bounds, vo);
  if (!camera.ok()) return camera.status();
  const bool ct = state.image.modality == "CT" || range.max > 1500;
  auto tf = TransferFunctionPreset(ct ? "ct" : "mri-t1", range);
  if (!tf.ok()) return tf.status();
  std::optional<RenderedImage> image, mesh_image;
  out["original_from"] = o.original_from;
  if (grid && mesh) {
    Json g, m;
    absl::Status s = TimeOriginal(o, *from_grid, *camera, *tf, g, &image);
    if (!s.ok()) return s;
    s = TimeOriginal(o, *from_mesh, *camera, *tf, m, &mesh_image);
    if (!s.ok()) return s;
    g["build_seconds"] = build["grid"];
    m["build_seconds"] = build["mesh"];
    out["grid"] = g;
    out["mesh"] = m;
    out["identical_pixels"] = image->rgb == mesh_image->rgb && image->alpha == mesh_image->alpha;
    out["seconds"] = g["seconds"];
  } else {
    absl::Status s = grid ? TimeOriginal(o, *from_grid, *camera, *tf, out, &image)
                          : TimeOriginal(o, *from_mesh, *camera, *tf, out, &image);
    if (!s.ok()) return s;
    out["build_seconds"] = grid ? build["grid"] : build["mesh"];
  }
  out["size"] = o.size;
  out["view"] = o.view;
  out["tets"] = tets;
  from_grid.reset();
  from_mesh.reset();
  if (state.simplified) {
    auto simplified = BuildRenderableMesh(state.simplified->mesh);
    if (!simplified.ok()) return simplified.status();
    auto b = Render(*simplified, *camera, *tf);
    if (!b.ok()) return b.status();
    auto diff = Diff(*image, *b);
    if (!diff.ok()) return diff.status();
    out["simplified_seconds"] = b->stats.seconds;
    out["diff1"] = diff->diff1;
    out["max_diff2"] = diff->max_diff2;
  }
  return absl::OkStatus();
}

// The whole job in this process; its own memory figures in *out (see the file comment).
int RunWholeJob(const BenchOptions& o, const std::string& out_dir, Json* out_json) {
  pipeline::JobSpec spec;
  spec.input = o.input;
  spec.regions = o.regions;
  spec.target_reduction = o.reduction;
  spec.policy = *ParseSimplifyPolicy(o.policy);  // the flag accepts only known names
  spec.interfaces = *ParseInterfaceMode(o.interfaces);
  if (o.min_psnr > 0) spec.min_psnr = o.min_psnr;  // --reduction stays the maximum, as in a job
  spec.stream_slab_voxels = o.stream_slab_voxels;
  spec.mesh_compression = *ParseVtuCompressor(o.mesh_compression);  // the flag checks the name
  spec.image_size = o.size;
  spec.views = {o.view};
  spec.original_from = o.original_from == "mesh" ? pipeline::JobSpec::OriginalSource::kMesh
                                                 : pipeline::JobSpec::OriginalSource::kGrid;
  pipeline::CheckpointOptions checkpoints;
  checkpoints.dir = o.checkpoints;
  checkpoints.key = o.input;
  // Seconds since the job began, the stage, its fraction and message: what a watcher sees.
  const auto began = std::chrono::steady_clock::now();
  ProgressFn progress = nullptr;
  if (o.progress) {
    progress = [&](const Progress& p) {
      const double t =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - began).count();
      std::cerr << absl::StrFormat("%9.1f s %-8s %5.1f %% %s\n", t, p.stage, 100 * p.fraction,
                                   p.message);
    };
  }
  auto result = pipeline::RunJob(spec, out_dir, progress, nullptr, checkpoints);
  if (!result.ok()) {
    std::cerr << "decima-bench: job: " << result.status() << "\n";
    return 1;
  }
  const Json metrics = Json::parse(result->metrics_json);
  const double voxels = metrics["input"]["voxels"].get<double>();
  const double tets = metrics["simplification"]["cells_before"].get<double>();
  const double peak_bytes = metrics["peak_rss_mb"].get<double>() * 1048576.0;
  Json out;
  out["input"] = o.input;
  out["job_out"] = out_dir;
  out["machine"] = {{"cores", std::thread::hardware_concurrency()},
                    {"load_average_1m_at_end", LoadAverage()}};
  out["dims"] = metrics["input"]["dims"];
  out["voxels"] = voxels;
  out["tets"] = tets;
  out["reduction"] = o.reduction;
  out["policy"] = o.policy;
  out["peak_rss_mb"] = metrics["peak_rss_mb"];
  out["bytes_per_voxel"] = peak_bytes / voxels;
  out["bytes_per_tet"] = peak_bytes / tets;
  out["stage_peak_rss_mb"] = metrics["stage_peak_rss_mb"];
  Json per_voxel = Json::object();
  for (const auto& [stage, mb] : metrics["stage_peak_rss_mb"].items()) {
    per_voxel[stage] = mb.get<double>() * 1048576.0 / voxels;
  }
  out["stage_bytes_per_voxel"] = per_voxel;
  out["seconds"] = metrics["seconds"];
  out["cells_after"] = metrics["simplification"]["cells_after"];
  out["fidelity"] = metrics["fidelity"];
  out["original_from"] = o.original_from;
  *out_json = out;
  return 0;
}

// metrics.json without what differs between two runs of one job: times and memory.
Json WithoutRunFigures(const Json& j) {
  if (j.is_object()) {
    Json out = Json::object();
    for (const auto& [key, value] : j.items()) {
      if (key.find("seconds") == std::string::npos && key.find("rss") == std::string::npos) {
        out[key] = WithoutRunFigures(value);
      }
    }
    return out;
  }
  if (!j.is_array()) return j;
  Json out = Json::array();
  for (const auto& v : j) out.push_back(WithoutRunFigures(v));
  return out;
}

std::string FileBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// --job-out with --original-from both: the job from the grid and from the mesh, each in a forked
// child (called before any thread starts), then the comparison (see the file comment).
int RunWholeJobBothWays(const BenchOptions& o, const std::string& out_dir) {
  namespace fs = std::filesystem;
  Json both;
  for (const char* source : {"grid", "mesh"}) {
    const fs::path dir = fs::path(out_dir) / source;
    std::cout.flush();
    const pid_t pid = fork();
    if (pid < 0) {
      std::cerr << "decima-bench: fork failed\n";
      return 1;
    }
    if (pid == 0) {
      BenchOptions one = o;
      one.original_from = source;
      Json out;
      int rc = RunWholeJob(one, dir.string(), &out);
      if (rc == 0) {
        std::ofstream f(dir / "bench.json");
        f << out.dump(2);
        rc = f.good() ? 0 : 1;
      }
      std::_Exit(rc);
    }
    int status = 0;
    if (waitpid(pid, &status, 0) != pid || !WIFEXITED(status) || WEXITSTATUS(status) != 0) {
      std::cerr << "decima-bench: the job with the original from the " << source << " failed\n";
      return 1;
    }
    std::ifstream in(dir / "bench.json");
    both[source] = Json::parse(in);
  }
  bool pngs_identical = true;
  Json pngs = Json::array();
  for (const auto& entry : fs::directory_iterator(fs::path(out_dir) / "grid")) {
    if (entry.path().extension() != ".png") continue;
    const fs::path other = fs::path(out_dir) / "mesh" / entry.path().filename();
    const bool same = FileBytes(entry.path()) == FileBytes(other);
    pngs_identical = pngs_identical && same;
    pngs.push_back({{"name", entry.path().filename().string()}, {"identical", same}});
  }
  both["pngs"] = pngs;
  both["pngs_identical"] = pngs_identical && !pngs.empty();
  const Json grid_metrics = Json::parse(FileBytes(fs::path(out_dir) / "grid" / "metrics.json"));
  const Json mesh_metrics = Json::parse(FileBytes(fs::path(out_dir) / "mesh" / "metrics.json"));
  both["metrics_identical_but_times_and_memory"] =
      WithoutRunFigures(grid_metrics) == WithoutRunFigures(mesh_metrics);
  std::cout << both.dump(2) << std::endl;
  return 0;
}

int Main(int argc, char** argv) {
  CLI::App app{"decima-bench: time Decima's pipeline stages on one input and print JSON"};
  BenchOptions o;
  std::string stages_arg = "load,tetra";
  bool json = false;
  app.add_option("--input", o.input, "Volume file, DICOM folder, or phantom:NxNxN (synthetic head)")
      ->required();
  app.add_option("--stages", stages_arg,
                 "Comma-separated stages: load,segment,tetra,simplify,render (load is implied)")
      ->capture_default_str();
  app.add_option("--repeat", o.repeat, "Runs per stage; the median is reported")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--regions", o.regions, "segment: number of regions K")
      ->check(CLI::Range(2, 8))
      ->capture_default_str();
  app.add_option("--reduction", o.reduction, "simplify: fraction of cells to remove")
      ->check(CLI::Range(0.0, 0.95))
      ->capture_default_str();
  app.add_option("--policy", o.policy, "simplify: field, paper or tetfusion")
      ->check(CLI::IsMember({"field", "paper", "tetfusion"}))
      ->capture_default_str();
  app.add_option("--min-dihedral", o.min_dihedral,
                 "simplify, field policy: the shape guard's floor in degrees (0 = no guard)")
      ->check(CLI::Range(0.0, 30.0))
      ->capture_default_str();
  app.add_option("--interfaces", o.interfaces,
                 "simplify, field policy: free (interface vertices move wherever every voxel "
                 "centre keeps its label) or voxel-faces (the voxel staircase kept as a set)")
      ->check(CLI::IsMember({"free", "voxel-faces"}))
      ->capture_default_str();
  app.add_option("--mesh-compression", o.mesh_compression,
                 "--job-out: mesh.vtu's compressor, zlib or lzma (a job's mesh_compression)")
      ->check(CLI::IsMember({"zlib", "lzma"}))
      ->capture_default_str();
  app.add_option("--refit-iterations", o.refit_iterations,
                 "simplify, field policy: least-squares refit steps (0 = keep the samples)")
      ->check(CLI::Range(0, 1000))
      ->capture_default_str();
  app.add_option("--record-levels-to", o.record_levels_to,
                 "simplify, field policy: record the collapses down to this reduction (0 = no "
                 "levels); the mesh is then the level at --reduction of that record")
      ->check(CLI::Range(0.0, 0.99))
      ->capture_default_str();
  app.add_option("--extract-levels", o.extract_levels,
                 "simplify with --record-levels-to: also extract these reductions from the "
                 "record (comma-separated), with their time and PSNR")
      ->delimiter(',')
      ->check(CLI::Range(0.0, 0.99));
  app.add_option("--min-psnr", o.min_psnr,
                 "simplify, field policy: a PSNR floor in dB, as a job's min_psnr (0 = none); "
                 "--reduction is then the maximum (0: none)")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app.add_option("--psnr-refine", o.psnr_refine,
                 "with --min-psnr: 1 = refine the levels' answer with runs (a job without the "
                 "levels output), 0 = levels only (a job with it)")
      ->capture_default_str();
  app.add_option("--simplify-cells", o.simplify_cells,
                 "simplify: dropped (the job's way: the input's cells freed and computed from "
                 "the grid, then restored) or kept (read from the array; the same mesh)")
      ->check(CLI::IsMember({"dropped", "kept"}))
      ->capture_default_str();
  app.add_option("--stream-slab-voxels", o.stream_slab_voxels,
                 "simplify, field policy: stream through the volume in slabs of this many voxel "
                 "layers along z (SimplifyStreamed; 0 = in memory); with --job-out the job's "
                 "JobSpec::stream_slab_voxels")
      ->check(CLI::Range(0, 1 << 20))
      ->capture_default_str();
  app.add_option("--size", o.size, "render: image width and height in pixels")
      ->check(CLI::Range(16, 4096))
      ->capture_default_str();
  app.add_option("--view", o.view,
                 "render: view preset (anterior, lateral, superior, oblique, ...)")
      ->capture_default_str();
  app.add_option("--original-from", o.original_from,
                 "render the original from the voxel grid, from its materialized mesh, or both "
                 "(compared; see the file comment)")
      ->check(CLI::IsMember({"grid", "mesh", "both"}))
      ->capture_default_str();
  std::string job_out;
  app.add_option("--job-out", job_out,
                 "Run the whole job (RunJob) into this folder instead of the stages and print "
                 "its memory figures");
  app.add_option("--checkpoints", o.checkpoints,
                 "--job-out: save the segment and simplify stages' checkpoints in this folder "
                 "and resume from them (keyed by --input and the spec), to measure the later "
                 "stages again without simplifying again");
  app.add_flag("--progress", o.progress,
               "--job-out: print the job's progress on stderr (seconds since the start, stage, "
               "fraction, message)");
  app.add_flag("--json", json, "Print the JSON object (the only output format; kept for scripts)");
  CLI11_PARSE(app, argc, argv);
  if (!(o.min_psnr >= 0)) {  // NaN passes CLI::Range
    std::cerr << "decima-bench: --min-psnr: expected a PSNR floor in dB >= 0 (0 = none)\n";
    return 2;
  }

  if (!job_out.empty()) {
    if (o.original_from == "both") return RunWholeJobBothWays(o, job_out);
    Json out;
    const int rc = RunWholeJob(o, job_out, &out);
    if (rc == 0) std::cout << out.dump(2) << std::endl;
    return rc;
  }

  const std::vector<std::string> order = {"load", "segment", "tetra", "simplify", "render"};
  std::vector<std::string> requested = absl::StrSplit(stages_arg, ',', absl::SkipEmpty());
  for (const auto& s : requested) {
    if (std::find(order.begin(), order.end(), s) == order.end()) {
      std::cerr << "decima-bench: unknown stage '" << s
                << "' (known: " << absl::StrJoin(order, ", ") << ")\n";
      return 2;
    }
  }
  auto wants = [&](const std::string& s) {
    return s == "load" || std::find(requested.begin(), requested.end(), s) != requested.end();
  };
  // Later stages need the earlier products: simplify and render need a mesh.
  if ((wants("simplify") || wants("render")) && !wants("tetra")) requested.push_back("tetra");

  Json result;
  result["input"] = o.input;
  result["repeat"] = o.repeat;
  result["machine"] = {{"cores", std::thread::hardware_concurrency()},
                       {"load_average_1m_at_start", LoadAverage()}};
  BenchState state;
  for (const auto& stage : order) {
    if (!wants(stage)) continue;
    Json out;
    absl::Status s;
    if (stage == "load") s = RunLoad(o, state, out);
    if (stage == "segment") s = RunSegment(o, state, out);
    if (stage == "tetra") s = RunTetra(o, state, out);
    if (stage == "simplify") s = RunSimplify(o, state, out);
    if (stage == "render") s = RunRender(o, state, out);
    if (!s.ok()) {
      std::cerr << "decima-bench: stage " << stage << ": " << s << "\n";
      return 1;
    }
    result["stages"][stage] = out;
  }
  result["machine"]["load_average_1m_at_end"] = LoadAverage();
  result["peak_rss_mb"] = PeakRssMb();
  if (state.image.voxel_count() > 0) {
    result["bytes_per_voxel"] = PeakRssMb() * 1048576.0 / state.image.voxel_count();
  }
  std::cout << result.dump(2) << std::endl;
  return 0;
}

}  // namespace
}  // namespace decima

int main(int argc, char** argv) { return decima::Main(argc, argv); }
