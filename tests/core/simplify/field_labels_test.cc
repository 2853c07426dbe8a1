// The field policy's free interfaces (InterfaceMode::kFree, the default): interface vertices may
// leave the voxel staircase as long as every voxel centre of the input keeps its own label in
// the simplified mesh, as core/metrics measures it (README "Interfaces free inside their
// voxels").
#include <algorithm>
#include <array>
#include <functional>
#include <iostream>
#include <map>
#include <set>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>

#include "core/metrics/fidelity.h"
#include "core/simplify/field_engine.h"
#include "core/simplify/simplify.h"
#include "tests/core/simplify/simplify_test_util.h"

namespace decima {
namespace {

using simplify_internal::CheckFieldCollapse;
using simplify_internal::FieldCollapseCheck;
using testing::Labeled;
using testing::MakeLabeled;

SimplifyOptions Field(double reduction, InterfaceMode interfaces, int threads = 2) {
  SimplifyOptions o;
  o.policy = SimplifyPolicy::kField;
  o.target_reduction = reduction;
  o.interfaces = interfaces;
  o.threads = threads;
  return o;
}

FidelityMetrics Measure(const Labeled& in, const TetMesh& mesh) {
  FidelityOptions fo;
  fo.labels = &in.labels;
  fo.threads = 1;
  auto m = MeasureFidelity(in.image, mesh, fo);
  EXPECT_TRUE(m.ok()) << m.status();
  return m.ok() ? *m : FidelityMetrics{};
}

// A block of label 1 in label 0, at voxel resolution, on an n^3 grid; the field is the label
// times 100 plus a gentle ramp.
Labeled Block(int64_t n, int64_t lo, int64_t hi) {
  auto inside = [=](int64_t i, int64_t j, int64_t k) {
    return i >= lo && i < hi && j >= lo && j < hi && k >= lo && k < hi;
  };
  return MakeLabeled(
      n, [&](int64_t i, int64_t j, int64_t k) { return 100.0 * inside(i, j, k) + 0.1 * i; },
      [&](int64_t i, int64_t j, int64_t k) { return inside(i, j, k) ? 1 : 0; });
}

// Of the vertices the voxel-faces rules pin in the input (the corners of the voxel staircase),
// how many are still vertices at their place in r.
int64_t StaircaseCornersInPlace(const Labeled& b, const SimplifyResult& r, int64_t* corners) {
  SimplifyOptions o = Field(0.5, InterfaceMode::kVoxelFaces);
  const std::vector<uint8_t> pinned = simplify_internal::PinnedFieldVertices(b.mesh, o);
  int64_t in_place = 0;
  *corners = 0;
  for (int64_t v = 0; v < b.mesh.vertex_count(); ++v) {
    if (!pinned[v]) continue;
    ++*corners;
    const int32_t out = r.vertex_map[v];
    in_place += out >= 0 && r.mesh.Position(out) == b.mesh.Position(v);
  }
  return in_place;
}

// The staircase phantom: with free interfaces the mesh goes past 97 % with every voxel centre
// keeping its label, and corners of the voxel staircase move (are removed: a half-edge collapse
// moves no vertex); with voxel-faces every corner stays. The block's 8 inner corner voxels stay
// under both: each is one voxel from three outside voxels of the other label, and removing it
// leaves its centre at best tied between the two labels (README "Interfaces free inside their
// voxels").
TEST(FieldFreeInterfaces, StaircaseBlockReachesNinetySevenPercentWithEveryLabelKept) {
  const int64_t n = 20, lo = 6, hi = 14;
  const Labeled b = Block(n, lo, hi);
  auto r = Simplify(b.mesh, Field(0.97, InterfaceMode::kFree));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->reached_target) << r->stop_message;
  EXPECT_GE(r->achieved_reduction, 0.97);
  const FidelityMetrics m = Measure(b, r->mesh);
  EXPECT_EQ(m.label_mismatch, 0);
  EXPECT_DOUBLE_EQ(m.coverage, 1.0);
  EXPECT_EQ(m.inverted_cells, 0);
  EXPECT_TRUE(m.manifold);
  EXPECT_GE(m.min_dihedral_deg, 5.0 - 1e-6);
  int64_t corners = 0;
  const int64_t kept = StaircaseCornersInPlace(b, *r, &corners);
  EXPECT_GT(corners, 8);
  EXPECT_LT(kept, corners) << "no staircase corner moved";

  auto staircase = Simplify(b.mesh, Field(0.97, InterfaceMode::kVoxelFaces));
  ASSERT_TRUE(staircase.ok()) << staircase.status();
  EXPECT_EQ(StaircaseCornersInPlace(b, *staircase, &corners), corners);
  EXPECT_EQ(Measure(b, staircase->mesh).label_mismatch, 0);
  std::cout << corners << " staircase corners, " << corners - kept << " removed with free "
            << "interfaces; voxel-faces reached " << staircase->achieved_reduction << "\n";
}

// The mesh after the half-edge collapse u -> v made by hand: cells holding both are dropped,
// u becomes v in the others (cell order kept, as the engine's output keeps it).
TetMesh CollapseByHand(const TetMesh& in, int32_t u, int32_t v) {
  TetMesh out = in;
  out.tets.clear();
  out.cell_regions.clear();
  for (int64_t c = 0; c < in.tet_count(); ++c) {
    std::array<int32_t, 4> t;
    bool has_u = false, has_v = false;
    for (int k = 0; k < 4; ++k) {
      t[k] = in.tets[4 * c + k];
      has_u |= t[k] == u;
      has_v |= t[k] == v;
    }
    if (has_u && has_v) continue;
    for (int32_t& x : t) x = x == u ? v : x;
    out.tets.insert(out.tets.end(), t.begin(), t.end());
    if (!in.cell_regions.empty()) out.cell_regions.push_back(in.cell_regions[c]);
  }
  return out;
}

// Every vertex's neighbours (the vertices it shares a cell with).
std::map<int32_t, std::set<int32_t>> Neighbours(const TetMesh& mesh) {
  std::map<int32_t, std::set<int32_t>> out;
  for (int64_t c = 0; c < mesh.tet_count(); ++c) {
    for (int i = 0; i < 4; ++i) {
      for (int j = 0; j < 4; ++j) {
        if (i != j) out[mesh.tets[4 * c + i]].insert(mesh.tets[4 * c + j]);
      }
    }
  }
  return out;
}

// The engine's label guard against the metric on single collapses: every collapse of an
// interface vertex of a small block is made by hand and measured. A collapse the metric sees
// give a voxel centre another label (or none) must be refused by the guard, and one the guard
// allows must keep every label. Both kinds must occur.
TEST(FieldFreeInterfaces, TheGuardRefusesEveryCollapseThatChangesAVoxelLabel) {
  const int64_t n = 7;
  const Labeled b = Block(n, 2, 5);
  const SimplifyOptions o = Field(0.5, InterfaceMode::kFree);
  const std::map<int32_t, std::set<int32_t>> neighbours = Neighbours(b.mesh);
  int refused_mismatch = 0, allowed = 0, refused = 0;
  for (const auto& [u, around] : neighbours) {
    bool interface = false;
    for (int32_t x : around) interface |= b.mesh.labels[x] != b.mesh.labels[u];
    if (!interface) continue;
    for (int32_t v : around) {
      const FieldCollapseCheck check = CheckFieldCollapse(b.mesh, o, u, v);
      if (check == FieldCollapseCheck::kNotATarget || check == FieldCollapseCheck::kInvalid) {
        continue;
      }
      const FidelityMetrics m = Measure(b, CollapseByHand(b.mesh, u, v));
      const bool changed = m.label_mismatch > 0 || m.coverage < 1;
      if (check == FieldCollapseCheck::kAllowed) {
        ++allowed;
        EXPECT_FALSE(changed) << "allowed " << u << " -> " << v << " changes "
                              << m.label_mismatch * double(b.image.voxel_count()) << " labels";
      } else {
        ++refused;
        refused_mismatch += changed;
      }
      if (changed) {
        EXPECT_EQ(check, FieldCollapseCheck::kLabelChanged) << u << " -> " << v;
      }
    }
  }
  EXPECT_GT(refused_mismatch, 0);
  EXPECT_GT(allowed, 0);
  std::cout << allowed << " allowed, " << refused << " refused (" << refused_mismatch
            << " of them change a label by the metric)\n";
}

// Topological invariants of every region and union of regions in a mesh: its number of pieces and
// its Euler characteristic, per set of labels (bit l for label l; every non-empty set of the
// labels present). Under the label rule the union of the regions of a set S deformation-retracts
// onto the full subcomplex of the vertices with a label in S (as one region does onto its own:
// field_engine.cc, KeepsRegionTopology; in a cell the points where a label of S weighs most slide
// straight onto the cell's S face), so both are counted there: every face of a cell whose
// vertices all have a label in S, and the pieces by its edges.
struct RegionTopology {
  int64_t pieces = 0, euler = 0;
  bool operator==(const RegionTopology&) const = default;
};

std::map<uint32_t, RegionTopology> Topology(const TetMesh& mesh) {
  std::set<std::vector<int32_t>> faces;
  uint32_t present = 0;
  for (int64_t c = 0; c < mesh.tet_count(); ++c) {
    for (int mask = 1; mask < 16; ++mask) {
      std::vector<int32_t> f;
      for (int k = 0; k < 4; ++k) {
        if (mask >> k & 1) f.push_back(mesh.tets[4 * c + k]);
      }
      std::sort(f.begin(), f.end());
      faces.insert(f);
      present |= 1u << mesh.labels[f[0]];
    }
  }
  std::map<uint32_t, RegionTopology> out;
  for (uint32_t set = present; set != 0; set = (set - 1) & present) {
    auto in = [&](int32_t x) { return (set >> mesh.labels[x] & 1) != 0; };
    std::map<int32_t, int32_t> parent;
    std::function<int32_t(int32_t)> find = [&](int32_t x) {
      return parent[x] == x ? x : parent[x] = find(parent[x]);
    };
    RegionTopology& t = out[set];
    for (const std::vector<int32_t>& f : faces) {
      if (!std::all_of(f.begin(), f.end(), in)) continue;
      t.euler += f.size() % 2 == 1 ? 1 : -1;
      if (f.size() == 1) {
        parent[f[0]] = f[0];
        ++t.pieces;
      }
    }
    for (const std::vector<int32_t>& f : faces) {
      if (f.size() != 2 || !in(f[0]) || !in(f[1])) continue;
      const int32_t a = find(f[0]), b = find(f[1]);
      if (a != b) {
        parent[a] = b;
        --t.pieces;
      }
    }
  }
  return out;
}

// Speckled labels: cubes of g^3 voxels, each of a label drawn by a hash from 2 (label 1 in 0, a
// third of them 1) or 3, with many edge and corner contacts between cubes of one label. A
// collapse across an interface can keep every voxel centre's label and still join two pieces of
// a region or open a hole in it, between the samples.
Labeled Speckles(int64_t n, int labels, int64_t g) {
  auto label = [labels, g](int64_t i, int64_t j, int64_t k) {
    const uint64_t h =
        uint64_t(i / g) * 73856093u ^ uint64_t(j / g) * 19349663u ^ uint64_t(k / g) * 83492791u;
    return labels == 2 ? int((h >> 4) % 3 == 0) : int((h >> 4) % 3);
  };
  return MakeLabeled(
      n, [&](int64_t i, int64_t j, int64_t k) { return 100.0 * label(i, j, k) + 0.2 * (i + j); },
      label);
}

// The link conditions on single collapses: every collapse across an interface that the label guard
// lets through is made by hand, and each label region's pieces and Euler characteristic are
// counted after it. A collapse the engine allows must keep both for every label; some of those
// the label guard alone would allow change them, and the engine refuses them. The speckles are
// simplified to 65 % first: on the voxel grid itself no collapse across an interface keeps the
// labels (u's centre is the midpoint of v and the neighbour opposite, a tie), so the label guard
// would leave nothing to check.
TEST(FieldFreeInterfaces, ACollapseThatKeepsEveryLabelButChangesARegionsTopologyIsRefused) {
  const Labeled in = Speckles(10, 2, 2);
  auto half = Simplify(in.mesh, Field(0.65, InterfaceMode::kFree));
  ASSERT_TRUE(half.ok()) << half.status();
  const TetMesh& mesh = half->mesh;
  const SimplifyOptions o = Field(0.5, InterfaceMode::kFree);
  const std::map<uint32_t, RegionTopology> before = Topology(mesh);
  const std::map<int32_t, std::set<int32_t>> neighbours = Neighbours(mesh);
  int allowed = 0, refused = 0, refused_changed = 0;
  for (const auto& [u, around] : neighbours) {
    for (int32_t v : around) {
      if (mesh.labels[u] == mesh.labels[v]) continue;
      const FieldCollapseCheck check = CheckFieldCollapse(mesh, o, u, v);
      if (check != FieldCollapseCheck::kAllowed && check != FieldCollapseCheck::kTopologyChanged) {
        continue;
      }
      const bool changed = Topology(CollapseByHand(mesh, u, v)) != before;
      if (check == FieldCollapseCheck::kAllowed) {
        ++allowed;
        EXPECT_FALSE(changed) << "allowed " << u << " -> " << v << " changes a region's topology";
      } else {
        ++refused;
        refused_changed += changed;
      }
    }
  }
  EXPECT_GT(allowed, 0);
  EXPECT_GT(refused_changed, 0);
  std::cout << allowed << " collapses across an interface allowed, " << refused
            << " refused by the link conditions (" << refused_changed
            << " of them change a region's pieces or Euler characteristic)\n";
}

// Whole runs on the speckles, two labels and three: every region and every union of regions keeps
// its pieces and Euler characteristic, and every voxel its label. With three labels the unions
// (which regions touch which) are checked too; the engine checks single regions only, and the
// junction rules keep the vertices where three labels meet on their curves.
TEST(FieldFreeInterfaces, SpecklesSimplifiedKeepEveryRegionsTopology) {
  for (const auto& [n, labels, g] : {std::tuple<int64_t, int, int64_t>{12, 2, 2}, {15, 3, 3}}) {
    const Labeled b = Speckles(n, labels, g);
    auto r = Simplify(b.mesh, Field(0.95, InterfaceMode::kFree));
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_GT(r->achieved_reduction, 0.5);
    EXPECT_EQ(Topology(r->mesh), Topology(b.mesh)) << labels << " labels";
    const FidelityMetrics m = Measure(b, r->mesh);
    EXPECT_EQ(m.label_mismatch, 0);
    EXPECT_DOUBLE_EQ(m.coverage, 1.0);
    std::cout << labels << "-label speckles reached " << r->achieved_reduction << "\n";
  }
}

// Three labels: two blocks side by side in a background. The rim of the blocks' shared face
// (i = 7.5) is a junction curve: labels 0, 1 and 2 meet along it. It bends at the face's four
// corners (j = 3.5 | 10.5, k = 3.5 | 7.5). Block 2's corners there (i = 8, j = 4 | 10,
// k = 4 | 7) and block 1's at k = 4 are corners of their own label's layers; at k = 7.5 block 1
// goes on straight and only the label across changes, between its vertices at k = 7 and 8.
// Simplified as far as it goes: those junction corners never move, a vertex of block 1 stays at
// each bend it has no corner at, vertices of the curve's straight runs slide along it (some
// junction vertices are removed), and every label is kept.
TEST(FieldFreeInterfaces, JunctionCornersOfThreeLabelsNeverMove) {
  const int64_t n = 16;
  auto label = [](int64_t i, int64_t j, int64_t k) {
    if (j < 4 || j >= 11 || k < 4 || k >= 11) return 0;
    if (i >= 3 && i < 8) return 1;
    if (i >= 8 && i < 13 && k < 8) return 2;
    return 0;
  };
  const Labeled b = MakeLabeled(
      n, [&](int64_t i, int64_t j, int64_t k) { return 300.0 * label(i, j, k) + 0.5 * j; }, label);
  std::vector<std::set<uint8_t>> around(b.mesh.vertex_count());
  for (int64_t c = 0; c < b.mesh.tet_count(); ++c) {
    for (int i = 0; i < 4; ++i) {
      for (int j = 0; j < 4; ++j) {
        around[b.mesh.tets[4 * c + i]].insert(b.mesh.labels[b.mesh.tets[4 * c + j]]);
      }
    }
  }
  auto r = Simplify(b.mesh, Field(0.99, InterfaceMode::kFree));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_GT(r->achieved_reduction, 0.9);
  auto in_place = [&](int64_t i, int64_t j, int64_t k) {
    const int64_t v = i + n * (j + n * k);
    const int32_t out = r->vertex_map[v];
    return out >= 0 && r->mesh.Position(out) == b.mesh.Position(v);
  };
  int junctions = 0, junctions_kept = 0;
  for (int64_t v = 0; v < b.mesh.vertex_count(); ++v) {
    if (around[v].size() < 3) continue;
    ++junctions;
    junctions_kept += in_place(v % n, (v / n) % n, v / (n * n));
  }
  int corners_kept = 0;
  for (int64_t j : {4, 10}) {
    for (auto [i, k] : {std::pair<int64_t, int64_t>{8, 4}, {8, 7}, {7, 4}}) {
      EXPECT_GE(around[i + n * (j + n * k)].size(), 3u);
      EXPECT_TRUE(in_place(i, j, k))
          << "junction corner (" << i << ", " << j << ", " << k << ") moved";
      corners_kept += in_place(i, j, k);
    }
    EXPECT_TRUE(in_place(7, j, 7) || in_place(7, j, 8))
        << "block 1 left the bend at (7.5, " << j << ", 7.5)";
  }
  EXPECT_EQ(corners_kept, 6);
  EXPECT_GT(junctions, 16);
  EXPECT_LT(junctions_kept, junctions) << "no vertex of a junction curve slid along it";
  const FidelityMetrics m = Measure(b, r->mesh);
  EXPECT_EQ(m.label_mismatch, 0);
  EXPECT_DOUBLE_EQ(m.coverage, 1.0);
}

// The head phantom (three regions, noisy field) on 1 and 2 threads with the free interfaces:
// the same mesh, and every voxel keeps its label.
TEST(FieldFreeInterfaces, SameResultOnOneAndTwoThreadsWithEveryLabelKept) {
  auto pm = testing::MakePhantomMesh(40, 40);
  std::vector<SimplifyResult> results;
  for (int threads : {1, 2}) {
    auto r = Simplify(pm.mesh, Field(0.9, InterfaceMode::kFree, threads));
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_TRUE(r->reached_target) << r->stop_message;
    results.push_back(*std::move(r));
  }
  EXPECT_EQ(results[0].mesh.tets, results[1].mesh.tets);
  EXPECT_EQ(results[0].mesh.positions, results[1].mesh.positions);
  EXPECT_EQ(results[0].mesh.scalars, results[1].mesh.scalars);
  EXPECT_EQ(results[0].vertex_map, results[1].vertex_map);
  FidelityOptions fo;
  fo.labels = &pm.phantom.labels;
  auto m = MeasureFidelity(pm.phantom.image, results[0].mesh, fo);
  ASSERT_TRUE(m.ok());
  EXPECT_EQ(m->label_mismatch, 0);
  EXPECT_DOUBLE_EQ(m->coverage, 1.0);
  EXPECT_TRUE(m->manifold);
}

}  // namespace
}  // namespace decima
