// simplify-measure: the figures of core/simplify/README.md (not a ctest; the lead's decima-bench
// owns the product benchmark). Builds the mesh of a volume file or a noisy head phantom, with
// labels from a 3-class threshold (CT: < 500, < 1300, rest) or the phantom's truth, and the
// 0.5-voxel interface flags of the simplify tests; then, per policy and target reduction, runs
// Simplify `--repeat` times (median seconds) and MeasureFidelity once. One line per run.
//
//   simplify-measure --input ct.nii.gz --policy paper --reductions 0.1,0.2,0.5 --repeat 3
//   simplify-measure --phantom 128 --policy tetfusion --reductions 0.5 --no-metrics
// --lock 1 / --widen 0 / --refit N switch SimplifyOptions::lock_neighbours /
// widen_collapse_point / refit_iterations;
// MEASURE_PASSES=1 prints the per-pass statistics.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "core/io/volume_io.h"
#include "core/metrics/fidelity.h"
#include "core/simplify/simplify.h"
#include "tests/core/simplify/simplify_test_util.h"

namespace {

using decima::Volume;

double CpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * double(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

double PeakRssGb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_maxrss) / (1024.0 * 1024.0);
}

std::vector<double> ParseList(const char* s) {
  std::vector<double> out;
  while (*s) {
    char* end = nullptr;
    out.push_back(std::strtod(s, &end));
    s = *end == ',' ? end + 1 : end;
    if (end == s && *s) break;
  }
  return out;
}

int Run(int argc, char** argv) {
  std::string input, policy_name = "paper";
  int64_t phantom = 0;
  int repeat = 1, threads = 2, lock = -1, widen = 1, refit = -1;
  bool metrics = true;
  std::vector<double> reductions = {0.5};
  for (int i = 1; i < argc; ++i) {
    auto arg = [&](const char* name) { return std::strcmp(argv[i], name) == 0 && i + 1 < argc; };
    if (arg("--input")) {
      input = argv[++i];
    } else if (arg("--phantom")) {
      phantom = std::atoll(argv[++i]);
    } else if (arg("--policy")) {
      policy_name = argv[++i];
    } else if (arg("--reductions")) {
      reductions = ParseList(argv[++i]);
    } else if (arg("--repeat")) {
      repeat = std::atoi(argv[++i]);
    } else if (arg("--threads")) {
      threads = std::atoi(argv[++i]);
    } else if (arg("--lock")) {
      lock = std::atoi(argv[++i]);
    } else if (arg("--refit")) {
      refit = std::atoi(argv[++i]);
    } else if (arg("--widen")) {
      widen = std::atoi(argv[++i]);
    } else if (std::strcmp(argv[i], "--no-metrics") == 0) {
      metrics = false;
    } else {
      std::fprintf(stderr, "unknown argument %s\n", argv[i]);
      return 2;
    }
  }
  Volume image, labels;
  if (!input.empty()) {
    auto v = decima::io::ReadVolume(input);
    if (!v.ok()) {
      std::fprintf(stderr, "%s\n", v.status().ToString().c_str());
      return 1;
    }
    image = *std::move(v);
    labels = image;
    labels.type = decima::VoxelType::kUInt8;
    labels.bytes.assign(image.voxel_count(), 0);
    for (int64_t p = 0; p < image.voxel_count(); ++p) {
      const double x = image.ValueAt(p);
      labels.bytes[p] = x < 500 ? 0 : (x < 1300 ? 1 : 2);
    }
  } else {
    decima::HeadPhantomOptions o;
    o.dims = {phantom, phantom, phantom};
    o.region_means = {0, 1000, 400};
    o.noise_sigma = 40;
    o.seed = 7;
    auto p = decima::MakeHeadPhantom(o);
    if (!p.ok()) return 1;
    image = std::move(p->image);
    labels = std::move(p->labels);
  }
  const std::vector<float> dist = decima::testing::SimpleInterfaceDistance(labels);
  decima::TetrahedralizeOptions t;
  t.labels = &labels;
  t.interface_distance = dist.data();
  auto mesh = decima::Tetrahedralize(image, t);
  if (!mesh.ok()) return 1;
  int64_t features = 0;
  for (uint8_t f : mesh->vertex_flags) features += (f & decima::kFeatureVertex) != 0;
  std::printf("mesh: %lld vertices, %lld cells, %lld feature vertices, rss %.2f GB\n",
              (long long)mesh->vertex_count(), (long long)mesh->tet_count(), (long long)features,
              PeakRssGb());
  if (std::getenv("MEASURE_PASSES")) {
    // Cells by number of feature / exterior-boundary vertices: the paper's rules 2 and 5 keep
    // those with two or more unless a neighbour's collapse deletes them.
    int64_t by_feature[5] = {}, by_boundary[5] = {}, pinned_either = 0;
    for (int64_t c = 0; c < mesh->tet_count(); ++c) {
      int nf = 0, nb = 0;
      for (int k = 0; k < 4; ++k) {
        nf += (mesh->vertex_flags[mesh->tets[4 * c + k]] & decima::kFeatureVertex) != 0;
        nb += (mesh->vertex_flags[mesh->tets[4 * c + k]] & decima::kExteriorBoundaryVertex) != 0;
      }
      ++by_feature[nf], ++by_boundary[nb];
      pinned_either += nf >= 2 || nb >= 2;
    }
    std::printf(
        "cells by feature vertices 0..4: %lld %lld %lld %lld %lld; by boundary vertices: "
        "%lld %lld %lld %lld %lld; >= 2 of either: %lld\n",
        (long long)by_feature[0], (long long)by_feature[1], (long long)by_feature[2],
        (long long)by_feature[3], (long long)by_feature[4], (long long)by_boundary[0],
        (long long)by_boundary[1], (long long)by_boundary[2], (long long)by_boundary[3],
        (long long)by_boundary[4], (long long)pinned_either);
  }
  std::fflush(stdout);

  for (double reduction : reductions) {
    decima::SimplifyOptions o;
    const auto policy = decima::ParseSimplifyPolicy(policy_name);
    if (!policy) {
      std::fprintf(stderr, "unknown policy %s\n", policy_name.c_str());
      return 2;
    }
    o.policy = *policy;
    o.target_reduction = reduction;
    o.threads = threads;
    if (lock >= 0) o.lock_neighbours = lock != 0;
    o.widen_collapse_point = widen != 0;
    if (refit >= 0) o.refit_iterations = refit;
    std::vector<double> secs, cpu;
    absl::StatusOr<decima::SimplifyResult> r;
    for (int k = 0; k < repeat; ++k) {
      r = decima::SimplifyResult{};
      const auto t0 = std::chrono::steady_clock::now();
      const double c0 = CpuSeconds();
      r = decima::Simplify(*mesh, o);
      secs.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
      cpu.push_back(CpuSeconds() - c0);
      if (!r.ok()) {
        std::fprintf(stderr, "%s\n", r.status().ToString().c_str());
        return 1;
      }
    }
    std::sort(secs.begin(), secs.end());
    std::sort(cpu.begin(), cpu.end());
    const double median = secs[secs.size() / 2];
    const int64_t removed = r->input_cells - r->output_cells;
    std::printf(
        "%s target %.2f: reached %.4f (%s) passes %d, %.3f s (median of %d), "
        "cpu %.3f s, %.2f M cells/s, rss %.2f GB | %s\n",
        policy_name.c_str(), reduction, r->achieved_reduction, r->reached_target ? "yes" : "no",
        r->passes, median, repeat, cpu[cpu.size() / 2], double(removed) / median / 1e6, PeakRssGb(),
        r->stop_message.c_str());
    if (std::getenv("MEASURE_PASSES")) {
      for (const auto& ps : r->pass_stats) {
        std::printf(
            "  pass: candidates %lld collapses %lld removed %lld flip %lld rule4 %lld "
            "requeued %lld other-point %lld\n",
            (long long)ps.candidates, (long long)ps.collapses, (long long)ps.cells_removed,
            (long long)ps.rejected_flip, (long long)ps.rejected_rule4, (long long)ps.requeued,
            (long long)ps.other_point);
      }
    }
    std::fflush(stdout);
    if (!metrics) continue;
    decima::FidelityOptions fo;
    fo.labels = &labels;
    fo.original = &*mesh;
    fo.vertex_map = &r->vertex_map;
    fo.threads = threads;
    auto f = decima::MeasureFidelity(image, r->mesh, fo);
    if (!f.ok()) {
      std::fprintf(stderr, "%s\n", f.status().ToString().c_str());
      return 1;
    }
    std::printf("  psnr %.2f dB, rmse %.2f, interface rmse %.2f, max %.1f, coverage %.6f, dice",
                f->psnr_db, f->rmse, f->interface_rmse, f->max_abs_error, f->coverage);
    for (const auto& d : f->dice) std::printf(" %d:%.4f", d.label, d.dice);
    std::printf(
        ", features moved %lld removed %lld, inverted %lld, degenerate %lld, "
        "min dihedral %.2f deg\n",
        (long long)f->feature_vertices_moved, (long long)f->feature_vertices_removed,
        (long long)f->inverted_cells, (long long)f->degenerate_cells, f->min_dihedral_deg);
    std::fflush(stdout);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) { return Run(argc, argv); }
