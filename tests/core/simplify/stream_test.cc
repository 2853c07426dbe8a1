// Streamed simplification (core/simplify/stream.h): slabs of voxel layers through a sliding
// window against the in-memory run, the window engine's frozen vertices, the edge cases, and the
// CT head when ../shared/data has it.
#include "core/simplify/stream.h"

#include <cmath>
#include <map>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "core/io/volume_io.h"
#include "core/metrics/fidelity.h"
#include "core/segment/segment.h"
#include "core/simplify/field_engine.h"
#include "core/simplify/simplify.h"
#include "tests/core/simplify/simplify_test_util.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

using testing::ExpectSameMesh;
using testing::FaceUse;
using testing::FieldOptions;
using testing::MeshWithLabels;
using testing::SimpleInterfaceDistance;

struct Case {
  Volume image, labels;
  TetMesh mesh;
};

// The 3-region head phantom with noise on a grid of `dims` voxels, meshed with its labels.
Case MakeCase(std::array<int64_t, 3> dims, double noise = 40) {
  HeadPhantomOptions o;
  o.dims = dims;
  o.noise_sigma = noise;
  o.seed = 11;
  auto p = MakeHeadPhantom(o);
  EXPECT_TRUE(p.ok()) << p.status();
  Case c{std::move(p->image), std::move(p->labels), {}};
  c.mesh = MeshWithLabels(c.image, c.labels, SimpleInterfaceDistance(c.labels));
  return c;
}

FidelityMetrics Measure(const Volume& image, const Volume& labels, const TetMesh& mesh) {
  FidelityOptions fo;
  fo.labels = &labels;
  fo.threads = 2;
  auto m = MeasureFidelity(image, mesh, fo);
  EXPECT_TRUE(m.ok()) << m.status();
  return m.ok() ? *m : FidelityMetrics{};
}

// Every cell positive, every face used by at most two cells, the hull's volume kept.
void ExpectValidMesh(const TetMesh& m, double volume, const std::string& what) {
  int64_t nonpositive = 0;
  double total = 0;
  for (int64_t t = 0; t < m.tet_count(); ++t) {
    const double v = TetVolume(m, t);
    nonpositive += !(v > 0);
    total += v;
  }
  EXPECT_EQ(nonpositive, 0) << what;
  int64_t over = 0;
  for (const auto& [face, use] : FaceUse(m)) over += use > 2;
  EXPECT_EQ(over, 0) << what << ": faces in more than two cells";
  EXPECT_NEAR(total, volume, 1e-6 * volume) << what;
}

// The field's RMSE on the image grid per z layer (the slabs' axis).
std::vector<double> LayerRmse(const Volume& image, const TetMesh& mesh) {
  GridResample r;
  auto e = MeasureFieldError(image, mesh, 2, 1e-5, nullptr, &r);
  EXPECT_TRUE(e.ok()) << e.status();
  const int64_t layer = image.dims[0] * image.dims[1], nz = image.dims[2];
  std::vector<double> rmse(nz, 0);
  if (!e.ok()) return rmse;
  for (int64_t z = 0; z < nz; ++z) {
    double sum = 0;
    for (int64_t g = z * layer; g < (z + 1) * layer; ++g) {
      const double d = r.values[g] - image.ValueAt(g);
      sum += d * d;
    }
    rmse[z] = std::sqrt(sum / double(layer));
  }
  return rmse;
}

// Streamed against in-memory on one case: cells and PSNR within 0.5 %, labels exact, valid.
// With max_layer_ratio > 0 also no band along z: no layer's RMSE above max_layer_ratio times
// the in-memory run's on that layer (slabs that give up more than their share, or seams, show as
// bands in the difference pictures).
void CompareWithInMemory(const Case& c, double reduction, int slab, const std::string& what,
                         double psnr_tolerance = 0.005, double max_layer_ratio = 0) {
  const SimplifyOptions o = FieldOptions(reduction);
  auto whole = Simplify(c.mesh, o);
  ASSERT_TRUE(whole.ok()) << whole.status();
  auto streamed = SimplifyStreamed(c.mesh, o, slab);
  ASSERT_TRUE(streamed.ok()) << streamed.status();
  const FidelityMetrics a = Measure(c.image, c.labels, whole->mesh);
  const FidelityMetrics b = Measure(c.image, c.labels, streamed->mesh);
  const double cells_diff =
      std::abs(double(streamed->output_cells) / double(whole->output_cells) - 1);
  std::printf("%s: cells %lld / %lld (%+.3f%%), PSNR %.3f / %.3f dB, windows %d\n", what.c_str(),
              (long long)streamed->output_cells, (long long)whole->output_cells,
              100 * (double(streamed->output_cells) / double(whole->output_cells) - 1), b.psnr_db,
              a.psnr_db, streamed->passes);
  if (max_layer_ratio > 0) {
    const std::vector<double> in_memory = LayerRmse(c.image, whole->mesh);
    const std::vector<double> layers = LayerRmse(c.image, streamed->mesh);
    size_t worst = 0;
    for (size_t z = 0; z < layers.size(); ++z) {
      if (layers[z] * in_memory[worst] > layers[worst] * in_memory[z]) worst = z;
    }
    const double ratio = layers[worst] / std::max(in_memory[worst], 1e-9);
    std::printf("%s: worst layer z=%zu, RMSE %.2f against %.2f in memory (x%.2f)\n", what.c_str(),
                worst, layers[worst], in_memory[worst], ratio);
    EXPECT_LE(ratio, max_layer_ratio) << what << ": a band at z=" << worst;
  }
  EXPECT_LE(cells_diff, 0.005) << what << ": " << streamed->stop_message;
  EXPECT_GE(b.psnr_db, a.psnr_db * (1 - psnr_tolerance)) << what;
  EXPECT_EQ(b.label_mismatch, 0) << what;
  EXPECT_EQ(b.coverage, 1) << what;
  EXPECT_TRUE(streamed->reached_target) << what << ": " << streamed->stop_message;
  ExpectValidMesh(streamed->mesh, testing::TotalVolume(c.mesh), what);
  // The vertex map points every input vertex at an output vertex.
  ASSERT_EQ(int64_t(streamed->vertex_map.size()), c.mesh.vertex_count());
  for (int32_t o2 : streamed->vertex_map) {
    ASSERT_GE(o2, 0) << what;
    ASSERT_LT(o2, streamed->mesh.vertex_count()) << what;
  }
}

// The 0.5 % holds on the noisy phantoms too since the pacing is a global cost threshold
// (stream.cc): streamed PSNR -0.20 % to +0.13 % of the in-memory run's on the cases below. With
// the shares by roughness it was 0.2-0.9 % below, and slabs of 4 at 80 % missed the cells by 5.5 %
// when the Newton step was taken once (the measuring pass's count missed by 7.6 %).
constexpr double kPhantomPsnrTolerance = 0.005;

TEST(SimplifyStreamedTest, MatchesInMemoryOnPhantomOddDepth) {
  const Case c = MakeCase({28, 26, 31});  // nz odd: 30 cube layers, 4 slabs of 7-8
  CompareWithInMemory(c, 0.5, 8, "phantom 28x26x31 50% slab 8", kPhantomPsnrTolerance);
  CompareWithInMemory(c, 0.8, 8, "phantom 28x26x31 80% slab 8", kPhantomPsnrTolerance);
}

TEST(SimplifyStreamedTest, MatchesInMemoryWithThinSlabs) {
  const Case c = MakeCase({24, 24, 33});
  CompareWithInMemory(c, 0.8, kMinStreamSlabVoxels, "phantom 24x24x33 80% slab 4",
                      kPhantomPsnrTolerance);
  CompareWithInMemory(c, 0.5, 5, "phantom 24x24x33 50% slab 5", kPhantomPsnrTolerance);
}

// A volume whose first slabs are empty (ch2better's are): window 0's share of the target goes at
// no cost, so the first threshold is far below what the other slabs need and the count at it
// flat over decades. The windows' share costs take the next threshold there; with clamped Newton
// steps alone (x4, then x64 a pass) the run stopped at 64.6 % of 80 on ch2better at half size.
TEST(SimplifyStreamedTest, ReachesTheTargetWhenTheFirstSlabsAreEmpty) {
  Case c = MakeCase({24, 24, 48});
  const int64_t layer = 24 * 24, empty_layers = 20;
  float* image = c.image.mutable_data<float>();
  uint8_t* labels = c.labels.mutable_data<uint8_t>();
  const float air = image[0];
  for (int64_t g = 0; g < empty_layers * layer; ++g) {
    image[g] = air;
    labels[g] = labels[0];
  }
  c.mesh = MeshWithLabels(c.image, c.labels, SimpleInterfaceDistance(c.labels));
  std::vector<std::string> messages;
  auto r = SimplifyStreamed(c.mesh, FieldOptions(0.8), 6,
                            [&](const Progress& p) { messages.push_back(p.message); });
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->reached_target) << r->stop_message;
  for (const std::string& m : messages) {
    if (m.find("measuring pass") != std::string::npos && m.find("target;") != std::string::npos)
      std::printf("%s\n", m.c_str());
  }
  CompareWithInMemory(c, 0.8, 6, "phantom 24x24x48, 20 empty layers, 80% slab 6",
                      kPhantomPsnrTolerance);
}

TEST(SimplifyStreamedTest, SameOutputOnOneAndTwoThreads) {
  const Case c = MakeCase({24, 22, 29});
  auto one = SimplifyStreamed(c.mesh, FieldOptions(0.8, 1), 6);
  auto two = SimplifyStreamed(c.mesh, FieldOptions(0.8, 2), 6);
  ASSERT_TRUE(one.ok() && two.ok());
  EXPECT_GT(one->passes, 1);  // really streamed
  ExpectSameMesh(*one, *two, "streamed, 1 vs 2 threads");
}

// A journal of records in memory, keyed by (pass, window), that can stop the run after a given
// number of saved records (as a killed job child would stop).
struct MemoryJournal {
  std::map<std::pair<int, int64_t>, std::string> records;
  std::vector<std::pair<int, int64_t>> order;  // as saved
  int64_t stop_after = -1;                     // records saved by this run, then cancel
  CancelToken cancel;

  StreamJournal Journal() {
    StreamJournal j;
    j.save = [this](int pass, int64_t window, const std::string& record) {
      records[{pass, window}] = record;
      order.emplace_back(pass, window);
      if (stop_after >= 0 && int64_t(order.size()) >= stop_after) cancel.Cancel();
    };
    j.load = [this](int pass, int64_t window) -> std::optional<std::string> {
      auto it = records.find({pass, window});
      if (it == records.end()) return std::nullopt;
      return it->second;
    };
    return j;
  }
};

// The mesh of a run stopped after `stop_after` windows and run again on its records, against the
// run in one go; returns the windows the second run read back.
// `whole_saved`: the records the run in one go saved.
int64_t ResumedAfter(const Case& c, const SimplifyOptions& o, int slab, int64_t stop_after,
                     const SimplifyResult& whole, int64_t whole_saved, MemoryJournal* journal) {
  journal->stop_after = stop_after;
  StreamJournal first = journal->Journal();
  auto stopped = SimplifyStreamed(c.mesh, o, slab, nullptr, &journal->cancel, &first);
  EXPECT_EQ(stopped.status().code(), absl::StatusCode::kCancelled) << stopped.status();
  EXPECT_EQ(first.resumed_windows, 0);
  MemoryJournal again;
  again.records = journal->records;
  StreamJournal second = again.Journal();
  auto resumed = SimplifyStreamed(c.mesh, o, slab, nullptr, nullptr, &second);
  EXPECT_TRUE(resumed.ok()) << resumed.status();
  if (!resumed.ok()) return -1;
  const std::string what = "stopped after " + std::to_string(stop_after) + " records";
  ExpectSameMesh(whole, *resumed, what);
  EXPECT_EQ(resumed->stop_message, whole.stop_message) << what;
  EXPECT_EQ(resumed->collapses, whole.collapses) << what;
  EXPECT_EQ(resumed->pass_stats.size(), whole.pass_stats.size()) << what;
  // The resumed run simplified (and saved) only the windows after the last saved one.
  EXPECT_EQ(int64_t(again.order.size()), whole_saved - stop_after) << what;
  return second.resumed_windows;
}

TEST(SimplifyStreamedTest, AStoppedRunResumesFromItsWindowRecordsWithTheSameMesh) {
  const Case c = MakeCase({24, 22, 29});  // 28 cube layers: 5 slabs of 5-6
  const SimplifyOptions o = FieldOptions(0.8, 2);
  MemoryJournal full;
  StreamJournal j = full.Journal();
  auto whole = SimplifyStreamed(c.mesh, o, 6, nullptr, nullptr, &j);
  ASSERT_TRUE(whole.ok()) << whole.status();
  auto plain = SimplifyStreamed(c.mesh, o, 6);
  ASSERT_TRUE(plain.ok());
  ExpectSameMesh(*plain, *whole, "with and without a journal");
  const int64_t saved = int64_t(full.order.size());
  ASSERT_GE(saved, 10) << "at least one measuring pass and the final one, 5 windows each";
  EXPECT_EQ(full.order.front(), std::make_pair(0, int64_t{0}));
  EXPECT_EQ(full.order.back().second, 4);
  // Stopped inside the first pass, at a pass's end, inside the final pass, and after its last
  // window (the records then hold the whole run: only the output is made again).
  for (int64_t stop : {int64_t{2}, int64_t{5}, saved - 2, saved}) {
    MemoryJournal journal;
    const int64_t read_back = ResumedAfter(c, o, 6, stop, *whole, saved, &journal);
    const auto& [pass, window] = journal.order[stop - 1];
    EXPECT_EQ(read_back, window + 1) << "stopped after window " << window << " of pass " << pass;
  }
}

TEST(SimplifyStreamedTest, ADamagedOrForeignWindowRecordIsSimplifiedAgain) {
  const Case c = MakeCase({24, 22, 29});
  const SimplifyOptions o = FieldOptions(0.8, 2);
  MemoryJournal full;
  StreamJournal j = full.Journal();
  auto whole = SimplifyStreamed(c.mesh, o, 6, nullptr, nullptr, &j);
  ASSERT_TRUE(whole.ok()) << whole.status();
  const auto last = full.order.back();  // the final pass's last window
  // Window 2 of the final pass truncated, missing, or another window's: the run reads back
  // windows 0 and 1 and simplifies the rest again, to the same mesh. (A flipped byte is the
  // checkpoint file's checksum's to catch: core/pipeline's tests.)
  for (int damage = 0; damage < 3; ++damage) {
    MemoryJournal journal;
    journal.records = full.records;
    std::string& r = journal.records.at({last.first, 2});
    if (damage == 0) r.resize(r.size() / 2);
    if (damage == 1) journal.records.erase({last.first, 2});
    if (damage == 2) r = full.records[{last.first, 3}];
    StreamJournal second = journal.Journal();
    auto resumed = SimplifyStreamed(c.mesh, o, 6, nullptr, nullptr, &second);
    ASSERT_TRUE(resumed.ok()) << resumed.status();
    const std::string what = "damage " + std::to_string(damage);
    ExpectSameMesh(*whole, *resumed, what);
    EXPECT_EQ(second.resumed_windows, 2) << what;
  }
  // A record of another run's size (another mesh) is not read back at all.
  const Case other = MakeCase({24, 22, 23});
  MemoryJournal foreign;
  foreign.records = full.records;
  StreamJournal f = foreign.Journal();
  auto fresh = SimplifyStreamed(other.mesh, o, 6, nullptr, nullptr, &f);
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  EXPECT_EQ(f.resumed_windows, 0);
}

// The stage's fraction never goes back, gives each pass its share of the passes that run (the
// ETA comes from it: a measuring pass shown as a sixth of the stage made the 511 CT's first ETA
// five times too long), and reaches 1 only with the refit. A measuring pass kept as the final one
// ends the windows' share at its last window.
TEST(SimplifyStreamedTest, ProgressGivesEachPassItsShareAndNeverGoesBack) {
  const Case c = MakeCase({24, 22, 29});
  bool kept_seen = false, final_pass_seen = false;
  for (double reduction : {0.8, 0.6}) {
    SCOPED_TRACE(reduction);
    std::vector<Progress> events;
    auto r = SimplifyStreamed(c.mesh, FieldOptions(reduction, 2), 6,
                              [&](const Progress& p) { events.push_back(p); });
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_GE(events.size(), 6u);
    double last = 0;
    int measuring = 0;
    bool final_seen = false;
    for (const Progress& p : events) {
      EXPECT_EQ(p.stage, "simplify");
      EXPECT_GE(p.fraction, last) << p.message;
      const double before = last;
      last = p.fraction;
      double pass = -1, kept = 0;
      for (const auto& [k, v] : p.metrics) {
        if (k == "measuring_pass") pass = v;
        if (k == "kept_measuring_pass") kept = v;
      }
      if (pass > 0) measuring = std::max(measuring, int(pass));
      if (pass == 0 && !final_seen) {
        final_seen = true;
        if (kept > 0) {
          // The kept pass's last window ends the windows' share; its other windows had the share
          // of a measuring pass.
          kept_seen = true;
          EXPECT_NE(p.message.find("kept as the final pass"), std::string::npos) << p.message;
          EXPECT_DOUBLE_EQ(p.fraction, 0.95) << p.message;
          EXPECT_LT(before, 0.95 * measuring / (measuring + 1.0)) << p.message;
          EXPECT_GT(before, 0.95 * (measuring - 0.5) / (measuring + 1.0)) << p.message;
        } else {
          final_pass_seen = true;
          // The measuring passes' last window ended their share.
          EXPECT_GT(before, 0.95 * measuring / (measuring + 1.0) - 1e-9) << p.message;
          // The final pass's first window: the measuring passes' share, plus that window's.
          EXPECT_GT(p.fraction, 0.95 * measuring / (measuring + 1.0) - 1e-9) << p.message;
          EXPECT_LT(p.fraction, 0.95 * (measuring + 0.3) / (measuring + 1.0)) << p.message;
        }
      }
      if (pass >= 0) {
        EXPECT_LE(p.fraction, 0.95 + 1e-12) << p.message;
      }
    }
    EXPECT_GE(measuring, 1);
    EXPECT_TRUE(final_seen);
    EXPECT_EQ(events.back().fraction, 1.0) << events.back().message;
  }
  // One run of each kind.
  EXPECT_TRUE(kept_seen);
  EXPECT_TRUE(final_pass_seen);
}

TEST(SimplifyStreamedTest, OneWindowIsTheInMemoryRun) {
  const Case c = MakeCase({20, 20, 17});  // 16 cube layers
  for (int slab : {16, 40}) {
    auto whole = Simplify(c.mesh, FieldOptions(0.7));
    auto streamed = SimplifyStreamed(c.mesh, FieldOptions(0.7), slab);
    ASSERT_TRUE(whole.ok() && streamed.ok());
    ExpectSameMesh(*whole, *streamed, "slab " + std::to_string(slab));
  }
  auto split = SimplifyStreamed(c.mesh, FieldOptions(0.7), 15);  // two windows: not the same run
  ASSERT_TRUE(split.ok());
  EXPECT_EQ(split->passes, 2);
}

TEST(SimplifyStreamedTest, RefusesWhatItCannotStream) {
  const Case c = MakeCase({12, 12, 12});
  for (int slab : {-1, 0, 1, 2, 3}) {
    auto r = SimplifyStreamed(c.mesh, FieldOptions(0.5), slab);
    ASSERT_FALSE(r.ok()) << slab;
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(r.status().message().find("stream_slab_voxels"), std::string::npos) << r.status();
  }
  SimplifyOptions paper = FieldOptions(0.5);
  paper.policy = SimplifyPolicy::kPaper;
  EXPECT_NE(SimplifyStreamed(c.mesh, paper, 4).status().message().find("policy"),
            std::string::npos);
  SimplifyOptions levels = FieldOptions(0.5);
  levels.record_levels_to = 0.8;
  EXPECT_NE(SimplifyStreamed(c.mesh, levels, 4).status().message().find("record_levels_to"),
            std::string::npos);
  EXPECT_NE(
      SimplifyStreamed(c.mesh, FieldOptions(0), 4).status().message().find("target_reduction"),
      std::string::npos);
  TetMesh explicit_mesh = c.mesh;
  explicit_mesh.grid.reset();
  EXPECT_NE(SimplifyStreamed(explicit_mesh, FieldOptions(0.5), 4).status().message().find("grid"),
            std::string::npos);
}

// The window engine never removes a frozen vertex; without the mask the same run removes many of
// them (so the test fails if the mask is ignored).
TEST(FieldWindowTest, FrozenVerticesAreNeverRemoved) {
  const Case c = MakeCase({18, 18, 18});
  const int64_t nv = c.mesh.vertex_count();
  std::vector<uint8_t> frozen(nv, 0);
  for (int64_t v = 0; v < nv; ++v) frozen[v] = (v % 3) == 0 || (v / (18 * 18)) == 9;
  float lo = c.mesh.scalars[0], hi = lo;
  for (float s : c.mesh.scalars) lo = std::min(lo, s), hi = std::max(hi, s);
  auto run = [&](const uint8_t* mask) {
    simplify_internal::FieldWindow w;
    w.frozen = mask;
    w.flags_complete = false;
    w.scalar_lo = lo;
    w.scalar_hi = hi;
    SimplifyResult r;
    const absl::Status s = simplify_internal::RunFieldSimplifyWindow(
        c.mesh, FieldOptions(0.8), 2, int64_t(0.8 * double(c.mesh.tet_count())), w, nullptr,
        nullptr, &r);
    EXPECT_TRUE(s.ok()) << s;
    return r;
  };
  // A vertex survived in place if the output vertex it maps to sits at its own position.
  auto removed_frozen = [&](const SimplifyResult& r) {
    int64_t n = 0;
    for (int64_t v = 0; v < nv; ++v) {
      if (!frozen[v]) continue;
      const int32_t o = r.vertex_map[v];
      bool same = o >= 0;
      for (int k = 0; k < 3 && same; ++k) {
        same = r.mesh.positions[3 * o + k] == c.mesh.positions[3 * v + k];
      }
      n += !same;
    }
    return n;
  };
  const SimplifyResult masked = run(frozen.data());
  const SimplifyResult free = run(nullptr);
  EXPECT_EQ(removed_frozen(masked), 0);
  EXPECT_GT(removed_frozen(free), nv / 10);                // the mask is what keeps them
  EXPECT_LT(masked.output_cells, c.mesh.tet_count() / 2);  // and the rest still collapses
}

// No band along z on the CT head: the worst layer's RMSE is 1.10-1.24x the in-memory run's
// with one cost threshold for all slabs (50 and 80 %, slabs of 16 and 8); with the shares by
// roughness it was 1.45x (50 %, slabs of 16) and 2.0x (80 %, slabs of 8), bands the difference
// pictures show (README "Streamed simplification").
constexpr double kCtHeadMaxLayerRatio = 1.3;

// The CT head at 50 % and 80 % (regions 3, as the job default segments it).
TEST(SimplifyStreamedTest, MatchesInMemoryOnCtHead) {
#ifdef __SANITIZE_ADDRESS__
  // A fidelity check on real data: 348 s under AddressSanitizer (CI's budget is 45 min), where
  // the phantom cases above run the same code paths.
  GTEST_SKIP() << "the CT head's fidelity is checked by the plain build";
#endif
  DECIMA_REQUIRE_SHARED_DATA(path, "ct-head-128x128x53.nii.gz");
  auto image = io::ReadVolume(path.string());
  ASSERT_TRUE(image.ok()) << image.status();
  SegmentOptions so;
  so.regions = 3;
  auto seg = Segment(*image, so, nullptr, nullptr);
  ASSERT_TRUE(seg.ok()) << seg.status();
  TetrahedralizeOptions t;
  t.labels = &seg->labels;
  t.interface_distance = seg->interface_distance_voxels.data();
  auto mesh = Tetrahedralize(*image, t);
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  Case c{*std::move(image), std::move(seg->labels), *std::move(mesh)};
  // Two of the four (50 and 80 %, slabs of 16 and 8) to keep the test short (they run under
  // ASan too); the README has all four.
  CompareWithInMemory(c, 0.5, 16, "CT head 50% slab 16", 0.005, kCtHeadMaxLayerRatio);
  CompareWithInMemory(c, 0.8, 8, "CT head 80% slab 8", 0.005, kCtHeadMaxLayerRatio);
}

}  // namespace
}  // namespace decima
