#include "core/metrics/fidelity.h"

#include <cmath>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/tetrahedralize.h"
#include "core/metrics/fidelity_json.h"
#include "core/volume/phantom.h"

namespace decima {
namespace {

Volume Ramp(std::array<int64_t, 3> dims, Eigen::Vector3d spacing = Eigen::Vector3d::Ones()) {
  auto v = MakeVolume(dims, VoxelType::kFloat32, spacing);
  EXPECT_TRUE(v.ok());
  for (int64_t k = 0, p = 0; k < dims[2]; ++k)
    for (int64_t j = 0; j < dims[1]; ++j)
      for (int64_t i = 0; i < dims[0]; ++i, ++p)
        v->mutable_data<float>()[p] = float(10 * i + 3 * j - 2 * k + ((i * j + k) % 5));
  return *std::move(v);
}

TetMesh Mesh(const Volume& v, const Volume* labels = nullptr) {
  TetrahedralizeOptions o;
  o.labels = labels;
  auto m = Tetrahedralize(v, o);
  EXPECT_TRUE(m.ok());
  return *std::move(m);
}

TEST(Fidelity, UnsimplifiedMeshReproducesTheVolumeExactly) {
  HeadPhantomOptions po;
  po.dims = {14, 12, 10};
  po.noise_sigma = 30;
  auto p = MakeHeadPhantom(po);
  ASSERT_TRUE(p.ok());
  const TetMesh m = Mesh(p->image, &p->labels);
  std::vector<int32_t> identity(m.vertex_count());
  for (int64_t v = 0; v < m.vertex_count(); ++v) identity[v] = int32_t(v);
  TetMesh flagged = m;
  for (int64_t v = 0; v < 40; ++v) flagged.vertex_flags[v] |= kFeatureVertex;
  FidelityOptions o;
  o.labels = &p->labels;
  o.original = &flagged;
  o.vertex_map = &identity;
  o.mesh_bytes = 1234;
  auto f = MeasureFidelity(p->image, m, o);
  ASSERT_TRUE(f.ok()) << f.status();
  EXPECT_EQ(f->grid_points, 14 * 12 * 10);
  EXPECT_DOUBLE_EQ(f->coverage, 1.0);
  EXPECT_LT(f->max_abs_error, 1e-3);
  EXPECT_GT(f->psnr_db, 100);
  EXPECT_DOUBLE_EQ(f->mean_dice, 1.0);
  EXPECT_EQ(f->label_mismatch, 0);
  EXPECT_EQ(f->feature_vertices, 40);
  EXPECT_EQ(f->feature_vertices_moved + f->feature_vertices_removed, 0);
  EXPECT_EQ(f->inverted_cells + f->degenerate_cells, 0);
  // The 5-tets-per-cube split: corner tets have 54.7356 degree dihedral angles at the slanted
  // face, the smallest in the mesh.
  EXPECT_NEAR(f->min_dihedral_deg, std::acos(1 / std::sqrt(3.0)) * 180 / M_PI, 1e-6);
  EXPECT_EQ(f->voxel_bytes, 14 * 12 * 10 * 4);
  EXPECT_NEAR(f->bytes_ratio, 1234.0 / (14 * 12 * 10 * 4), 1e-12);
}

TEST(Fidelity, ConstantOffsetGivesThatRmseAndPsnr) {
  const Volume v = Ramp({8, 9, 7});
  TetMesh m = Mesh(v);
  for (float& s : m.scalars) s += 2.5f;
  auto f = MeasureFidelity(v, m);
  ASSERT_TRUE(f.ok());
  EXPECT_NEAR(f->rmse, 2.5, 1e-3);
  EXPECT_NEAR(f->max_abs_error, 2.5, 1e-3);
  const auto [lo, hi] = v.ValueRange();
  EXPECT_NEAR(f->psnr_db, 20 * std::log10((hi - lo) / 2.5), 1e-3);
}

TEST(Fidelity, AnisotropicRotatedGridIsResampledInIndexSpace) {
  Volume v = Ramp({6, 7, 5}, {0.7, 1.3, 2.0});
  v.origin = {-10, 5, 3};
  v.direction = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const TetMesh m = Mesh(v);
  auto f = MeasureFidelity(v, m);
  ASSERT_TRUE(f.ok()) << f.status();
  EXPECT_DOUBLE_EQ(f->coverage, 1.0);
  EXPECT_LT(f->max_abs_error, 1e-3);
}

TEST(Fidelity, PointsOutsideTheMeshCountAsUncoveredAndWrongLabel) {
  const Volume v = Ramp({6, 6, 6});
  auto labels = MakeVolume(v.dims, VoxelType::kUInt8);
  ASSERT_TRUE(labels.ok());
  TetMesh m = Mesh(v);
  // Keep only the cells of the lower half (z <= 2): grid points with z > 2 are outside.
  TetMesh half = m;
  half.tets.clear();
  half.cell_regions.clear();
  for (int64_t t = 0; t < m.tet_count(); ++t) {
    bool low = true;
    for (int k = 0; k < 4; ++k) low &= m.positions[3 * m.tets[4 * t + k] + 2] <= 2.0f;
    if (!low) continue;
    half.tets.insert(half.tets.end(), &m.tets[4 * t], &m.tets[4 * t] + 4);
    half.cell_regions.push_back(0);
  }
  FidelityOptions o;
  o.labels = &*labels;
  auto f = MeasureFidelity(v, half, o);
  ASSERT_TRUE(f.ok());
  EXPECT_EQ(f->covered_points, 6 * 6 * 3);
  EXPECT_DOUBLE_EQ(f->coverage, 0.5);
  EXPECT_DOUBLE_EQ(f->label_mismatch, 0.5);
  ASSERT_EQ(f->dice.size(), 1u);
  EXPECT_NEAR(f->dice[0].dice, 2.0 * 108 / (216 + 108), 1e-12);
}

TEST(Fidelity, CountsInvertedCellsAndMovedOrMergedFeatureVertices) {
  const Volume v = Ramp({4, 4, 4});
  TetMesh orig = Mesh(v);
  orig.vertex_flags[0] |= kFeatureVertex;
  orig.vertex_flags[1] |= kFeatureVertex;
  orig.vertex_flags[2] |= kFeatureVertex;
  TetMesh out = orig;
  std::swap(out.tets[2], out.tets[3]);  // cell 0 inverted
  out.positions[3 * 5] += 0.1f;
  std::vector<int32_t> map(orig.vertex_count());
  for (int64_t i = 0; i < orig.vertex_count(); ++i) map[i] = int32_t(i);
  map[1] = 0;                              // feature 1 merged into feature 0
  map[2] = -1;                             // feature 2 removed
  orig.vertex_flags[5] |= kFeatureVertex;  // feature 5 moved
  // Feature 3 merged into feature 7, which comes later in index order and stays in place: a
  // removal, not a move (half-edge collapses merge in any order).
  orig.vertex_flags[3] |= kFeatureVertex;
  orig.vertex_flags[7] |= kFeatureVertex;
  map[3] = 7;
  FidelityOptions o;
  o.original = &orig;
  o.vertex_map = &map;
  auto f = MeasureFidelity(v, out, o);
  ASSERT_TRUE(f.ok());
  EXPECT_EQ(f->feature_vertices, 6);
  EXPECT_EQ(f->feature_vertices_removed, 3);
  EXPECT_EQ(f->feature_vertices_moved, 1);
  EXPECT_EQ(f->inverted_cells, 1);
  // The inverted cell lies on the same side of its interior faces as its neighbours.
  EXPECT_GE(f->folded_faces, 1);
  EXPECT_FALSE(f->manifold);
}

// A job counts the feature vertices before it frees the original (issue 30) and passes the
// counts in: the same figures as from the original and the vertex map.
TEST(Fidelity, FeatureCountsMadeBeforeGiveTheSameFigures) {
  const Volume v = Ramp({4, 4, 4});
  TetMesh orig = Mesh(v);
  for (int32_t f : {0, 1, 2, 3, 5, 7}) orig.vertex_flags[f] |= kFeatureVertex;
  TetMesh out = orig;
  out.positions[3 * 5] += 0.1f;
  std::vector<int32_t> map(orig.vertex_count());
  for (int64_t i = 0; i < orig.vertex_count(); ++i) map[i] = int32_t(i);
  map[1] = 0;
  map[2] = -1;
  map[3] = 7;
  auto counts = CountFeatureVertices(orig, map, out);
  ASSERT_TRUE(counts.ok()) << counts.status();
  EXPECT_EQ(counts->vertices, 6);
  EXPECT_EQ(counts->removed, 3);
  EXPECT_EQ(counts->moved, 1);

  FidelityOptions from_mesh;
  from_mesh.original = &orig;
  from_mesh.vertex_map = &map;
  FidelityOptions from_counts;
  from_counts.feature_counts = &*counts;
  auto a = MeasureFidelity(v, out, from_mesh);
  auto b = MeasureFidelity(v, out, from_counts);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->feature_vertices, b->feature_vertices);
  EXPECT_EQ(a->feature_vertices_removed, b->feature_vertices_removed);
  EXPECT_EQ(a->feature_vertices_moved, b->feature_vertices_moved);

  // Both sources at once, or a vertex map of the wrong size, are refused.
  from_counts.original = &orig;
  from_counts.vertex_map = &map;
  EXPECT_TRUE(absl::IsInvalidArgument(MeasureFidelity(v, out, from_counts).status()));
  map.pop_back();
  EXPECT_TRUE(absl::IsInvalidArgument(CountFeatureVertices(orig, map, out).status()));
}

TEST(Fidelity, RejectsInconsistentInputs) {
  const Volume v = Ramp({4, 4, 4});
  const TetMesh m = Mesh(v);
  TetMesh bad = m;
  bad.tets[0] = 999;
  EXPECT_EQ(MeasureFidelity(v, bad).status().code(), absl::StatusCode::kInvalidArgument);
  auto labels = MakeVolume({4, 4, 5}, VoxelType::kUInt8);
  FidelityOptions o;
  o.labels = &*labels;
  EXPECT_EQ(MeasureFidelity(v, m, o).status().code(), absl::StatusCode::kInvalidArgument);
  std::vector<int32_t> short_map(3, 0);
  FidelityOptions o2;
  o2.original = &m;
  o2.vertex_map = &short_map;
  auto s = MeasureFidelity(v, m, o2);
  EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.status().message().find("vertex_map"), std::string::npos);
  FidelityOptions o3;
  o3.original = &m;
  EXPECT_EQ(MeasureFidelity(v, m, o3).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(Fidelity, ResultDoesNotDependOnThreads) {
  const Volume v = Ramp({20, 18, 16});
  const TetMesh m = Mesh(v);
  auto a = ResampleOnGrid(v, m, 1);
  auto b = ResampleOnGrid(v, m, 3);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->cell, b->cell);
  EXPECT_EQ(a->values, b->values);
}

// Tets sharing the face (0, 1, 2) in the z = 0 plane, one per apex, each ordered to be positively
// oriented.
TetMesh FanAroundOneFace(const std::vector<float>& apex_z) {
  TetMesh m;
  m.positions = {0, 0, 0, 4, 0, 0, 0, 4, 0};
  for (size_t i = 0; i < apex_z.size(); ++i) {
    m.positions.insert(m.positions.end(), {1, 1, apex_z[i]});
    const int32_t a = int32_t(3 + i);
    if (apex_z[i] > 0) {
      m.tets.insert(m.tets.end(), {0, 1, 2, a});
    } else {
      m.tets.insert(m.tets.end(), {0, 2, 1, a});
    }
  }
  const int64_t nv = m.positions.size() / 3;
  m.scalars.assign(nv, 1.0f);
  m.labels.assign(nv, 0);
  m.interface_distance.assign(nv, 1.0f);
  m.vertex_flags.assign(nv, 0);
  m.cell_regions.assign(m.tet_count(), 0);
  for (int64_t t = 0; t < m.tet_count(); ++t) EXPECT_GT(TetVolume(m, t), 0) << t;
  return m;
}

TEST(Fidelity, GridMeshIsManifoldWithTheBoxAsItsBoundary) {
  const Volume v = Ramp({6, 5, 4}, {0.5, 1.0, 2.0});
  const TetMesh m = Mesh(v);
  // Cubes 5 x 4 x 3, two triangles per boundary square.
  const int64_t boundary = 2 * 2 * (5 * 4 + 4 * 3 + 5 * 3);
  for (int threads : {1, 3}) {
    const FaceCounts c = CountFaces(m, threads);
    EXPECT_EQ(c.boundary_faces, boundary);
    EXPECT_EQ(c.interior_faces, (4 * m.tet_count() - boundary) / 2);
    EXPECT_EQ(c.nonmanifold_faces, 0);
    EXPECT_EQ(c.folded_faces, 0);
    // Box 2.5 x 4 x 6 mm.
    EXPECT_NEAR(c.boundary_area_mm2, 2 * (2.5 * 4 + 4 * 6 + 2.5 * 6), 1e-9);
  }
  auto f = MeasureFidelity(v, m);
  ASSERT_TRUE(f.ok());
  EXPECT_TRUE(f->manifold);
  EXPECT_EQ(f->boundary_faces, boundary);
  EXPECT_EQ(f->nonmanifold_faces, 0);
}

TEST(Fidelity, FaceSharedByThreeCellsIsReportedNonManifold) {
  const TetMesh m = FanAroundOneFace({1, -1, 2});
  const FaceCounts c = CountFaces(m);
  EXPECT_EQ(c.nonmanifold_faces, 1);
  EXPECT_EQ(c.interior_faces, 0);
  EXPECT_EQ(c.boundary_faces, 9);  // the three other faces of each tet
  const Volume v = Ramp({4, 4, 4});
  auto f = MeasureFidelity(v, m);
  ASSERT_TRUE(f.ok()) << f.status();
  EXPECT_EQ(f->nonmanifold_faces, 1);
  EXPECT_FALSE(f->manifold);
  const auto json = FidelityToJson(*f);
  EXPECT_EQ(json["nonmanifold_faces"], 1);
  EXPECT_EQ(json["manifold"], false);
  EXPECT_EQ(json["boundary_faces"], 9);
}

TEST(Fidelity, TwoCellsOnTheSameSideOfTheirFaceAreAFold) {
  const FaceCounts opposite = CountFaces(FanAroundOneFace({1, -1}));
  EXPECT_EQ(opposite.interior_faces, 1);
  EXPECT_EQ(opposite.folded_faces, 0);
  const FaceCounts same = CountFaces(FanAroundOneFace({1, 2}));
  EXPECT_EQ(same.interior_faces, 1);
  EXPECT_EQ(same.folded_faces, 1);
  EXPECT_EQ(same.nonmanifold_faces, 0);
}

}  // namespace
}  // namespace decima
