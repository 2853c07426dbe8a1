// Region surfaces: closed, consistently oriented out of their region, 2-manifold also where a
// region touches itself along an edge or at a vertex, enclosing exactly the region's cells, and
// written as binary STL that reads back.
#include "core/mesh/region_surface.h"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <iterator>

#include "core/mesh/tetrahedralize.h"
#include "core/volume/volume.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

Volume Zeros(std::array<int64_t, 3> dims, Eigen::Vector3d spacing = Eigen::Vector3d::Ones()) {
  auto v = MakeVolume(dims, VoxelType::kInt16, spacing);
  EXPECT_TRUE(v.ok());
  return *std::move(v);
}

// The grid's mesh with each cell's region chosen from its centroid (index space = mm here).
TetMesh MeshWithRegions(std::array<int64_t, 3> dims,
                        const std::function<uint8_t(const Eigen::Vector3d&)>& region_at,
                        Eigen::Vector3d spacing = Eigen::Vector3d::Ones()) {
  Volume v = Zeros(dims, spacing);
  auto m = Tetrahedralize(v);
  EXPECT_TRUE(m.ok()) << m.status();
  for (int64_t t = 0; t < m->tet_count(); ++t) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) c += m->Position(m->tets[4 * t + k]) / 4.0;
    m->cell_regions[t] = region_at(c.cwiseQuotient(spacing));
  }
  return *std::move(m);
}

// Volume enclosed by a closed surface (divergence theorem); positive when normals point out.
double EnclosedVolume(const RegionSurface& s) {
  double sum = 0;
  for (int64_t f = 0; f < s.triangle_count(); ++f) {
    Eigen::Vector3d p[3];
    for (int k = 0; k < 3; ++k) {
      const int64_t v = s.triangles[3 * f + k];
      p[k] = {s.positions[3 * v], s.positions[3 * v + 1], s.positions[3 * v + 2]};
    }
    sum += p[0].dot(p[1].cross(p[2])) / 6.0;
  }
  return sum;
}

double RegionVolume(const TetMesh& m, uint8_t region) {
  double sum = 0;
  for (int64_t t = 0; t < m.tet_count(); ++t) {
    if (m.cell_regions[t] == region) sum += TetVolume(m, t);
  }
  return sum;
}

void ExpectClosedManifold(const RegionSurface& s, int64_t euler) {
  const SurfaceTopology topo = MeasureTopology(s);
  EXPECT_EQ(topo.boundary_edges, 0) << "region " << int{s.region};
  EXPECT_EQ(topo.non_manifold_edges, 0) << "region " << int{s.region};
  EXPECT_EQ(topo.misoriented_edges, 0) << "region " << int{s.region};
  EXPECT_EQ(topo.euler_characteristic, euler) << "region " << int{s.region};
}

TEST(RegionSurface, ASphereInABoxGivesTwoClosedSurfacesEnclosingTheirCells) {
  // Anisotropic spacing, as a thick-slice MR: the surfaces are in mm, not in voxels.
  const Eigen::Vector3d spacing(0.8, 0.8, 3.0);
  TetMesh m = MeshWithRegions(
      {14, 14, 14},
      [](const Eigen::Vector3d& c) {
        return static_cast<uint8_t>((c - Eigen::Vector3d(6.5, 6.5, 6.5)).norm() < 4.0 ? 1 : 0);
      },
      spacing);
  const auto surfaces = ExtractRegionSurfaces(m);
  ASSERT_EQ(surfaces.size(), 2u);
  EXPECT_EQ(surfaces[0].region, 0);
  EXPECT_EQ(surfaces[1].region, 1);
  ExpectClosedManifold(surfaces[1], 2);  // the ball: one sphere
  ExpectClosedManifold(surfaces[0], 4);  // the box around it: the outer and the inner sphere
  for (const RegionSurface& s : surfaces) {
    EXPECT_NEAR(EnclosedVolume(s), RegionVolume(m, s.region), 1e-6 * RegionVolume(m, 0))
        << "region " << int{s.region};
  }
  // The ball is 3 mm per slice along z: it is no "squished" sphere in mm.
  float zmin = 1e9f, zmax = -1e9f, xmin = 1e9f, xmax = -1e9f;
  for (int64_t v = 0; v < surfaces[1].vertex_count(); ++v) {
    xmin = std::min(xmin, surfaces[1].positions[3 * v]);
    xmax = std::max(xmax, surfaces[1].positions[3 * v]);
    zmin = std::min(zmin, surfaces[1].positions[3 * v + 2]);
    zmax = std::max(zmax, surfaces[1].positions[3 * v + 2]);
  }
  EXPECT_NEAR((zmax - zmin) / (xmax - xmin), 3.0 / 0.8, 0.01);
}

TEST(RegionSurface, BlocksTouchingAlongAnEdgeAreSplitThereIntoTwoSpheres) {
  // Region 1: [0,2]^2 x [0,2] and [2,4]^2 x [0,2]; they share the segment x = y = 2.
  TetMesh m = MeshWithRegions({5, 5, 3}, [](const Eigen::Vector3d& c) {
    const bool a = c.x() < 2 && c.y()<2, b = c.x()> 2 && c.y() > 2;
    return static_cast<uint8_t>(a || b ? 1 : 0);
  });
  const auto surfaces = ExtractRegionSurfaces(m);
  ASSERT_EQ(surfaces.size(), 2u);
  ExpectClosedManifold(surfaces[1], 4);
  ExpectClosedManifold(surfaces[0], 4);  // the complement is pinched along the same edge
  // Two blocks of 2 x 2 x 2; the split copies moved a thousandth of their fan into their block.
  EXPECT_NEAR(EnclosedVolume(surfaces[1]), 16.0, 0.01);
}

TEST(RegionSurface, BlocksTouchingAtAVertexAreSplitThere) {
  TetMesh m = MeshWithRegions({5, 5, 5}, [](const Eigen::Vector3d& c) {
    const bool a = c.x() < 2 && c.y() < 2 && c.z() < 2;
    const bool b = c.x() > 2 && c.y() > 2 && c.z() > 2;
    return static_cast<uint8_t>(a || b ? 1 : 0);
  });
  const auto surfaces = ExtractRegionSurfaces(m);
  ASSERT_EQ(surfaces.size(), 2u);
  ExpectClosedManifold(surfaces[1], 4);
  EXPECT_NEAR(EnclosedVolume(surfaces[1]), 16.0, 0.01);
}

TEST(RegionSurface, TheSameOnOneAndTwoThreads) {
  TetMesh m = MeshWithRegions({9, 8, 7}, [](const Eigen::Vector3d& c) {
    return static_cast<uint8_t>((c.x() + 2 * c.y() + c.z()) < 9 ? 2 : (c.z() < 3 ? 0 : 1));
  });
  const auto one = ExtractRegionSurfaces(m, 1), two = ExtractRegionSurfaces(m, 2);
  ASSERT_EQ(one.size(), two.size());
  for (size_t i = 0; i < one.size(); ++i) {
    EXPECT_EQ(one[i].positions, two[i].positions);
    EXPECT_EQ(one[i].triangles, two[i].triangles);
  }
}

TEST(RegionSurface, StlHoldsEveryTriangleWithItsNameAndOutwardNormals) {
  TetMesh m = MeshWithRegions({4, 4, 4}, [](const Eigen::Vector3d&) { return uint8_t{3}; });
  const auto surfaces = ExtractRegionSurfaces(m);
  ASSERT_EQ(surfaces.size(), 1u);
  // A 3 mm cube: 6 sides of 9 squares of 2 triangles.
  EXPECT_EQ(surfaces[0].triangle_count(), 6 * 9 * 2);
  ExpectClosedManifold(surfaces[0], 2);
  const std::filesystem::path dir = testing::MakeScratchDir("region_surface_stl");
  const auto path = dir / "surface-bone.stl";
  ASSERT_TRUE(WriteStl(surfaces[0], "bone", path).ok());
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  ASSERT_EQ(bytes.size(), 84u + 50u * 108u);
  EXPECT_NE(bytes.rfind("solid", 0), 0u);
  EXPECT_NE(bytes.substr(0, 80).find("bone"), std::string::npos);
  uint32_t count = 0;
  std::memcpy(&count, bytes.data() + 80, 4);
  EXPECT_EQ(count, 108u);
  // Every facet normal points away from the cube's centre (1.5, 1.5, 1.5).
  for (uint32_t f = 0; f < count; ++f) {
    float rec[12];
    std::memcpy(rec, bytes.data() + 84 + 50 * f, 48);
    const Eigen::Vector3f n(rec[0], rec[1], rec[2]);
    const Eigen::Vector3f centroid =
        (Eigen::Vector3f(rec[3], rec[4], rec[5]) + Eigen::Vector3f(rec[6], rec[7], rec[8]) +
         Eigen::Vector3f(rec[9], rec[10], rec[11])) /
        3.0f;
    EXPECT_GT(n.dot(centroid - Eigen::Vector3f(1.5f, 1.5f, 1.5f)), 0.0f) << "facet " << f;
  }
  // The STL is the folder's only file: no temporary is left beside it.
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir),
                          std::filesystem::directory_iterator()),
            1);
  // An unwritable place is an error naming it, not a crash.
  const auto bad = WriteStl(surfaces[0], "bone", "/nonexistent-dir/x.stl");
  EXPECT_FALSE(bad.ok());
  EXPECT_NE(bad.message().find("/nonexistent-dir/x.stl"), std::string::npos);
}

TEST(RegionSurface, GlbHoldsEveryRegionNamedAndColouredInGltfsFrame) {
  TetMesh m = MeshWithRegions({6, 6, 6}, [](const Eigen::Vector3d& c) {
    return static_cast<uint8_t>(c.x() < 2.5 ? 0 : 4);
  });
  const auto surfaces = ExtractRegionSurfaces(m);
  ASSERT_EQ(surfaces.size(), 2u);
  std::vector<RegionStyle> styles = {DefaultRegionStyle(0), DefaultRegionStyle(4)};
  styles[1].name = "bone \"cortical\"";  // quotes must be escaped in the JSON
  const auto path = std::filesystem::path(::testing::TempDir()) / "surfaces.glb";
  ASSERT_TRUE(WriteGlb(surfaces, styles, path).ok());
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  ASSERT_GE(bytes.size(), 28u);
  uint32_t header[5];
  std::memcpy(header, bytes.data(), sizeof(header));
  EXPECT_EQ(header[0], 0x46546C67u);  // "glTF"
  EXPECT_EQ(header[1], 2u);
  EXPECT_EQ(header[2], bytes.size());
  EXPECT_EQ(header[4], 0x4E4F534Au);  // "JSON"
  const auto json = nlohmann::json::parse(bytes.substr(20, header[3]));
  ASSERT_EQ(json["meshes"].size(), 2u);
  EXPECT_EQ(json["meshes"][0]["name"], "region_0");
  EXPECT_EQ(json["meshes"][1]["name"], "bone \"cortical\"");
  EXPECT_EQ(json["nodes"].size(), 2u);
  EXPECT_EQ(json["scenes"][0]["nodes"].size(), 2u);
  for (int c = 0; c < 3; ++c) {
    EXPECT_FLOAT_EQ(json["materials"][1]["pbrMetallicRoughness"]["baseColorFactor"][c].get<float>(),
                    styles[1].rgb[c]);
  }
  // Okabe-Ito's first two colours differ.
  EXPECT_NE(json["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"],
            json["materials"][1]["pbrMetallicRoughness"]["baseColorFactor"]);
  const size_t bin_at = 20 + header[3];
  uint32_t bin_chunk[2];
  std::memcpy(bin_chunk, bytes.data() + bin_at, 8);
  EXPECT_EQ(bin_chunk[1], 0x004E4942u);  // "BIN"
  EXPECT_EQ(json["buffers"][0]["byteLength"].get<size_t>() + 3 >= bin_chunk[0], true);
  for (int i = 0; i < 2; ++i) {
    const auto& pos = json["accessors"][2 * i];
    const auto& idx = json["accessors"][2 * i + 1];
    EXPECT_EQ(pos["count"].get<int64_t>(), surfaces[i].vertex_count());
    EXPECT_EQ(idx["count"].get<int64_t>(), 3 * surfaces[i].triangle_count());
    // The first vertex, at LPS (x, y, z) mm, is stored at (x, z, -y) m, within the bounds.
    const auto& view = json["bufferViews"][pos["bufferView"].get<int>()];
    float p[3];
    std::memcpy(p, bytes.data() + bin_at + 8 + view["byteOffset"].get<size_t>(), sizeof(p));
    EXPECT_FLOAT_EQ(p[0], surfaces[i].positions[0] / 1000.0f);
    EXPECT_FLOAT_EQ(p[1], surfaces[i].positions[2] / 1000.0f);
    EXPECT_FLOAT_EQ(p[2], -surfaces[i].positions[1] / 1000.0f);
    for (int c = 0; c < 3; ++c) {
      EXPECT_GE(p[c], pos["min"][c].get<float>());
      EXPECT_LE(p[c], pos["max"][c].get<float>());
    }
  }
  EXPECT_FALSE(WriteGlb(surfaces, {DefaultRegionStyle(0)}, path).ok());  // one style short
}

}  // namespace
}  // namespace decima
