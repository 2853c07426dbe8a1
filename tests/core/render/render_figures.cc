// render_figures: the renderer's figures on the CT head (not a ctest; run by hand).
//
//   render_figures OUT_DIR [--data FILE] [--size 512] [--view anterior] [--tf ct|FILE.json]
//                  [--repeat 3]
//                  [--threads 2] [--fig5] [--perspective] [--render-only] [--downsample N]
//
// Reads the volume, meshes it (labels: 3-class threshold < 500, < 1300, rest; feature flags
// from a 0.5-voxel interface distance, as tests/core/simplify), then prints the median of
// `repeat` timings of BuildRenderableMesh and Render, writes original.png, simplifies 50 % with
// both policies and writes <policy>-diff2.png and <policy>-comparison.png with their diff1, and
// with --fig5 the paper's Fig. 5 (diff1 against cells removed, 10..50 %) as fig5.png.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <string>
#include <vector>

#include "core/io/volume_io.h"
#include "core/mesh/tetrahedralize.h"
#include "core/render/diff.h"
#include "core/render/plot.h"
#include "core/render/renderer.h"
#include "core/simplify/simplify.h"

namespace {

using namespace decima;
using Clock = std::chrono::steady_clock;

// CPU seconds of the whole process (all threads): with other jobs on the machine, wall time
// alone over-states the cost; cpu / threads is what an idle machine would show.
double CpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

void Die(const absl::Status& s) {
  std::fprintf(stderr, "error: %s\n", s.ToString().c_str());
  std::exit(1);
}

template <typename T>
T Must(absl::StatusOr<T> v) {
  if (!v.ok()) Die(v.status());
  return *std::move(v);
}

// 0.5 for a voxel with a 6-neighbour of another label, 1.5 otherwise (voxels).
std::vector<float> InterfaceDistance(const Volume& labels) {
  const int64_t nx = labels.dims[0], ny = labels.dims[1], nz = labels.dims[2];
  const uint8_t* l = labels.data<uint8_t>();
  std::vector<float> d(labels.voxel_count(), 1.5f);
  for (int64_t k = 0; k < nz; ++k)
    for (int64_t j = 0; j < ny; ++j)
      for (int64_t i = 0; i < nx; ++i) {
        const int64_t p = i + nx * (j + ny * k);
        const bool edge = (i > 0 && l[p - 1] != l[p]) || (i + 1 < nx && l[p + 1] != l[p]) ||
                          (j > 0 && l[p - nx] != l[p]) || (j + 1 < ny && l[p + nx] != l[p]) ||
                          (k > 0 && l[p - nx * ny] != l[p]) ||
                          (k + 1 < nz && l[p + nx * ny] != l[p]);
        if (edge) d[p] = 0.5f;
      }
  return d;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr,
                 "usage: %s OUT_DIR [--data FILE] [--size N] [--view NAME] [--tf NAME|FILE.json] "
                 "[--repeat N] "
                 "[--threads N] [--fig5] [--perspective] [--render-only] [--downsample N]\n",
                 argv[0]);
    return 2;
  }
  const std::filesystem::path out = argv[1];
  std::string data;
  if (const char* d = std::getenv("DECIMA_SHARED_DATA")) data = std::string(d) + "/";
  data += "ct-head-128x128x53.nii.gz";
  int size = 512, repeat = 3, threads = 2, downsample = 1;
  std::string view = "anterior", tf_name = "ct";
  bool fig5 = false, perspective = false, simplify = true;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) Die(absl::InvalidArgumentError(a + " needs a value"));
      return argv[++i];
    };
    if (a == "--data")
      data = next();
    else if (a == "--size")
      size = std::stoi(next());
    else if (a == "--view")
      view = next();
    else if (a == "--tf")
      tf_name = next();
    else if (a == "--downsample")
      downsample = std::max(1, std::stoi(next()));
    else if (a == "--repeat")
      repeat = std::max(1, std::stoi(next()));
    else if (a == "--threads")
      threads = std::stoi(next());
    else if (a == "--fig5")
      fig5 = true;
    else if (a == "--perspective")
      perspective = true;
    else if (a == "--render-only")
      simplify = false;
    else
      Die(absl::InvalidArgumentError("unknown option " + a));
  }
  std::filesystem::create_directories(out);

  Volume vol = Must(io::ReadVolume(data));
  if (downsample > 1) {
    // Every n-th voxel (for large MRIs such as Colin27: 35 M tets at full size).
    std::array<int64_t, 3> d;
    for (int a = 0; a < 3; ++a) d[a] = (vol.dims[a] + downsample - 1) / downsample;
    std::vector<float> v(d[0] * d[1] * d[2]);
    for (int64_t k = 0; k < d[2]; ++k)
      for (int64_t j = 0; j < d[1]; ++j)
        for (int64_t i = 0; i < d[0]; ++i)
          v[i + d[0] * (j + d[1] * k)] = static_cast<float>(
              vol.ValueAt(vol.Index(i * downsample, j * downsample, k * downsample)));
    Volume small = Must(MakeFloatVolume(d, std::move(v)));
    small.spacing = vol.spacing * downsample;
    small.origin = vol.origin;
    small.direction = vol.direction;
    vol = std::move(small);
  }
  Volume labels = Must(MakeVolume(vol.dims, VoxelType::kUInt8));
  labels.spacing = vol.spacing;
  labels.origin = vol.origin;
  labels.direction = vol.direction;
  for (int64_t i = 0; i < vol.voxel_count(); ++i) {
    const double v = vol.ValueAt(i);
    labels.mutable_data<uint8_t>()[i] = v < 500 ? 0 : v < 1300 ? 1 : 2;
  }
  const std::vector<float> dist = InterfaceDistance(labels);
  TetrahedralizeOptions topt;
  topt.labels = &labels;
  topt.interface_distance = dist.data();
  topt.threads = threads;
  const TetMesh mesh = Must(Tetrahedralize(vol, topt));
  std::printf("mesh: %lld vertices, %lld tets\n", (long long)mesh.vertex_count(),
              (long long)mesh.tet_count());

  RenderableMeshOptions bopt;
  bopt.threads = threads;
  std::vector<double> build_s, build_cpu;
  RenderableMesh original;
  for (int r = 0; r < repeat; ++r) {
    const auto t0 = Clock::now();
    const double c0 = CpuSeconds();
    original = RenderableMesh();
    original = Must(BuildRenderableMesh(mesh, bopt));
    build_cpu.push_back(CpuSeconds() - c0);
    build_s.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
  }
  std::printf(
      "BuildRenderableMesh: %.3f s wall, %.3f s cpu (medians of %d, %d threads), %zu boundary "
      "faces\n",
      Median(build_s), Median(build_cpu), repeat, threads, original.boundary_faces.size());

  ViewOptions vopt;
  vopt.width = vopt.height = size;
  vopt.perspective = perspective;
  const Camera cam = Must(MakeViewCamera(Must(ParseView(view)), original.bounds, vopt));
  // A preset name, or a JSON file in the transfer_function.h format.
  const TransferFunction tf = tf_name.find(".json") != std::string::npos
                                  ? Must(LoadTransferFunction(tf_name, original.scalar_range))
                                  : Must(TransferFunctionPreset(tf_name, original.scalar_range));
  RenderOptions ropt;
  ropt.threads = threads;
  std::vector<double> render_s, render_cpu;
  RenderedImage img;
  for (int r = 0; r < repeat; ++r) {
    const double c0 = CpuSeconds();
    img = Must(Render(original, cam, tf, ropt));
    render_cpu.push_back(CpuSeconds() - c0);
    render_s.push_back(img.stats.seconds);
  }
  std::printf(
      "Render %dx%d %s %s: %.3f s wall, %.3f s cpu (medians of %d, %d threads; raster %.3f s), "
      "visible tets %lld, entries %lld, rays %lld, steps %lld, fallback %lld, lost %lld\n",
      size, size, view.c_str(), perspective ? "perspective" : "orthographic", Median(render_s),
      Median(render_cpu), repeat, threads, img.stats.raster_seconds,
      (long long)img.stats.visible_tets, (long long)img.stats.entry_faces,
      (long long)img.stats.rays_hit, (long long)img.stats.steps,
      (long long)img.stats.fallback_steps, (long long)img.stats.lost_rays);
  if (auto s = WriteRenderedPng(img, out / "original.png"); !s.ok()) Die(s);

  struct Policy {
    const char* name;
    SimplifyPolicy policy;
  };
  const Policy policies[] = {{"paper", SimplifyPolicy::kPaper},
                             {"tetfusion", SimplifyPolicy::kTetFusion}};
  std::vector<PlotSeries> series;
  for (const Policy& p : policies) {
    if (!simplify) break;
    PlotSeries ser{p.policy == SimplifyPolicy::kPaper ? "paper" : "TetFusion", {{0, 0}}};
    std::vector<double> targets = {0.5};
    if (fig5) targets = {0.1, 0.2, 0.3, 0.4, 0.5};
    for (double target : targets) {
      SimplifyOptions sopt;
      sopt.policy = p.policy;
      sopt.target_reduction = target;
      sopt.threads = threads;
      const auto t0 = Clock::now();
      const SimplifyResult res = Must(Simplify(mesh, sopt));
      const double simplify_s = std::chrono::duration<double>(Clock::now() - t0).count();
      const RenderableMesh rm = Must(BuildRenderableMesh(res.mesh, bopt));
      const RenderedImage simg = Must(Render(rm, cam, tf, ropt));
      const DiffResult d = Must(Diff(img, simg));
      const int64_t removed = res.input_cells - res.output_cells;
      std::printf(
          "%s target %.0f%%: removed %lld cells (%.1f%%, %s) in %.1f s; diff1 %.4f, max diff2 "
          "%.1f, changed pixels %lld; render %.3f s, lost %lld\n",
          p.name, 100 * target, (long long)removed, 100 * res.achieved_reduction,
          res.reached_target ? "reached" : res.stop_message.c_str(), simplify_s, d.diff1,
          d.max_diff2, (long long)d.changed_pixels, simg.stats.seconds,
          (long long)simg.stats.lost_rays);
      ser.points.push_back({double(removed), d.diff1});
      if (target == 0.5) {
        const std::string base = p.name;
        if (auto s = WriteRenderedPng(simg, out / (base + "-50.png")); !s.ok()) Die(s);
        if (auto s = WriteDiffImage(d, out / (base + "-diff2.png")); !s.ok()) Die(s);
        if (auto s = WriteComparison(img, simg, d, out / (base + "-comparison.png")); !s.ok())
          Die(s);
      }
    }
    series.push_back(std::move(ser));
  }
  if (fig5) {
    PlotOptions po;
    po.title = "CT head: diff1 vs cells removed";
    if (auto s = WriteDiffPlot(series, out / "fig5.png", po); !s.ok()) Die(s);
  }
  std::printf("images in %s\n", out.c_str());
  return 0;
}
