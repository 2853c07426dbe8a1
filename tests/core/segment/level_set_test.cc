// Multiphase level set (paper §2.1): the acceptance tests of issue 3 on phantoms with ground
// truth, plus parameter validation, cancellation, progress and determinism.
#include <algorithm>
#include <cmath>
#include <queue>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/segment/internal.h"
#include "core/segment/segment.h"
#include "core/volume/phantom.h"

namespace decima {
namespace {

// Segment's set-up reports (k-means, initial level sets) carry iteration 0, before the first.
bool IsSetupReport(const Progress& p) { return p.metrics.at(0).second == 0; }

// Dice of region `a` in `seg` against region `b` in `truth`.
double Dice(const Volume& seg, int a, const Volume& truth, int b) {
  int64_t both = 0, ns = 0, nt = 0;
  for (int64_t x = 0; x < seg.voxel_count(); ++x) {
    const bool s = seg.data<uint8_t>()[x] == a, t = truth.data<uint8_t>()[x] == b;
    both += s && t;
    ns += s;
    nt += t;
  }
  return ns + nt == 0 ? 1.0 : 2.0 * both / static_cast<double>(ns + nt);
}

// For every truth region r (mean truth_means[r]), the Dice of the segmented region whose class
// mean is nearest.
std::vector<double> DicePerRegion(const Volume& seg, const std::vector<double>& seg_means,
                                  const Volume& truth, const std::vector<double>& truth_means) {
  std::vector<double> out;
  for (size_t r = 0; r < truth_means.size(); ++r) {
    int best = 0;
    for (size_t s = 1; s < seg_means.size(); ++s)
      if (std::abs(seg_means[s] - truth_means[r]) < std::abs(seg_means[best] - truth_means[r]))
        best = static_cast<int>(s);
    out.push_back(Dice(seg, best, truth, static_cast<int>(r)));
  }
  return out;
}

double Min(const std::vector<double>& v) { return *std::min_element(v.begin(), v.end()); }

// ---------------------------------------------------------------------------------------------
// The gradient-magnitude baseline of the paper's Fig. 1b, made as strong as we fairly can:
// optional Gaussian pre-smoothing, |grad I| by central differences, threshold -> edge pixels;
// background = non-edge pixels 4-connected to the image border, region 1 = the rest (enclosed
// components and the edges themselves). The best Dice over every smoothing and threshold
// tried is reported, i.e. the baseline even gets to pick its parameters by the truth.
std::vector<float> Smooth2D(const std::vector<float>& in, int nx, int ny, double sigma) {
  if (sigma <= 0) return in;
  const int r = static_cast<int>(std::ceil(3 * sigma));
  std::vector<double> w(2 * r + 1);
  double sum = 0;
  for (int t = -r; t <= r; ++t) sum += w[t + r] = std::exp(-0.5 * t * t / (sigma * sigma));
  for (double& v : w) v /= sum;
  std::vector<float> tmp(in.size()), out(in.size());
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x) {
      double s = 0;
      for (int t = -r; t <= r; ++t) s += w[t + r] * in[y * nx + std::clamp(x + t, 0, nx - 1)];
      tmp[y * nx + x] = static_cast<float>(s);
    }
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x) {
      double s = 0;
      for (int t = -r; t <= r; ++t) s += w[t + r] * tmp[std::clamp(y + t, 0, ny - 1) * nx + x];
      out[y * nx + x] = static_cast<float>(s);
    }
  return out;
}

double BestGradientThresholdDice(const Phantom& p) {
  const int nx = static_cast<int>(p.image.dims[0]), ny = static_cast<int>(p.image.dims[1]);
  const std::vector<float> img = p.image.ToFloat();
  double best = 0;
  for (double sigma : {0.0, 1.0, 2.0, 3.0}) {
    const std::vector<float> s = Smooth2D(img, nx, ny, sigma);
    std::vector<float> grad(s.size(), 0.f);
    for (int y = 1; y + 1 < ny; ++y)
      for (int x = 1; x + 1 < nx; ++x) {
        const float gx = 0.5f * (s[y * nx + x + 1] - s[y * nx + x - 1]);
        const float gy = 0.5f * (s[(y + 1) * nx + x] - s[(y - 1) * nx + x]);
        grad[y * nx + x] = std::sqrt(gx * gx + gy * gy);
      }
    std::vector<float> sorted = grad;
    std::sort(sorted.begin(), sorted.end());
    for (int pct = 50; pct <= 99; ++pct) {
      const float thr = sorted[sorted.size() * pct / 100];
      std::vector<uint8_t> lab(grad.size(), 1);
      std::queue<int> q;
      for (int y = 0; y < ny; ++y)
        for (int x = 0; x < nx; ++x)
          if ((x == 0 || y == 0 || x == nx - 1 || y == ny - 1) && grad[y * nx + x] <= thr) {
            lab[y * nx + x] = 0;
            q.push(y * nx + x);
          }
      while (!q.empty()) {
        const int v = q.front();
        q.pop();
        const int x = v % nx, y = v / nx;
        const int nbr[4][2] = {{x - 1, y}, {x + 1, y}, {x, y - 1}, {x, y + 1}};
        for (const auto& nb : nbr) {
          if (nb[0] < 0 || nb[1] < 0 || nb[0] >= nx || nb[1] >= ny) continue;
          const int u = nb[1] * nx + nb[0];
          if (lab[u] == 1 && grad[u] <= thr) {
            lab[u] = 0;
            q.push(u);
          }
        }
      }
      Volume seg = p.labels;
      std::copy(lab.begin(), lab.end(), seg.mutable_data<uint8_t>());
      best = std::max(best, std::min(Dice(seg, 0, p.labels, 0), Dice(seg, 1, p.labels, 1)));
    }
  }
  return best;
}

// The paper's Fig. 1 in 2D: a 96x96x1 volume (one slice; the level set is 3D, and a flat axis
// behaves as 2D through the zero-flux border).
//
// Why these parameters: Fig. 1's premise is two regions whose intensity distributions overlap,
// so no single voxel (and no local gradient) tells them apart. With the means 100 / 115 and
// sigma 20 the contrast is 0.75 sigma: the two histograms overlap by ~70 %, the border's step is
// smaller than the typical difference between two neighbouring noise samples, and even after
// Gaussian smoothing (sigma <= 3 px) the gradient of the noise competes with the border's. At
// the phantom's old default (means 100 / 130, contrast 1.5 sigma) a smoothed gradient already
// found the disc (Dice 0.93): the distributions barely overlapped after smoothing, so that
// image did not show what Fig. 1 shows.
// The level set gets two constants set for this image, as the paper sets its nu_i and beta per
// dataset: at 0.75 sigma contrast the fitting term of a single voxel is mostly noise, so the
// length weight must be larger than the default tuned for CT/MRI tissue contrasts (nu = 4), and
// the non-overlap weight must exceed the fitting force of a noisy voxel (beta = 5); with the
// default beta = 1 the noise inside the weak disc opens vacuum holes that grow over a long run.
// The Dice threshold of the level set is unchanged (>= 0.95 for both regions). The stop
// criterion is tightened too (see below).
TEST(SegmentAcceptance, Fig1LevelSetRecoversGaussianBlobsWhereGradientThresholdFails) {
  GaussianBlobsOptions o;  // 96x96x1, seed 1
  o.mean0 = 100;
  o.mean1 = 115;
  o.sigma = 20;
  auto p = MakeGaussianBlobsPhantom(o);
  ASSERT_TRUE(p.ok());
  SegmentOptions so;
  so.regions = 2;
  so.curvature_weight = 4;
  so.overlap_weight = 5;
  so.max_iterations = 600;
  // The default stop (0.4 % of the interface per iteration) is one pixel of the ~250-face
  // interface of this 96x96 slice: it stops the slow low-contrast evolution after ~195
  // iterations at Dice 0.946. 1e-3 means "no label changes", reached after ~400 iterations.
  so.convergence_threshold = 1e-3;
  auto r = Segment(p->image, so, nullptr, nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  const std::vector<double> dice =
      DicePerRegion(r->labels, r->class_means, p->labels, {o.mean0, o.mean1});
  const double gradient = BestGradientThresholdDice(*p);
  std::cout << "Fig.1: level set Dice " << dice[0] << " / " << dice[1] << " in " << r->iterations
            << " iterations (converged " << r->converged << "); best gradient threshold Dice "
            << gradient << "\n";
  EXPECT_GE(Min(dice), 0.95);
  EXPECT_TRUE(r->converged);
  EXPECT_LT(gradient, Min(dice) - 0.1) << "the gradient baseline is not clearly worse";
}

struct HeadCase {
  HeadPhantomOptions options;
  Phantom phantom;
};

HeadCase NoisyHead(std::array<int64_t, 3> dims = {48, 48, 48}) {
  HeadCase c;
  c.options.dims = dims;
  c.options.region_means = {0, 1000, 400};  // neighbours 0|1000 and 1000|400: smallest 600
  c.options.noise_sigma = 0.25 * 600;
  c.options.seed = 3;
  auto p = MakeHeadPhantom(c.options);
  EXPECT_TRUE(p.ok());
  c.phantom = *std::move(p);
  return c;
}

TEST(SegmentAcceptance, HeadPhantomThreeRegionsBeatsKMeans) {
  HeadCase c = NoisyHead();
  SegmentOptions so;
  so.regions = 3;
  auto r = Segment(c.phantom.image, so, nullptr, nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  auto km = KMeansIntensities(c.phantom.image, 3);
  ASSERT_TRUE(km.ok());
  const auto dls =
      DicePerRegion(r->labels, r->class_means, c.phantom.labels, c.options.region_means);
  const auto dkm = DicePerRegion(km->labels, km->means, c.phantom.labels, c.options.region_means);
  for (int i = 0; i < 3; ++i) {
    std::cout << "region " << i << ": level set Dice " << dls[i] << ", k-means " << dkm[i] << "\n";
    EXPECT_GE(dls[i], 0.95) << "region " << i;
    EXPECT_GT(dls[i], dkm[i]) << "region " << i;
  }
  EXPECT_TRUE(r->converged) << r->iterations << " iterations";
}

TEST(Segment, NoiseFreePhantomIsRecoveredExactly) {
  HeadPhantomOptions o;
  o.dims = {32, 28, 20};
  o.spacing = {1, 1, 2};
  o.region_means = {10, 200, 120, 60};
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok());
  SegmentOptions so;
  so.regions = 4;
  auto r = Segment(p->image, so, nullptr, nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  const auto d = DicePerRegion(r->labels, r->class_means, p->labels, o.region_means);
  for (double v : d) EXPECT_GE(v, 0.999);
  EXPECT_TRUE(r->converged);
  int64_t total = 0;
  for (int64_t v : r->region_voxels) total += v;
  EXPECT_EQ(total, p->image.voxel_count());
  EXPECT_DOUBLE_EQ(r->region_volumes_mm3[0], r->region_voxels[0] * 2.0);
}

TEST(Segment, GivenClassMeansStayFixedAndOrderTheRegions) {
  HeadCase c = NoisyHead({32, 32, 32});
  SegmentOptions so;
  so.regions = 3;
  so.class_means = {1000, 0, 400};  // region 0 = the bright shell
  auto r = Segment(c.phantom.image, so, nullptr, nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->class_means, so.class_means);
  EXPECT_GE(Dice(r->labels, 0, c.phantom.labels, 1), 0.95);
  EXPECT_GE(Dice(r->labels, 1, c.phantom.labels, 0), 0.95);
}

TEST(Segment, ZeroIterationsReturnsTheKMeansPartition) {
  HeadCase c = NoisyHead({24, 24, 24});
  SegmentOptions so;
  so.max_iterations = 0;
  auto r = Segment(c.phantom.image, so, nullptr, nullptr);
  auto km = KMeansIntensities(c.phantom.image, 3);
  ASSERT_TRUE(r.ok() && km.ok());
  EXPECT_EQ(r->labels.bytes, km->labels.bytes);
  EXPECT_EQ(r->iterations, 0);
}

TEST(Segment, ReportsEveryIterationAndStopsWithinOneIterationWhenCancelled) {
  HeadCase c = NoisyHead({32, 32, 32});
  SegmentOptions so;
  so.convergence_threshold = 0;  // never converges: only the cancel can stop it early
  CancelToken token;
  int calls = 0, calls_after_cancel = 0;
  std::vector<double> iterations;
  auto r = Segment(
      c.phantom.image, so,
      [&](const Progress& p) {
        EXPECT_EQ(p.stage, "segment");
        ASSERT_FALSE(p.metrics.empty());
        if (IsSetupReport(p)) return;
        ++calls;
        if (token.cancelled()) ++calls_after_cancel;
        ASSERT_EQ(p.metrics.size(), 6u);
        EXPECT_EQ(p.metrics[0].first, "iteration");
        EXPECT_EQ(p.metrics[2].first, "changed_fraction");
        EXPECT_GE(p.metrics[2].second, 0.0);
        EXPECT_LE(p.metrics[2].second, 1.0);
        EXPECT_EQ(p.metrics[3].first, "interface_changed_fraction");
        EXPECT_EQ(p.metrics[4].first, "reinit_changed_labels");
        EXPECT_EQ(p.metrics[5].first, "expected_iterations");
        iterations.push_back(p.metrics[0].second);
        if (p.metrics[0].second == 2) token.Cancel();
      },
      &token);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled) << r.status();
  EXPECT_LE(calls_after_cancel, 1);
  EXPECT_EQ(iterations, (std::vector<double>{1, 2}));
}

TEST(Segment, CancelledBeforeStartReturnsCancelled) {
  HeadCase c = NoisyHead({16, 16, 16});
  CancelToken token;
  token.Cancel();
  auto r = Segment(c.phantom.image, SegmentOptions{}, nullptr, &token);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled);
}

TEST(Segment, SameLabelsWithOneAndTwoThreads) {
  HeadCase c = NoisyHead({40, 36, 30});
  SegmentOptions so;
  so.threads = 1;
  auto a = Segment(c.phantom.image, so, nullptr, nullptr);
  so.threads = 2;
  auto b = Segment(c.phantom.image, so, nullptr, nullptr);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->labels.bytes, b->labels.bytes);
  EXPECT_EQ(a->iterations, b->iterations);
  EXPECT_EQ(a->energy, b->energy);
  EXPECT_EQ(a->class_means, b->class_means);
}

// Re-initialization must keep the partition: every phi_i becomes the signed distance to the
// current region i, so argmax_i phi_i right after it equals the labels right before it. Segment
// relabels once after each re-initialization and reports how many labels that changed.
TEST(Segment, ReinitializationKeepsEveryLabelOnANoisyPhantom) {
  HeadCase c = NoisyHead({40, 40, 40});
  for (int interval : {1, 5}) {
    SegmentOptions so;
    so.reinit_interval = interval;
    so.max_iterations = 26;
    so.convergence_threshold = 0;  // run all 26 iterations: 5 or 25 re-initializations
    std::vector<double> reinit_changed;
    double moved = 0;
    auto r = Segment(
        c.phantom.image, so,
        [&](const Progress& p) {
          if (IsSetupReport(p)) return;
          moved += p.metrics[2].second;
          if (static_cast<int>(p.metrics[0].second) % interval == 1 || interval == 1)
            reinit_changed.push_back(p.metrics[4].second);
        },
        nullptr);
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_GT(moved, 0.0) << "the evolution did not move any label: nothing was tested";
    ASSERT_GE(reinit_changed.size(), 5u);
    for (size_t a = 0; a < reinit_changed.size(); ++a)
      EXPECT_EQ(reinit_changed[a], 0.0) << "interval " << interval << ", reinit " << a;
  }
}

// The stop is relative to the interface: the reported interface fraction is the changed labels
// over the voxel faces between different labels (counted here on the returned labels).
TEST(Segment, ConvergenceFractionIsRelativeToTheInterface) {
  HeadCase c = NoisyHead({32, 30, 28});
  SegmentOptions so;
  so.max_iterations = 1;
  double volume_fraction = -1, interface_fraction = -1;
  auto r = Segment(
      c.phantom.image, so,
      [&](const Progress& p) {
        if (IsSetupReport(p)) return;
        volume_fraction = p.metrics[2].second;
        interface_fraction = p.metrics[3].second;
      },
      nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  const auto& d = r->labels.dims;
  const uint8_t* l = r->labels.data<uint8_t>();
  int64_t faces = 0;
  for (int64_t z = 0; z < d[2]; ++z)
    for (int64_t y = 0; y < d[1]; ++y)
      for (int64_t x = 0; x < d[0]; ++x) {
        const int64_t i = x + d[0] * (y + d[1] * z);
        if (x + 1 < d[0]) faces += l[i] != l[i + 1];
        if (y + 1 < d[1]) faces += l[i] != l[i + d[0]];
        if (z + 1 < d[2]) faces += l[i] != l[i + d[0] * d[1]];
      }
  ASSERT_GT(faces, 0);
  const double changed = volume_fraction * r->labels.voxel_count();
  EXPECT_GT(changed, 0.5);
  EXPECT_NEAR(interface_fraction, changed / faces, 1e-9);
}

TEST(Segment, EnergyDecreasesOverall) {
  HeadCase c = NoisyHead({32, 32, 32});
  std::vector<double> energy;
  auto r = Segment(
      c.phantom.image, SegmentOptions{},
      [&](const Progress& p) {
        if (!IsSetupReport(p)) energy.push_back(p.metrics[1].second);
      },
      nullptr);
  ASSERT_TRUE(r.ok());
  ASSERT_GE(energy.size(), 3u);
  EXPECT_LT(energy.back(), energy.front());
}

// Issue 32, honest progress: the stage's fraction counts the iterations against a forecast of
// how many there will be (not against max_iterations, which a converging run never reaches), so
// it is past the middle when half the iterations are done and never goes backwards.
TEST(Segment, ProgressCountsIterationsAgainstTheForecastAndNeverGoesBack) {
  HeadCase c = NoisyHead({40, 40, 40});
  std::vector<double> fractions;
  std::vector<int> expected;
  std::vector<std::string> setup;
  auto r = Segment(
      c.phantom.image, SegmentOptions{},
      [&](const Progress& p) {
        fractions.push_back(p.fraction);
        if (IsSetupReport(p)) {
          setup.push_back(p.message);
        } else {
          expected.push_back(static_cast<int>(p.metrics[5].second));
        }
      },
      nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_TRUE(r->converged);
  const int n = r->iterations;
  ASSERT_GE(n, 6) << "too short a run to test a forecast";
  EXPECT_EQ(setup, (std::vector<std::string>{"k-means of the intensities", "initial level sets"}));
  for (size_t i = 1; i < fractions.size(); ++i) EXPECT_GE(fractions[i], fractions[i - 1]) << i;
  EXPECT_GE(fractions.back(), 0.95);
  EXPECT_LT(fractions.back(), 1.0);
  // Half-way through the iterations the bar is well past the start (0.27 here against 0.07 when
  // it counted against max_iterations = 300), and from three quarters on the forecast is within
  // a factor of two of the truth.
  const double half = fractions[setup.size() + n / 2 - 1];
  EXPECT_GT(half, 0.2) << n << " iterations";
  for (int i = 3 * n / 4; i <= n; ++i) {
    EXPECT_GE(expected[i - 1], i);
    EXPECT_LE(expected[i - 1], 2 * n) << "iteration " << i;
  }
  EXPECT_EQ(expected.back(), n);
}

TEST(Segment, TheForecastFollowsTheDecayAndFallsBackToTheLimit) {
  using segment_internal::ForecastIterations;
  SegmentOptions o;  // threshold 4e-3, window 3, at most 300
  EXPECT_EQ(ForecastIterations({}, 0, o), 300);
  EXPECT_EQ(ForecastIterations({0.5, 0.4, 0.3}, 0, o), 300) << "too few values for a rate";
  EXPECT_EQ(ForecastIterations({0.2, 0.2, 0.2, 0.2}, 0, o), 300) << "no decay, no forecast";
  // Halving every iteration (the first value is left out): 0.05 is below 0.004 after 4 more
  // (0.003125), then the quiet window.
  EXPECT_EQ(ForecastIterations({0.01, 0.2, 0.1, 0.05}, 0, o), 4 + 4 + 3);
  // A spike (a re-initialization) among the halvings moves the forecast by little.
  const int spiked = ForecastIterations({0.01, 0.4, 0.2, 0.1, 0.3, 0.025}, 0, o);
  EXPECT_GE(spiked, 6 + 2);
  EXPECT_LE(spiked, 6 + 8);
  EXPECT_EQ(ForecastIterations({0.001}, 1, o), 300) << "a quiet first iteration says little";
  EXPECT_EQ(ForecastIterations({0.01, 0.2, 0.1, 0.003}, 1, o), 4 + 2) << "in the quiet window";
  EXPECT_EQ(ForecastIterations({0.01, 0.003, 0.002, 0.001}, 3, o), 4) << "converged";
  o.max_iterations = 8;
  EXPECT_EQ(ForecastIterations({0.01, 0.2, 0.1, 0.05}, 0, o), 8) << "never above the limit";
  o.convergence_threshold = 0;
  EXPECT_EQ(ForecastIterations({0.01, 0.2, 0.1, 0.05}, 0, o), 8) << "cannot converge";
}

TEST(SegmentOptionsValidation, RejectsBadParametersByName) {
  HeadCase c = NoisyHead({12, 12, 12});
  auto expect_error = [&](const SegmentOptions& o, const std::string& name) {
    auto r = Segment(c.phantom.image, o, nullptr, nullptr);
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << name;
    EXPECT_NE(r.status().message().find(name), std::string::npos) << r.status();
  };
  SegmentOptions o;
  o.regions = 1;
  expect_error(o, "regions");
  o.regions = 9;
  expect_error(o, "regions");
  o = SegmentOptions{};
  o.curvature_weight = -1;
  expect_error(o, "curvature_weight");
  o = SegmentOptions{};
  o.fitting_weight = -0.1;
  expect_error(o, "fitting_weight");
  o = SegmentOptions{};
  o.overlap_weight = -2;
  expect_error(o, "overlap_weight");
  o = SegmentOptions{};
  o.curvature_weights = {1, 1};
  expect_error(o, "curvature_weights");
  o = SegmentOptions{};
  o.fitting_weights = {1, -1, 1};
  expect_error(o, "fitting_weights[1]");
  o = SegmentOptions{};
  o.alpha = 0;
  expect_error(o, "alpha");
  o = SegmentOptions{};
  o.dt = 1.01 * MaxStableTimeStep(o, c.phantom.image);
  expect_error(o, "stability bound");
  o = SegmentOptions{};
  o.dt = std::nan("");
  expect_error(o, "dt");
  o = SegmentOptions{};
  o.reinit_interval = 0;
  expect_error(o, "reinit_interval");
  o = SegmentOptions{};
  o.max_iterations = -1;
  expect_error(o, "max_iterations");
  o = SegmentOptions{};
  o.convergence_threshold = 1;
  expect_error(o, "convergence_threshold");
  o = SegmentOptions{};
  o.band_width = 2;
  expect_error(o, "band_width");
  o = SegmentOptions{};
  o.class_means = {1, 2};
  expect_error(o, "class_means");
  o.class_means = {1, 2, 1};
  expect_error(o, "class_means");
  o = SegmentOptions{};
  o.threads = -1;
  expect_error(o, "threads");
  // A stable explicit dt is accepted.
  o = SegmentOptions{};
  o.dt = 0.99 * MaxStableTimeStep(o, c.phantom.image);
  EXPECT_TRUE(Segment(c.phantom.image, o, nullptr, nullptr).ok());
}

TEST(SegmentOptionsValidation, StabilityBoundFollowsSpacingAndWeights) {
  auto v = MakeVolume({8, 8, 8}, VoxelType::kFloat32);
  ASSERT_TRUE(v.ok());
  SegmentOptions o;
  o.curvature_weight = 1;
  o.overlap_weight = 0;
  o.alpha = 1.5;
  // 3 unit axes: 1 / (2 * 1 * 3 / 1.5) = 0.25.
  EXPECT_NEAR(MaxStableTimeStep(o, *v), 0.25, 1e-12);
  auto flat = MakeVolume({8, 8, 1}, VoxelType::kFloat32);
  EXPECT_NEAR(MaxStableTimeStep(o, *flat), 1.5 / 4, 1e-12);
  o.curvature_weight = 2;
  EXPECT_NEAR(MaxStableTimeStep(o, *v), 0.125, 1e-12);
}

TEST(SegmentOptionsValidation, RejectsInvalidImage) {
  Volume bad;
  bad.dims = {2, 2, 2};  // no bytes
  auto r = Segment(bad, SegmentOptions{}, nullptr, nullptr);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  auto flat = MakeVolume({4, 4, 4}, VoxelType::kUInt8);  // one intensity level
  ASSERT_TRUE(flat.ok());
  r = Segment(*flat, SegmentOptions{}, nullptr, nullptr);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace decima
