// Helpers for the simplify tests: phantom meshes with labels and a stand-in interface distance,
// and the conformity / hull checks.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/tetrahedralize.h"
#include "core/simplify/simplify.h"
#include "core/volume/phantom.h"
#include "tests/testing/mesh_checks.h"

namespace decima::testing {

// Stand-in for the segmentation's distance to the interface, in voxels: 0.5 for a voxel with a
// 6-neighbour of another label (it touches the interface), 1.5 otherwise.
inline std::vector<float> SimpleInterfaceDistance(const Volume& labels) {
  const int64_t nx = labels.dims[0], ny = labels.dims[1], nz = labels.dims[2];
  const uint8_t* l = labels.data<uint8_t>();
  std::vector<float> d(labels.voxel_count(), 1.5f);
  for (int64_t k = 0; k < nz; ++k) {
    for (int64_t j = 0; j < ny; ++j) {
      for (int64_t i = 0; i < nx; ++i) {
        const int64_t p = i + nx * (j + ny * k);
        const bool edge = (i > 0 && l[p - 1] != l[p]) || (i + 1 < nx && l[p + 1] != l[p]) ||
                          (j > 0 && l[p - nx] != l[p]) || (j + 1 < ny && l[p + nx] != l[p]) ||
                          (k > 0 && l[p - nx * ny] != l[p]) ||
                          (k + 1 < nz && l[p + nx * ny] != l[p]);
        if (edge) d[p] = 0.5f;
      }
    }
  }
  return d;
}

// A scan and its labels on an n^3 grid, and their tet mesh.
struct Labeled {
  Volume image, labels;
  TetMesh mesh;
};

// A float image and uint8 labels on an n^3 grid from per-voxel functions, meshed with the
// stand-in interface distance (SimpleInterfaceDistance: feature vertices = voxels with a
// 6-neighbour of another label) or, when `distance` is given, with its per-voxel interface distance
// in voxels.
// The grid mesh of `image` with `labels` and the per-voxel interface distance `dist` (voxels).
inline TetMesh MeshWithLabels(const Volume& image, const Volume& labels,
                              const std::vector<float>& dist) {
  TetrahedralizeOptions t;
  t.labels = &labels;
  t.interface_distance = dist.data();
  auto mesh = Tetrahedralize(image, t);
  EXPECT_TRUE(mesh.ok()) << mesh.status();
  return mesh.ok() ? *std::move(mesh) : TetMesh();
}

// The field policy to `reduction` on `threads` threads, every other option its default.
inline SimplifyOptions FieldOptions(double reduction, int threads = 2) {
  SimplifyOptions o;
  o.policy = SimplifyPolicy::kField;
  o.target_reduction = reduction;
  o.threads = threads;
  return o;
}

template <typename ValueFn, typename LabelFn>
Labeled MakeLabeled(int64_t n, ValueFn value, LabelFn label,
                    std::function<double(int64_t, int64_t, int64_t)> distance = nullptr) {
  Labeled out;
  auto image = MakeVolume({n, n, n}, VoxelType::kFloat32);
  auto labels = MakeVolume({n, n, n}, VoxelType::kUInt8);
  EXPECT_TRUE(image.ok() && labels.ok());
  out.image = *std::move(image);
  out.labels = *std::move(labels);
  for (int64_t k = 0, p = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i, ++p) {
        out.image.mutable_data<float>()[p] = float(value(i, j, k));
        out.labels.mutable_data<uint8_t>()[p] = uint8_t(label(i, j, k));
      }
  std::vector<float> dist = SimpleInterfaceDistance(out.labels);
  if (distance) {
    for (int64_t k = 0, p = 0; k < n; ++k)
      for (int64_t j = 0; j < n; ++j)
        for (int64_t i = 0; i < n; ++i, ++p) dist[p] = float(distance(i, j, k));
  }
  out.mesh = MeshWithLabels(out.image, out.labels, dist);
  return out;
}

struct PhantomMesh {
  Phantom phantom;
  TetMesh mesh;
};

// The 3-region head phantom (air, shell, core) with Gaussian noise, meshed with its labels.
inline PhantomMesh MakePhantomMesh(int64_t n, double noise_sigma, uint64_t seed = 7) {
  HeadPhantomOptions o;
  o.dims = {n, n, n};
  o.region_means = {0, 1000, 400};
  o.noise_sigma = noise_sigma;
  o.seed = seed;
  auto p = MakeHeadPhantom(o);
  EXPECT_TRUE(p.ok()) << p.status();
  PhantomMesh out{*std::move(p), {}};
  const std::vector<float> dist = SimpleInterfaceDistance(out.phantom.labels);
  TetrahedralizeOptions t;
  t.labels = &out.phantom.labels;
  t.interface_distance = dist.data();
  auto m = Tetrahedralize(out.phantom.image, t);
  EXPECT_TRUE(m.ok()) << m.status();
  out.mesh = *std::move(m);
  return out;
}

using ::decima::testing::FaceUse;

inline double TotalVolume(const TetMesh& m) {
  double total = 0;
  for (int64_t t = 0; t < m.tet_count(); ++t) total += TetVolume(m, t);
  return total;
}

// Two simplifications that must be one: cells, labels, positions, values, flags, the vertex map
// and whether the target was reached.
inline void ExpectSameMesh(const SimplifyResult& a, const SimplifyResult& b,
                           const std::string& what) {
  EXPECT_EQ(a.output_cells, b.output_cells) << what;
  EXPECT_EQ(a.mesh.tets, b.mesh.tets) << what;
  EXPECT_EQ(a.mesh.cell_regions, b.mesh.cell_regions) << what;
  EXPECT_EQ(a.mesh.labels, b.mesh.labels) << what;
  EXPECT_EQ(a.mesh.positions, b.mesh.positions) << what;
  EXPECT_EQ(a.mesh.scalars, b.mesh.scalars) << what;
  EXPECT_EQ(a.mesh.vertex_flags, b.mesh.vertex_flags) << what;
  EXPECT_EQ(a.vertex_map, b.vertex_map) << what;
  EXPECT_EQ(a.reached_target, b.reached_target) << what;
}

}  // namespace decima::testing
