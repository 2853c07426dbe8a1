#include "core/simplify/simplify.h"

#include <algorithm>
#include <cmath>
#include <set>
#include <vector>

#include <gtest/gtest.h>

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

TEST(Simplify, NoisyPhantomAtHalfKeepsFeaturesHullAndConformity) {
  auto pm = MakePhantomMesh(28, 40);
  const TetMesh& in = pm.mesh;
  SimplifyOptions o;
  o.target_reduction = 0.5;
  auto r = Simplify(in, o);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->reached_target) << r->stop_message;
  EXPECT_GE(r->achieved_reduction, 0.5);
  EXPECT_EQ(r->stop_reason, StopReason::kTargetReached);
  EXPECT_GE(r->passes, 1);
  const TetMesh& out = r->mesh;

  FidelityOptions fo;
  fo.labels = &pm.phantom.labels;
  fo.original = &in;
  fo.vertex_map = &r->vertex_map;
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
  const double box = 27.0 * 27.0 * 27.0;
  EXPECT_NEAR(TotalVolume(out), box, 1e-9 * box);
  // Boundary vertices are all still there, unmoved.
  int64_t boundary_in = 0, boundary_out = 0;
  for (int64_t v = 0; v < in.vertex_count(); ++v) {
    if (!(in.vertex_flags[v] & kExteriorBoundaryVertex)) continue;
    ++boundary_in;
    const int32_t n = r->vertex_map[v];
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

}  // namespace
}  // namespace decima
