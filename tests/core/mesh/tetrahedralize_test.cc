#include "core/mesh/tetrahedralize.h"
#include "tests/testing/mesh_checks.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/grid_tets.h"
#include "core/volume/phantom.h"

namespace decima {
namespace {

Volume Ramp(std::array<int64_t, 3> dims, Eigen::Vector3d spacing = Eigen::Vector3d::Ones()) {
  auto v = MakeVolume(dims, VoxelType::kInt16, spacing);
  EXPECT_TRUE(v.ok());
  for (int64_t i = 0; i < v->voxel_count(); ++i) v->mutable_data<int16_t>()[i] = int16_t(i % 1000);
  return *std::move(v);
}

using ::decima::testing::FaceUse;

double BoxVolume(const Volume& v) {
  return (v.dims[0] - 1) * v.spacing[0] * (v.dims[1] - 1) * v.spacing[1] * (v.dims[2] - 1) *
         v.spacing[2];
}

void ExpectValidMesh(const Volume& image, const TetMesh& m) {
  const int64_t nx = image.dims[0], ny = image.dims[1], nz = image.dims[2];
  ASSERT_EQ(m.vertex_count(), nx * ny * nz);
  ASSERT_EQ(m.tet_count(), 5 * (nx - 1) * (ny - 1) * (nz - 1));
  double total = 0;
  for (int64_t t = 0; t < m.tet_count(); ++t) {
    const double vol = TetVolume(m, t);
    ASSERT_GT(vol, 0) << "tet " << t << " is not positively oriented";
    total += vol;
  }
  EXPECT_NEAR(total, BoxVolume(image), 1e-6 * BoxVolume(image));

  int64_t boundary_faces = 0;
  for (const auto& [face, count] : FaceUse(m)) {
    ASSERT_LE(count, 2) << "face shared by " << count << " tets";
    if (count == 1) {
      ++boundary_faces;
      for (int32_t v : face) ASSERT_TRUE(m.vertex_flags[v] & kExteriorBoundaryVertex);
    }
  }
  // Every square on the box surface is split into exactly two triangles.
  EXPECT_EQ(boundary_faces, 4 * ((nx - 1) * (ny - 1) + (nx - 1) * (nz - 1) + (ny - 1) * (nz - 1)));
}

TEST(Tetrahedralize, SingleCubeGivesFiveTetsFillingIt) {
  Volume v = Ramp({2, 2, 2});
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok()) << m.status();
  ExpectValidMesh(v, *m);
}

TEST(Tetrahedralize, NeighbouringCubesShareWholeFaces) {
  Volume v = Ramp({5, 4, 6});
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok()) << m.status();
  ExpectValidMesh(v, *m);
  // Scalars are the voxel values at the voxel centres.
  EXPECT_EQ(m->scalars[v.Index(3, 2, 4)], float(v.Index(3, 2, 4) % 1000));
}

TEST(Tetrahedralize, AnisotropicSpacingAndRotatedDirection) {
  Volume v = Ramp({4, 5, 3}, Eigen::Vector3d(0.7, 1.3, 2.5));
  v.origin = Eigen::Vector3d(-10, 4, 2);
  v.direction = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok()) << m.status();
  ExpectValidMesh(v, *m);
  const Eigen::Vector3d expected = v.PhysicalPoint(3, 1, 2);
  EXPECT_TRUE(m->Position(v.Index(3, 1, 2)).isApprox(expected, 1e-6));
}

TEST(Tetrahedralize, MirroredDirectionStillGivesPositiveTets) {
  Volume v = Ramp({3, 4, 5}, Eigen::Vector3d(1, 1, 2));
  v.direction = Eigen::Vector3d(-1, -1, 1).asDiagonal() * Eigen::Matrix3d::Identity();
  v.direction.col(2) *= -1;  // determinant -1
  ASSERT_LT(v.direction.determinant(), 0);
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok()) << m.status();
  ExpectValidMesh(v, *m);
}

TEST(Tetrahedralize, PaperCtHeadSizeGivesTable1Counts) {
  auto v = MakeVolume({128, 128, 53}, VoxelType::kUInt16);
  ASSERT_TRUE(v.ok());
  auto m = Tetrahedralize(*v);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->vertex_count(), 868352);
  EXPECT_EQ(m->tet_count(), 4193540);
}

TEST(Tetrahedralize, OutputDoesNotDependOnThreadCount) {
  Volume v = Ramp({9, 7, 11});
  TetrahedralizeOptions one, two;
  one.threads = 1;
  two.threads = 2;
  auto a = Tetrahedralize(v, one), b = Tetrahedralize(v, two);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->tets, b->tets);
  EXPECT_EQ(a->positions, b->positions);
}

TEST(Tetrahedralize, CarriesLabelsDistancesAndFeatureFlags) {
  HeadPhantomOptions o;
  o.dims = {12, 12, 12};
  o.region_means = {0, 100};
  auto p = MakeHeadPhantom(o);
  ASSERT_TRUE(p.ok());
  std::vector<float> distance(p->image.voxel_count(), 3.0f);
  distance[p->image.Index(6, 6, 6)] = 0.5f;
  distance[p->image.Index(6, 6, 7)] = -0.4f;
  distance[p->image.Index(6, 6, 8)] = 0.6f;
  TetrahedralizeOptions opts;
  opts.labels = &p->labels;
  opts.interface_distance = distance.data();
  auto m = Tetrahedralize(p->image, opts);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_TRUE(m->vertex_flags[p->image.Index(6, 6, 6)] & kFeatureVertex);
  EXPECT_TRUE(m->vertex_flags[p->image.Index(6, 6, 7)] & kFeatureVertex);
  EXPECT_FALSE(m->vertex_flags[p->image.Index(6, 6, 8)] & kFeatureVertex);
  EXPECT_EQ(m->labels[p->image.Index(6, 6, 6)], 1);
  EXPECT_EQ(m->labels[0], 0);
  for (int64_t t = 0; t < m->tet_count(); ++t) {
    const int32_t* tv = &m->tets[4 * t];
    EXPECT_EQ(m->cell_regions[t],
              CellRegion(m->labels[tv[0]], m->labels[tv[1]], m->labels[tv[2]], m->labels[tv[3]]));
  }
}

TEST(Tetrahedralize, RejectsFlatVolumesAndForeignLabelGrids) {
  Volume flat = Ramp({8, 8, 1});
  auto m = Tetrahedralize(flat);
  ASSERT_FALSE(m.ok());
  EXPECT_NE(m.status().message().find("at least 2 voxels"), std::string::npos) << m.status();

  Volume v = Ramp({4, 4, 4});
  auto labels = MakeVolume({4, 4, 5}, VoxelType::kUInt8);
  TetrahedralizeOptions opts;
  opts.labels = &*labels;
  EXPECT_FALSE(Tetrahedralize(v, opts).ok());
}

// GridTets is the one definition of the grid's cells; a stage that reads cells from it instead
// of the mesh must see exactly the mesh Tetrahedralize wrote, for either orientation and for
// dimensions of every parity.
TEST(GridTets, GivesTheCellsTetrahedralizeWrites) {
  for (const bool mirrored : {false, true}) {
    for (const std::array<int64_t, 3> dims :
         {std::array<int64_t, 3>{2, 2, 2}, {5, 4, 3}, {4, 7, 6}}) {
      Volume v = Ramp(dims);
      if (mirrored) v.direction.col(1) *= -1;
      auto m = Tetrahedralize(v);
      ASSERT_TRUE(m.ok()) << m.status();
      const GridTets grid(dims[0], dims[1], dims[2], v.direction.determinant() < 0);
      ASSERT_EQ(grid.tet_count(), m->tet_count());
      ASSERT_EQ(grid.vertex_count(), m->vertex_count());
      for (int64_t t = 0; t < m->tet_count(); ++t) {
        int32_t cell[4];
        grid.Cell(t, cell);
        for (int q = 0; q < 4; ++q) {
          ASSERT_EQ(cell[q], m->tets[4 * t + q])
              << "tet " << t << " vertex " << q << (mirrored ? " (mirrored)" : "");
        }
      }
    }
  }
}

// ForEachCell steps from cube to cube instead of dividing each id: from any start (inside a cube,
// at the end of a row or of a slice) it gives Cell(t) for every t of the range, in order.
TEST(GridTets, ForEachCellStepsThroughTheCellsCellComputes) {
  for (const std::array<int64_t, 3> dims :
       {std::array<int64_t, 3>{2, 2, 2}, {5, 4, 3}, {4, 7, 6}, {3, 2, 5}}) {
    const GridTets grid(dims[0], dims[1], dims[2], false);
    const int64_t nt = grid.tet_count(), row = 5 * (dims[0] - 1);
    const int64_t slice = row * (dims[1] - 1);
    for (const auto& [t0, t1] :
         std::vector<std::pair<int64_t, int64_t>>{{0, nt},
                                                  {3, nt},
                                                  {row - 1, nt - 2},
                                                  {slice - 2, slice + row + 3},
                                                  {nt - 1, nt},
                                                  {7, 7}}) {
      if (t0 > t1 || t1 > nt) continue;
      int64_t expected = t0;
      grid.ForEachCell(t0, t1, [&](int64_t t, const int32_t* cell) {
        ASSERT_EQ(t, expected);
        int32_t want[4];
        grid.Cell(t, want);
        for (int q = 0; q < 4; ++q) {
          ASSERT_EQ(cell[q], want[q]) << "tet " << t << " of [" << t0 << ", " << t1 << ")";
        }
        ++expected;
      });
      EXPECT_EQ(expected, t1) << "range [" << t0 << ", " << t1 << ")";
    }
  }
}

// A mesh records its grid, so a stage can free its cells and get them back: dropped, it still
// counts them and gives each through Cell; restored, tets and cell_regions are what
// Tetrahedralize wrote (labelled phantom, either orientation); the adjacency built from the grid is
// the one built from the array.
TEST(GridTets, DroppedCellsAreCountedComputedAndRestoredAsTetrahedralizeWroteThem) {
  for (const bool mirrored : {false, true}) {
    HeadPhantomOptions o;
    o.dims = {9, 8, 7};
    o.region_means = {0, 100, 50};
    auto p = MakeHeadPhantom(o);
    ASSERT_TRUE(p.ok());
    if (mirrored) {
      p->image.direction.col(2) *= -1;
      p->labels.direction = p->image.direction;
    }
    TetrahedralizeOptions opts;
    opts.labels = &p->labels;
    opts.threads = 2;
    auto m = Tetrahedralize(p->image, opts);
    ASSERT_TRUE(m.ok()) << m.status();
    ASSERT_TRUE(m->grid.has_value());
    EXPECT_EQ(m->grid->flip(), mirrored);
    const TetMesh written = *m;
    const VertexTetAdjacency from_array = BuildVertexTetAdjacency(written, 2);
    DropGridCells(&*m);
    ASSERT_TRUE(m->cells_dropped);
    EXPECT_TRUE(m->tets.empty());
    EXPECT_TRUE(m->cell_regions.empty());
    EXPECT_EQ(m->tet_count(), written.tet_count());
    for (int64_t t = 0; t < m->tet_count(); ++t) {
      int32_t cell[4];
      m->Cell(t, cell);
      for (int q = 0; q < 4; ++q) ASSERT_EQ(cell[q], written.tets[4 * t + q]) << "tet " << t;
      ASSERT_EQ(TetVolume(*m, t), TetVolume(written, t)) << "tet " << t;
    }
    const VertexTetAdjacency from_grid = BuildVertexTetAdjacency(*m, 2);
    EXPECT_EQ(from_grid.offsets, from_array.offsets);
    EXPECT_EQ(from_grid.tet_ids, from_array.tet_ids);
    // Tetrahedralize without cells gives the mesh DropGridCells leaves: the same vertices and
    // grid, no cell written.
    TetrahedralizeOptions without = opts;
    without.cells = false;
    auto bare = Tetrahedralize(p->image, without);
    ASSERT_TRUE(bare.ok()) << bare.status();
    EXPECT_TRUE(bare->cells_dropped);
    EXPECT_TRUE(bare->tets.empty());
    EXPECT_TRUE(bare->cell_regions.empty());
    EXPECT_EQ(bare->tet_count(), written.tet_count());
    EXPECT_EQ(bare->positions, written.positions);
    EXPECT_EQ(bare->vertex_flags, written.vertex_flags);
    EXPECT_EQ(bare->labels, written.labels);
    RestoreGridCells(&*bare, 1);
    EXPECT_EQ(bare->tets, written.tets);
    EXPECT_EQ(bare->cell_regions, written.cell_regions);
    RestoreGridCells(&*m, 2);
    EXPECT_FALSE(m->cells_dropped);
    // Cells cleared by an editor (not dropped) are not read as the grid's.
    TetMesh edited = written;
    edited.tets.clear();
    EXPECT_EQ(edited.tet_count(), 0);
    EXPECT_EQ(m->tets, written.tets);
    EXPECT_EQ(m->cell_regions, written.cell_regions);
  }
  // A mesh without a grid (read from a file, a simplified one) keeps its cells.
  TetMesh plain;
  plain.tets = {0, 1, 2, 3};
  plain.cell_regions = {0};
  DropGridCells(&plain);
  EXPECT_EQ(plain.tets.size(), 4u);
  EXPECT_FALSE(plain.cells_dropped);
}

TEST(Tetrahedralize, CellRegionIsMajorityWithTiesToSmaller) {
  EXPECT_EQ(CellRegion(2, 2, 1, 0), 2);
  EXPECT_EQ(CellRegion(2, 1, 2, 1), 1);
  EXPECT_EQ(CellRegion(3, 3, 3, 3), 3);
  EXPECT_EQ(CellRegion(0, 1, 2, 3), 0);
}

TEST(MeshTopology, AdjacencyListsEveryIncidentTetOnce) {
  Volume v = Ramp({4, 3, 3});
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok());
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(*m);
  ASSERT_EQ(adj.offsets.size(), size_t(m->vertex_count() + 1));
  EXPECT_EQ(adj.offsets.back(), 4 * m->tet_count());
  for (int64_t vtx = 0; vtx < m->vertex_count(); ++vtx) {
    for (int64_t e = adj.offsets[vtx]; e < adj.offsets[vtx + 1]; ++e) {
      const int32_t* tv = &m->tets[4 * adj.tet_ids[e]];
      EXPECT_TRUE(tv[0] == vtx || tv[1] == vtx || tv[2] == vtx || tv[3] == vtx);
      if (e > adj.offsets[vtx]) {
        EXPECT_LT(adj.tet_ids[e - 1], adj.tet_ids[e]);
      }
    }
  }
}

// On several threads the tets are counted and filled in chunks (at least 65536 tets each): the
// rows must come out exactly as the one-thread build makes them.
TEST(MeshTopology, AdjacencyIsTheSameOnOneTwoAndThreeThreads) {
  Volume v = Ramp({40, 40, 40});
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok());
  ASSERT_GT(m->tet_count(), 3 * 65536);  // three chunks
  const VertexTetAdjacency one = BuildVertexTetAdjacency(*m, 1);
  for (int threads : {2, 3}) {
    const VertexTetAdjacency many = BuildVertexTetAdjacency(*m, threads);
    EXPECT_EQ(one.offsets, many.offsets) << threads;
    EXPECT_EQ(one.tet_ids, many.tet_ids) << threads;
  }
  EXPECT_EQ(one.offsets.back(), 4 * m->tet_count());
}

// Every face of a tet has exactly one tet across it or none (the box hull), and the tet across
// holds that face: on a single cube the central tet of the five has a neighbour across each of its
// faces, and every face of a corner tet with the cube's corner on it lies on the hull.
TEST(MeshTopology, TetAcrossFaceFindsTheOtherTetOrNone) {
  Volume v = Ramp({2, 2, 2});
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok());
  ASSERT_EQ(m->tet_count(), 5);
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(*m);
  int64_t interior = 0, hull = 0;
  for (int64_t t = 0; t < m->tet_count(); ++t) {
    const int32_t* c = &m->tets[4 * t];
    for (int k = 0; k < 4; ++k) {
      const int32_t a = c[(k + 1) % 4], b = c[(k + 2) % 4], d = c[(k + 3) % 4];
      const int64_t other = TetAcrossFace(*m, adj, t, a, b, d);
      if (other < 0) {
        ++hull;
        continue;
      }
      ++interior;
      EXPECT_NE(other, t);
      const int32_t* o = &m->tets[4 * other];
      for (int32_t x : {a, b, d}) {
        EXPECT_TRUE(o[0] == x || o[1] == x || o[2] == x || o[3] == x) << t << " " << k;
      }
      // Across the same face from the other side leads back.
      EXPECT_EQ(TetAcrossFace(*m, adj, other, b, d, a), t);
    }
  }
  EXPECT_EQ(interior, 8);  // the central tet's four faces, seen from both sides
  EXPECT_EQ(hull, 12);     // two triangles per face of the cube
}

TEST(MeshTopology, BoundarySurfaceIsTheBoxHullFacingOutwards) {
  Volume v = Ramp({4, 5, 3}, Eigen::Vector3d(1, 2, 3));
  auto m = Tetrahedralize(v);
  ASSERT_TRUE(m.ok());
  const BoundarySurface b = ExtractBoundary(*m);
  const int64_t nx = 4, ny = 5, nz = 3;
  EXPECT_EQ(int64_t(b.faces.size() / 3),
            4 * ((nx - 1) * (ny - 1) + (nx - 1) * (nz - 1) + (ny - 1) * (nz - 1)));
  for (int64_t vtx = 0; vtx < m->vertex_count(); ++vtx) {
    EXPECT_EQ(bool(b.is_boundary_vertex[vtx]),
              bool(m->vertex_flags[vtx] & kExteriorBoundaryVertex));
  }
  // Divergence theorem: sum over outward faces of (centroid . normal) / 3 = enclosed volume.
  double volume = 0;
  for (size_t f = 0; f < b.faces.size(); f += 3) {
    const Eigen::Vector3d a = m->Position(b.faces[f]), c1 = m->Position(b.faces[f + 1]),
                          c2 = m->Position(b.faces[f + 2]);
    volume += a.dot(c1.cross(c2)) / 6.0;
  }
  EXPECT_NEAR(volume, BoxVolume(v), 1e-6);
}

// GridTets::Neighbour against the adjacency of the materialized mesh (TetAcrossFace over its
// vertex-tet lists): every face of every tet, on odd and even dims (so both cube parities meet
// every side), with and without an orientation-reversing direction (the stored vertex order, and
// so which face is q, changes with it).
TEST(GridTets, NeighbourIsTheTetAcrossTheFaceOfTheMaterializedMesh) {
  struct Case {
    std::array<int64_t, 3> dims;
    bool flip;
  };
  for (const Case& c : {Case{{2, 2, 2}, false}, Case{{3, 3, 3}, false}, Case{{5, 4, 6}, false},
                        Case{{4, 5, 3}, true}, Case{{7, 3, 4}, true}, Case{{6, 6, 5}, false}}) {
    SCOPED_TRACE(::testing::Message() << c.dims[0] << "x" << c.dims[1] << "x" << c.dims[2]
                                      << (c.flip ? " flipped" : ""));
    Volume v = Ramp(c.dims);
    if (c.flip) v.direction.col(2) *= -1;
    auto m = Tetrahedralize(v);
    ASSERT_TRUE(m.ok()) << m.status();
    ASSERT_TRUE(m->grid.has_value());
    ASSERT_EQ(m->grid->flip(), c.flip);
    const VertexTetAdjacency adj = BuildVertexTetAdjacency(*m);
    int64_t boundary = 0;
    for (int64_t t = 0; t < m->tet_count(); ++t) {
      const int32_t* tv = &m->tets[4 * t];
      for (int q = 0; q < 4; ++q) {
        int32_t f[3], n = 0;
        for (int r = 0; r < 4; ++r)
          if (r != q) f[n++] = tv[r];
        const int64_t expected = TetAcrossFace(*m, adj, t, f[0], f[1], f[2]);
        ASSERT_EQ(m->grid->Neighbour(t, q), expected) << "tet " << t << " face " << q;
        boundary += expected < 0;
      }
    }
    const int64_t nx = c.dims[0], ny = c.dims[1], nz = c.dims[2];
    EXPECT_EQ(boundary, 4 * ((nx - 1) * (ny - 1) + (nx - 1) * (nz - 1) + (ny - 1) * (nz - 1)));
  }
}

}  // namespace
}  // namespace decima
