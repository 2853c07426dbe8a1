// segment_figures: measures Segment on one input for the closing note of issue 3 (median of
// --repeat runs, peak RSS), and writes the montage. Not a test; decima-bench owns the product
// benchmark.
//
//   segment_figures INPUT [--regions K] [--repeat N] [--threads T] [--nu V] [--beta B]
//                   [--alpha A] [--reinit N] [--max-iterations N] [--png PATH] [--verbose 1]
//   INPUT: a volume file io::ReadVolume reads (NIfTI, MetaImage, NRRD,
//   DICOM folder), "head:N" (N^3 noisy 3-region head phantom) or "fig1"
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <string>

#include "core/io/volume_io.h"
#include "core/segment/montage.h"
#include "core/segment/segment.h"
#include "core/volume/phantom.h"

namespace {

double PeakRssMb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss / 1024.0;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace decima;
  if (argc < 2) {
    std::cerr << "usage: segment_figures INPUT [--regions K] [--repeat N] [--threads T] [--nu V] "
                 "[--beta B] [--png PATH] [--max-iterations N] [--threshold T] [--verbose 1]\n";
    return 2;
  }
  std::string input = argv[1], png;
  SegmentOptions o;
  int repeat = 3;
  bool verbose = false;  // print (iteration, energy, changed fraction) of every iteration
  for (int a = 2; a + 1 < argc; a += 2) {
    const std::string k = argv[a];
    const char* v = argv[a + 1];
    if (k == "--regions")
      o.regions = std::atoi(v);
    else if (k == "--repeat")
      repeat = std::atoi(v);
    else if (k == "--threads")
      o.threads = std::atoi(v);
    else if (k == "--nu")
      o.curvature_weight = std::atof(v);
    else if (k == "--beta")
      o.overlap_weight = std::atof(v);
    else if (k == "--alpha")
      o.alpha = std::atof(v);
    else if (k == "--reinit")
      o.reinit_interval = std::atoi(v);
    else if (k == "--threshold")
      o.convergence_threshold = std::atof(v);
    else if (k == "--max-iterations")
      o.max_iterations = std::atoi(v);
    else if (k == "--png")
      png = v;
    else if (k == "--verbose")
      verbose = std::atoi(v) != 0;
    else {
      std::cerr << "unknown option " << k << "\n";
      return 2;
    }
  }
  Volume image;
  Volume truth;
  if (input == "fig1") {
    GaussianBlobsOptions b;  // as in the Fig. 1 acceptance test (run it with --nu 4 --beta 5)
    b.mean1 = 115;
    auto p = MakeGaussianBlobsPhantom(b);
    image = p->image;
    truth = p->labels;
  } else if (input.rfind("head:", 0) == 0) {
    const int64_t n = std::atoll(input.c_str() + 5);
    HeadPhantomOptions h;
    h.dims = {n, n, n};
    h.region_means = {0, 1000, 400};
    h.noise_sigma = 150;
    auto p = MakeHeadPhantom(h);
    if (!p.ok()) {
      std::cerr << p.status() << "\n";
      return 1;
    }
    image = std::move(p->image);
  } else {
    auto v = io::ReadVolume(input);
    if (!v.ok()) {
      std::cerr << v.status() << "\n";
      return 1;
    }
    image = *std::move(v);
  }
  const double rss_input = PeakRssMb();
  std::cout << "input " << Describe(image) << ", peak RSS after load " << rss_input << " MB\n";
  std::vector<double> seconds;
  absl::StatusOr<SegmentResult> r;
  for (int i = 0; i < repeat; ++i) {
    r = absl::StatusOr<SegmentResult>();  // free the previous result first
    const auto t0 = std::chrono::steady_clock::now();
    r = Segment(
        image, o,
        [&](const Progress& p) {
          if (verbose && i == 0 && p.metrics.size() >= 5)  // not the set-up's reports
            std::printf(
                "  iteration %g energy %.6g changed %.3g of volume, %.3g of interface, "
                "%g by the previous re-initialization\n",
                p.metrics[0].second, p.metrics[1].second, p.metrics[2].second, p.metrics[3].second,
                p.metrics[4].second);
        },
        nullptr);
    seconds.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    if (!r.ok()) {
      std::cerr << r.status() << "\n";
      return 1;
    }
  }
  std::vector<double> sorted = seconds;
  std::sort(sorted.begin(), sorted.end());
  const double rss = PeakRssMb();
  const double extra_per_voxel = (rss - rss_input) * 1024 * 1024 / image.voxel_count();
  std::printf("seconds median %.3f (runs:", sorted[sorted.size() / 2]);
  for (double s : seconds) std::printf(" %.3f", s);
  std::printf(")\niterations %d converged %d energy %.6g sigma %.3g\n", r->iterations, r->converged,
              r->energy, r->within_class_sigma);
  std::printf("peak RSS %.1f MB, %.2f bytes/voxel beyond the input = %.2f floats (K+3 = %d)\n", rss,
              extra_per_voxel, extra_per_voxel / 4, o.regions + 3);
  for (size_t i = 0; i < r->class_means.size(); ++i) {
    std::printf("region %zu: mean %.1f, %lld voxels, %.1f ml\n", i, r->class_means[i],
                static_cast<long long>(r->region_voxels[i]), r->region_volumes_mm3[i] / 1000);
  }
  if (truth.voxel_count() > 0) {
    for (int reg = 0; reg < o.regions; ++reg) {
      int64_t both = 0, a = 0, b = 0;
      for (int64_t x = 0; x < truth.voxel_count(); ++x) {
        const bool s = r->labels.data<uint8_t>()[x] == reg, t = truth.data<uint8_t>()[x] == reg;
        both += s && t;
        a += s;
        b += t;
      }
      std::printf("Dice region %d: %.4f\n", reg, 2.0 * both / (a + b));
    }
  }
  if (!png.empty()) {
    auto s = WriteSegmentationMontage(image, r->labels, png);
    if (!s.ok()) std::cerr << s << "\n";
  }
  return 0;
}
