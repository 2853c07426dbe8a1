#include "core/mesh/tet_mesh.h"

#include <algorithm>

namespace decima {

VertexTetAdjacency BuildVertexTetAdjacency(const TetMesh& mesh) {
  const int64_t nv = mesh.vertex_count(), nt = mesh.tet_count();
  VertexTetAdjacency adj;
  adj.offsets.assign(nv + 1, 0);
  for (int64_t i = 0; i < 4 * nt; ++i) ++adj.offsets[mesh.tets[i] + 1];
  for (int64_t v = 0; v < nv; ++v) adj.offsets[v + 1] += adj.offsets[v];
  adj.tet_ids.resize(4 * nt);
  std::vector<int64_t> cursor(adj.offsets.begin(), adj.offsets.end() - 1);
  // Tets visited in increasing id, so each row comes out sorted.
  for (int64_t t = 0; t < nt; ++t) {
    for (int q = 0; q < 4; ++q)
      adj.tet_ids[cursor[mesh.tets[4 * t + q]]++] = static_cast<int32_t>(t);
  }
  return adj;
}

double TetVolume(const TetMesh& mesh, int64_t t) {
  const int32_t* v = &mesh.tets[4 * t];
  const Eigen::Vector3d p0 = mesh.Position(v[0]);
  return (mesh.Position(v[1]) - p0)
             .dot((mesh.Position(v[2]) - p0).cross(mesh.Position(v[3]) - p0)) /
         6.0;
}

namespace {

// Faces of a positively oriented tet (a, b, c, d), each wound so its normal points outwards.
constexpr int kFaces[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};

bool Contains(const int32_t* tet, int32_t v) {
  return tet[0] == v || tet[1] == v || tet[2] == v || tet[3] == v;
}

}  // namespace

BoundarySurface ExtractBoundary(const TetMesh& mesh) {
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(mesh);
  BoundarySurface out;
  out.is_boundary_vertex.assign(mesh.vertex_count(), 0);
  const int64_t nt = mesh.tet_count();
  for (int64_t t = 0; t < nt; ++t) {
    const int32_t* tet = &mesh.tets[4 * t];
    for (const auto& f : kFaces) {
      const int32_t a = tet[f[0]], b = tet[f[1]], c = tet[f[2]];
      // A face is interior iff another tet around its first vertex holds the other two.
      bool shared = false;
      for (int64_t e = adj.offsets[a]; e < adj.offsets[a + 1] && !shared; ++e) {
        const int32_t other = adj.tet_ids[e];
        shared =
            other != t && Contains(&mesh.tets[4 * other], b) && Contains(&mesh.tets[4 * other], c);
      }
      if (!shared) {
        out.faces.insert(out.faces.end(), {a, b, c});
        out.is_boundary_vertex[a] = out.is_boundary_vertex[b] = out.is_boundary_vertex[c] = 1;
      }
    }
  }
  return out;
}

}  // namespace decima
