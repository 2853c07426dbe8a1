#include "core/simplify/simplify.h"

#include <algorithm>
#include <cmath>
#include <set>
#include <vector>

#include <gtest/gtest.h>

#include "absl/strings/str_cat.h"
#include "core/metrics/fidelity.h"
#include "core/simplify/collapse_engine.h"
#include "tests/core/simplify/simplify_test_util.h"

namespace decima {
namespace {

using simplify_internal::CollapseEngine;
using simplify_internal::Outcome;
using testing::FaceUse;
using testing::MakePhantomMesh;
using testing::TotalVolume;

// Boundary faces of `m` as sorted position triples, so meshes with different vertex numbering
// can be compared.
std::set<std::array<float, 9>> HullFaces(const TetMesh& m) {
  std::set<std::array<float, 9>> faces;
  for (const auto& [f, count] : FaceUse(m)) {
    if (count != 1) continue;
    std::array<std::array<float, 3>, 3> p;
    for (int k = 0; k < 3; ++k)
      p[k] = {m.positions[3 * f[k]], m.positions[3 * f[k] + 1], m.positions[3 * f[k] + 2]};
    std::sort(p.begin(), p.end());
    std::array<float, 9> key;
    for (int k = 0; k < 9; ++k) key[k] = p[k / 3][k % 3];
    faces.insert(key);
  }
  return faces;
}

// The invariants of the acceptance list: zero feature vertices moved or removed, no
// inverted or degenerate cell, the exterior boundary unchanged (same hull faces and boundary
// vertices, unmoved), conforming, the box volume kept, compacted.
void ExpectInvariants(const testing::PhantomMesh& pm, const SimplifyResult& r) {
  const TetMesh& in = pm.mesh;
  const TetMesh& out = r.mesh;
  EXPECT_EQ(r.output_cells, out.tet_count());
  FidelityOptions fo;
  fo.labels = &pm.phantom.labels;
  fo.original = &in;
  fo.vertex_map = &r.vertex_map;
  auto m = MeasureFidelity(pm.phantom.image, out, fo);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_GT(m->feature_vertices, 1000);
  EXPECT_EQ(m->feature_vertices_moved, 0);
  EXPECT_EQ(m->feature_vertices_removed, 0);
  EXPECT_EQ(m->inverted_cells, 0);
  EXPECT_EQ(m->degenerate_cells, 0);
  EXPECT_DOUBLE_EQ(m->coverage, 1.0);

  // Conforming: every face is used by one (hull) or two cells.
  for (const auto& [face, count] : FaceUse(out)) ASSERT_LE(count, 2);
  // The hull is the same surface, and so the same volume.
  EXPECT_EQ(HullFaces(out), HullFaces(in));
  const double side = double(pm.phantom.image.dims[0] - 1), box = side * side * side;
  EXPECT_NEAR(TotalVolume(out), box, 1e-9 * box);
  // Boundary vertices are all still there, unmoved.
  int64_t boundary_in = 0, boundary_out = 0;
  for (int64_t v = 0; v < in.vertex_count(); ++v) {
    if (!(in.vertex_flags[v] & kExteriorBoundaryVertex)) continue;
    ++boundary_in;
    const int32_t n = r.vertex_map[v];
    ASSERT_GE(n, 0);
    EXPECT_EQ(out.Position(n), in.Position(v));
  }
  for (int64_t v = 0; v < out.vertex_count(); ++v)
    boundary_out += (out.vertex_flags[v] & kExteriorBoundaryVertex) != 0;
  EXPECT_EQ(boundary_in, boundary_out);
  // Compacted: every vertex is used.
  std::vector<uint8_t> used(out.vertex_count(), 0);
  for (int32_t v : out.tets) used[v] = 1;
  EXPECT_EQ(std::count(used.begin(), used.end(), 0), 0);
}

// The acceptance case: a noisy 3-region phantom halved (default options).
TEST(Simplify, NoisyPhantomHalvedKeepsFeaturesHullConformityAndVolume) {
  auto pm = MakePhantomMesh(40, 40);
  SimplifyOptions o;
  o.target_reduction = 0.5;
  auto r = Simplify(pm.mesh, o);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->reached_target) << r->stop_message;
  EXPECT_EQ(r->stop_reason, StopReason::kTargetReached);
  EXPECT_NEAR(r->achieved_reduction, 0.5, 1e-4);
  ExpectInvariants(pm, *r);
}

// Runs to the end (no collapse left), the hardest case for the invariants; in the other queue
// mode (no lock, lazy re-scoring).
TEST(Simplify, NoisyPhantomSimplifiedToTheEndKeepsFeaturesHullAndConformity) {
  auto pm = MakePhantomMesh(28, 40);
  SimplifyOptions o;
  o.lock_neighbours = false;
  o.target_reduction = 0.95;
  o.min_pass_gain = 0;
  auto r = Simplify(pm.mesh, o);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->reached_target);
  EXPECT_EQ(r->stop_reason, StopReason::kNoValidCollapse);
  EXPECT_NE(r->stop_message.find("target not reached"), std::string::npos) << r->stop_message;
  EXPECT_GE(r->achieved_reduction, 0.5) << r->stop_message;
  EXPECT_GE(r->passes, 2);
  ExpectInvariants(pm, *r);
}

// A 6x6x6 grid mesh (one region, no features) whose cells the rule tests pick from. Interior
// vertices are jittered by up to 0.15 voxel (fixed pattern): on the exact grid every collapse
// onto a vertex flattens the cells lying in a grid plane through it, so rules 2, 4 and 5 could
// never act.
TetMesh GridMesh(int64_t n = 6, bool jitter = true) {
  auto v = MakeVolume({n, n, n}, VoxelType::kFloat32);
  EXPECT_TRUE(v.ok());
  for (int64_t i = 0; i < v->voxel_count(); ++i) v->mutable_data<float>()[i] = float(i % 7);
  auto m = Tetrahedralize(*v);
  EXPECT_TRUE(m.ok());
  NormalSampler noise(3);
  for (int64_t p = 0; p < m->vertex_count() && jitter; ++p) {
    for (int c = 0; c < 3; ++c) {
      const double d = std::clamp(0.06 * noise.Next(), -0.15, 0.15);
      if (!(m->vertex_flags[p] & kExteriorBoundaryVertex)) m->positions[3 * p + c] += float(d);
    }
  }
  for (int64_t t = 0; t < m->tet_count(); ++t) EXPECT_GT(TetVolume(*m, t), 0);
  return *std::move(m);
}

bool Interior(const TetMesh& m, int64_t t) {
  for (int k = 0; k < 4; ++k)
    if (m.vertex_flags[m.tets[4 * t + k]] & kExteriorBoundaryVertex) return false;
  return true;
}

std::vector<int32_t> InteriorCells(const TetMesh& m) {
  std::vector<int32_t> cells;
  for (int64_t t = 0; t < m.tet_count(); ++t)
    if (Interior(m, t)) cells.push_back(int32_t(t));
  return cells;
}

struct Finished {
  TetMesh mesh;
  std::vector<int32_t> map;
};
Finished Finish(CollapseEngine& e) {
  Finished f;
  e.Finish(&f.mesh, &f.map);
  return f;
}

TEST(CollapseRules, CellWithTwoFeatureVerticesIsNeverCollapsed) {
  TetMesh m = GridMesh();
  const int32_t c = InteriorCells(m)[0];
  m.vertex_flags[m.tets[4 * c]] |= kFeatureVertex;
  m.vertex_flags[m.tets[4 * c + 1]] |= kFeatureVertex;
  CollapseEngine e(m, {});
  e.BeginPass(1);
  EXPECT_EQ(e.TryCollapse(c).outcome, Outcome::kTwoFeatureVertices);
  EXPECT_EQ(Finish(e).mesh.tets, m.tets);
}

TEST(CollapseRules, CellWithOneFeatureVertexCollapsesOntoIt) {
  for (bool widen : {false, true}) {
    SimplifyOptions o;
    o.widen_collapse_point = widen;
    int collapsed = 0, partial = 0;
    for (int32_t c : InteriorCells(GridMesh())) {
      TetMesh m = GridMesh();
      const int32_t f = m.tets[4 * c + 2];
      m.vertex_flags[f] |= kFeatureVertex;
      CollapseEngine e(m, o);
      e.BeginPass(1);
      const auto r = e.TryCollapse(c);
      if (r.outcome == Outcome::kFlip) continue;
      ASSERT_EQ(r.outcome, Outcome::kCollapsed) << OutcomeName(r.outcome);
      ++collapsed;
      EXPECT_EQ(r.survivor, f);
      const Finished out = Finish(e);
      // The paper's collapse merges all four onto v_f; a widened one merges two or three of
      // them, always onto v_f. Either way τ is gone and v_f did not move.
      int merged = 0;
      for (int k = 0; k < 4; ++k) merged += out.map[m.tets[4 * c + k]] == out.map[f];
      EXPECT_EQ(merged, r.merged);
      if (!widen) {
        EXPECT_EQ(merged, 4);
      }
      partial += merged < 4;
      EXPECT_GE(merged, 2);
      EXPECT_EQ(out.mesh.tet_count(), m.tet_count() - r.cells_removed);
      EXPECT_EQ(out.mesh.Position(out.map[f]), m.Position(f));
      EXPECT_EQ(out.mesh.scalars[out.map[f]], m.scalars[f]);
      EXPECT_NEAR(TotalVolume(out.mesh), 125.0, 1e-9);
    }
    EXPECT_GT(collapsed, 0);
    if (widen) {
      EXPECT_GT(partial, 0);
    }
  }
}

TEST(CollapseRules, CrossRegionCellIsNeverCollapsed) {
  TetMesh m = GridMesh();
  const int32_t c = InteriorCells(m)[0];
  m.labels[m.tets[4 * c + 3]] = 1;  // two regions, no feature vertex
  CollapseEngine e(m, {});
  e.BeginPass(1);
  EXPECT_EQ(e.TryCollapse(c).outcome, Outcome::kCrossRegion);
  EXPECT_EQ(Finish(e).mesh.tets, m.tets);
}

TEST(CollapseRules, NeighbourOfCrossRegionCellCollapsesOntoTheCommonVertex) {
  const TetMesh grid = GridMesh(7);
  const int32_t w = int32_t(3 + 7 * (3 + 7 * 3));  // the centre vertex, label 1
  int collapsed = 0;
  for (int32_t c : InteriorCells(grid)) {
    const int32_t* t = &grid.tets[4 * c];
    if (std::count(t, t + 4, w)) continue;
    TetMesh m = grid;
    m.labels[w] = 1;
    // Vertices of τ shared with every cross-region cell around it (the cells holding w).
    unsigned common = 0xF, crossing = 0;
    for (int64_t n = 0; n < m.tet_count(); ++n) {
      const int32_t* o = &m.tets[4 * n];
      if (!std::count(o, o + 4, w)) continue;
      unsigned mask = 0;
      for (int k = 0; k < 4; ++k) mask |= std::count(o, o + 4, t[k]) ? 1u << k : 0;
      if (mask) ++crossing, common &= mask;
    }
    if (crossing == 0) continue;
    CollapseEngine e(m, {});
    e.BeginPass(1);
    const auto r = e.TryCollapse(c);
    if (common == 0) {
      EXPECT_EQ(r.outcome, Outcome::kCrossRegionNeighbours);
      continue;
    }
    if (r.outcome == Outcome::kFlip || r.outcome == Outcome::kFeatureNeighbourhood) continue;
    ASSERT_EQ(r.outcome, Outcome::kCollapsed) << OutcomeName(r.outcome);
    ++collapsed;
    int slot = int(std::find(t, t + 4, r.survivor) - t);
    ASSERT_LT(slot, 4) << "collapsed to a centroid next to a cross-region cell";
    EXPECT_TRUE(common & (1u << slot));
  }
  EXPECT_GT(collapsed, 0);
}

TEST(CollapseRules, BoundaryCellNeverMovesItsBoundaryVertex) {
  const TetMesh m = GridMesh();
  for (bool widen : {false, true}) {
    SimplifyOptions o;
    o.widen_collapse_point = widen;
    int two = 0, one = 0;
    for (int64_t c = 0; c < m.tet_count(); ++c) {
      const int32_t* t = &m.tets[4 * c];
      int nb = 0, b = -1;
      for (int k = 0; k < 4; ++k)
        if (m.vertex_flags[t[k]] & kExteriorBoundaryVertex) ++nb, b = t[k];
      if (nb == 0) continue;
      CollapseEngine e(m, o);
      e.BeginPass(1);
      const auto r = e.TryCollapse(int32_t(c));
      if (nb >= 2) {
        ++two;
        EXPECT_EQ(r.outcome, Outcome::kTwoBoundaryVertices);
      } else if (r.outcome == Outcome::kCollapsed) {
        ++one;
        EXPECT_EQ(r.survivor, b);
        const Finished out = Finish(e);
        EXPECT_EQ(out.mesh.Position(out.map[b]), m.Position(b));
        EXPECT_NEAR(TotalVolume(out.mesh), 125.0, 1e-9);
      } else {
        EXPECT_EQ(r.outcome, Outcome::kFlip);
      }
    }
    EXPECT_GT(two, 0);
    if (!widen) {
      // On a flat hull pulling all three interior vertices onto v_b flattens the cells lying
      // on the hull plane, so rule 6 rejects every paper collapse of such a cell.
      EXPECT_EQ(one, 0);
    } else {
      // Merging only two of τ's vertices onto v_b (an edge along the grid) often is valid.
      EXPECT_GT(one, 0);
    }
  }
}

TEST(CollapseRules, NormalCellCollapsesToItsCentroidKeepingVolumeAndConformity) {
  const TetMesh m = GridMesh();
  const int32_t c = InteriorCells(m)[0];
  CollapseEngine e(m, {});
  e.BeginPass(1);
  const auto r = e.TryCollapse(c);
  ASSERT_EQ(r.outcome, Outcome::kCollapsed) << OutcomeName(r.outcome);
  EXPECT_GE(r.cells_removed, 5);
  const Finished out = Finish(e);
  EXPECT_EQ(out.mesh.tet_count(), m.tet_count() - r.cells_removed);
  EXPECT_EQ(out.mesh.vertex_count(), m.vertex_count() - 3);
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  double mean = 0;
  for (int k = 0; k < 4; ++k) {
    centroid += m.Position(m.tets[4 * c + k]) / 4;
    mean += m.scalars[m.tets[4 * c + k]] / 4.0;
  }
  const int32_t s = out.map[r.survivor];
  EXPECT_LT((out.mesh.Position(s) - centroid).norm(), 1e-5);
  EXPECT_NEAR(out.mesh.scalars[s], mean, 1e-5);
  EXPECT_NEAR(TotalVolume(out.mesh), 125.0, 1e-9);
  for (int64_t t = 0; t < out.mesh.tet_count(); ++t) EXPECT_GT(TetVolume(out.mesh, t), 0);
  for (const auto& [face, count] : FaceUse(out.mesh)) EXPECT_LE(count, 2);
}

TEST(CollapseRules, CollapseThatWouldFlipANeighbourIsRejectedAndMeshUntouched) {
  // Search a grid mesh with one vertex displaced so that collapsing some cell to its centroid
  // would push a vertex through the opposite face of a cell of A(τ), while the mesh stays valid.
  const TetMesh grid = GridMesh(6, false);
  for (int32_t c : InteriorCells(grid)) {
    const int32_t* t = &grid.tets[4 * c];
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) centroid += grid.Position(t[k]) / 4;
    for (int64_t n = 0; n < grid.tet_count(); ++n) {
      const int32_t* o = &grid.tets[4 * n];
      int shared = 0, u = -1;
      for (int k = 0; k < 4; ++k)
        if (std::count(o, o + 4, t[k])) ++shared, u = t[k];
      if (shared != 1) continue;
      for (int j = 0; j < 4; ++j) {
        const int32_t w = o[j];
        if (w == u || (grid.vertex_flags[w] & kExteriorBoundaryVertex)) continue;
        for (double f : {0.3, 0.5, 0.7, 0.9}) {
          TetMesh m = grid;
          const Eigen::Vector3d target = 0.5 * (grid.Position(u) + centroid);
          const Eigen::Vector3d p = grid.Position(w) + f * (target - grid.Position(w));
          for (int a = 0; a < 3; ++a) m.positions[3 * w + a] = float(p[a]);
          bool valid = true;
          for (int64_t x = 0; x < m.tet_count() && valid; ++x) valid = TetVolume(m, x) > 0.01;
          if (!valid) continue;
          TetMesh moved = m;  // the A cell with u at the centroid
          for (int a = 0; a < 3; ++a) moved.positions[3 * u + a] = float(centroid[a]);
          if (TetVolume(moved, n) >= 0) continue;
          SimplifyOptions paper_only;
          paper_only.widen_collapse_point = false;
          CollapseEngine e(m, paper_only);
          e.BeginPass(1);
          EXPECT_EQ(e.TryCollapse(c).outcome, Outcome::kFlip);
          const Finished out = Finish(e);
          EXPECT_EQ(out.mesh.tets, m.tets);
          EXPECT_EQ(out.mesh.positions, m.positions);
          EXPECT_EQ(out.mesh.scalars, m.scalars);
          // The widened set may delete τ another way; then every cell is still positive.
          CollapseEngine wide(m, {});
          wide.BeginPass(1);
          const auto r = wide.TryCollapse(c);
          const Finished w = Finish(wide);
          if (r.outcome == Outcome::kCollapsed) {
            EXPECT_NE(r.point, 0);
            for (int64_t x = 0; x < w.mesh.tet_count(); ++x) EXPECT_GT(TetVolume(w.mesh, x), 0);
            EXPECT_NEAR(TotalVolume(w.mesh), TotalVolume(m), 1e-9);
          } else {
            EXPECT_EQ(r.outcome, Outcome::kFlip);
            EXPECT_EQ(w.mesh.tets, m.tets);
          }
          return;
        }
      }
    }
  }
  FAIL() << "no flipping configuration found";
}

TEST(CollapseRules, SliverGuardRejectsCollapsesLeavingTinyCells) {
  const TetMesh m = GridMesh();
  SimplifyOptions o;
  o.min_volume_fraction = 0.9;  // larger than any cell of the grid after a move
  o.target_reduction = 0.5;
  auto r = Simplify(m, o);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->collapses, 0);
  EXPECT_EQ(r->mesh.tets, m.tets);
  EXPECT_EQ(r->mesh.positions, m.positions);
  EXPECT_EQ(r->stop_reason, StopReason::kNoValidCollapse);
  EXPECT_FALSE(r->reached_target);
}

TEST(Simplify, SameResultOnOneAndTwoThreads) {
  auto pm = MakePhantomMesh(20, 40);
  for (bool lock : {true, false}) {
    SimplifyOptions o;
    o.target_reduction = 0.5;
    o.lock_neighbours = lock;
    o.threads = 1;
    auto a = Simplify(pm.mesh, o);
    o.threads = 2;
    auto b = Simplify(pm.mesh, o);
    ASSERT_TRUE(a.ok() && b.ok());
    EXPECT_GT(a->collapses, 0);
    EXPECT_EQ(a->mesh.tets, b->mesh.tets);
    EXPECT_EQ(a->mesh.positions, b->mesh.positions);
    EXPECT_EQ(a->mesh.scalars, b->mesh.scalars);
    EXPECT_EQ(a->mesh.labels, b->mesh.labels);
    EXPECT_EQ(a->mesh.vertex_flags, b->mesh.vertex_flags);
    EXPECT_EQ(a->vertex_map, b->vertex_map);
    EXPECT_EQ(a->passes, b->passes);
  }
}

// At 40 %: TetFusion (centroid collapses only, as its paper defines it) jams at ~47 % on this
// phantom, so 50 % cannot be compared.
TEST(Simplify, PaperPolicyBeatsTetFusionOnFieldAndBoundaries) {
  auto pm = MakePhantomMesh(40, 40);
  FidelityMetrics m[2];
  int i = 0;
  for (SimplifyPolicy policy : {SimplifyPolicy::kPaper, SimplifyPolicy::kTetFusion}) {
    SimplifyOptions o;
    o.policy = policy;
    o.target_reduction = 0.4;
    auto r = Simplify(pm.mesh, o);
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_TRUE(r->reached_target) << r->stop_message;
    FidelityOptions fo;
    fo.labels = &pm.phantom.labels;
    fo.original = &pm.mesh;
    fo.vertex_map = &r->vertex_map;
    auto f = MeasureFidelity(pm.phantom.image, r->mesh, fo);
    ASSERT_TRUE(f.ok()) << f.status();
    m[i++] = *f;
  }
  EXPECT_LT(m[0].rmse, m[1].rmse);
  EXPECT_LT(m[0].interface_rmse, m[1].interface_rmse);
  EXPECT_LE(m[0].label_mismatch, m[1].label_mismatch);
  EXPECT_EQ(m[0].feature_vertices_moved + m[0].feature_vertices_removed, 0);
  EXPECT_GT(m[1].feature_vertices_moved + m[1].feature_vertices_removed, 0);
}

TEST(Simplify, StopsWhenAPassGainsTooLittleAndSaysSo) {
  auto pm = MakePhantomMesh(20, 40);
  SimplifyOptions o;
  o.target_reduction = 0.9;
  o.min_pass_gain = 0.05;
  auto r = Simplify(pm.mesh, o);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->stop_reason, StopReason::kStalled);
  EXPECT_LT(r->pass_stats.back().cells_removed, 0.05 * double(r->input_cells));
  for (size_t i = 0; i + 1 < r->pass_stats.size(); ++i)
    EXPECT_GE(r->pass_stats[i].cells_removed, 0.05 * double(r->input_cells));
  EXPECT_NE(r->stop_message.find("jammed"), std::string::npos) << r->stop_message;
}

TEST(Simplify, ErrorToleranceStopsTheLoopAndSaysSo) {
  auto pm = MakePhantomMesh(16, 40);
  SimplifyOptions o;
  o.target_reduction = 0.5;
  o.error_tolerance = 1e-6;
  auto r = Simplify(pm.mesh, o);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->collapses, 0);
  EXPECT_EQ(r->stop_reason, StopReason::kErrorTolerance);
  EXPECT_FALSE(r->reached_target);
  EXPECT_NE(r->stop_message.find("tolerance"), std::string::npos);
}

TEST(Simplify, ReportsProgressPerPassAndHonoursCancellation) {
  auto pm = MakePhantomMesh(16, 40);
  SimplifyOptions o;
  o.target_reduction = 0.3;
  std::vector<Progress> seen;
  auto r = Simplify(pm.mesh, o, [&](const Progress& p) { seen.push_back(p); });
  ASSERT_TRUE(r.ok());
  ASSERT_EQ(int(seen.size()), r->passes);
  EXPECT_EQ(seen[0].stage, "simplify");
  EXPECT_EQ(seen[0].metrics[0].first, "pass");
  EXPECT_EQ(seen.back().metrics[1].first, "cells_removed");
  CancelToken cancel;
  cancel.Cancel();
  EXPECT_EQ(Simplify(pm.mesh, o, nullptr, &cancel).status().code(), absl::StatusCode::kCancelled);
}

TEST(Simplify, RejectsBadOptionsAndMeshes) {
  const TetMesh m = GridMesh(3);
  SimplifyOptions o;
  o.target_reduction = 1.5;
  EXPECT_EQ(Simplify(m, o).status().code(), absl::StatusCode::kInvalidArgument);
  o = {};
  o.weights.regional = -1;
  EXPECT_EQ(Simplify(m, o).status().code(), absl::StatusCode::kInvalidArgument);
  o = {};
  o.min_volume_fraction = 0;
  EXPECT_EQ(Simplify(m, o).status().code(), absl::StatusCode::kInvalidArgument);
  TetMesh bad = m;
  bad.tets[5] = 1000;
  auto s = Simplify(bad, {});
  EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.status().message().find("cell 1"), std::string::npos) << s.status();
  bad = m;
  std::swap(bad.tets[2], bad.tets[3]);  // inverted
  EXPECT_EQ(Simplify(bad, {}).status().code(), absl::StatusCode::kInvalidArgument);
  bad = m;
  bad.labels.pop_back();
  EXPECT_EQ(Simplify(bad, {}).status().code(), absl::StatusCode::kInvalidArgument);
}

// The cells are checked on all threads; the error names the lowest bad cell, as a serial scan
// would, whichever thread meets a bad cell first.
TEST(Simplify, ABadMeshNamesItsLowestBadCellOnAnyThreadCount) {
  TetMesh bad = GridMesh(32);  // 148,955 cells: more than one range per thread
  ASSERT_GT(bad.tet_count(), 2 * 65536);
  const int64_t late = bad.tet_count() - 3, early = 7;
  std::swap(bad.tets[4 * late + 2], bad.tets[4 * late + 3]);  // inverted
  for (int threads : {1, 2, 3}) {
    SimplifyOptions o;
    o.threads = threads;
    auto s = Simplify(bad, o);
    EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(s.status().message().find(absl::StrCat("cell ", late, " is not positively")),
              std::string::npos)
        << s.status();
  }
  bad.tets[4 * early + 1] = bad.tets[4 * early];  // repeats a vertex
  for (int threads : {1, 2, 3}) {
    SimplifyOptions o;
    o.threads = threads;
    auto s = Simplify(bad, o);
    EXPECT_NE(s.status().message().find(absl::StrCat("cell ", early, " repeats vertex")),
              std::string::npos)
        << s.status();
  }
}

TEST(Simplify, LinearFieldStaysExactUnderBothPolicies) {
  auto v = MakeVolume({12, 12, 12}, VoxelType::kFloat32);
  ASSERT_TRUE(v.ok());
  for (int64_t k = 0, p = 0; k < 12; ++k)
    for (int64_t j = 0; j < 12; ++j)
      for (int64_t i = 0; i < 12; ++i, ++p) v->mutable_data<float>()[p] = float(3 * i - 2 * j + k);
  auto mesh = Tetrahedralize(*v);
  ASSERT_TRUE(mesh.ok());
  for (SimplifyPolicy policy : {SimplifyPolicy::kPaper, SimplifyPolicy::kTetFusion}) {
    SimplifyOptions o;
    o.policy = policy;
    o.target_reduction = 0.3;
    auto r = Simplify(*mesh, o);
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_TRUE(r->reached_target) << r->stop_message;
    auto f = MeasureFidelity(*v, r->mesh);
    ASSERT_TRUE(f.ok()) << f.status();
    EXPECT_LT(f->max_abs_error, 1e-3);
    EXPECT_DOUBLE_EQ(f->coverage, 1.0);
  }
}

}  // namespace
}  // namespace decima
