#include "core/mesh/tet_mesh.h"

#include <algorithm>
#include <limits>
#include <utility>
#include <vector>

#include "core/common/huge_pages.h"
#include "core/common/parallel.h"

namespace decima {

namespace {

// The counting sort of BuildVertexTetAdjacency with per-chunk counters of type Slot: int32 where
// every slot index fits (4 * tets < 2^31, the meshes Simplify takes), halving the counters' memory
// (134 MB on phantom:256, freshly faulted on every call).
// `cells(t0, t1, f)` calls f(t, cell) for the tets t0 <= t < t1 in order (TetMesh::ForEachCell).
template <typename Slot, typename CellsFn>
void FillAdjacency(const CellsFn& cells, int64_t nv, int64_t nt, int threads,
                   VertexTetAdjacency* adj) {
  // A counting sort in contiguous chunks of tets, one per thread: each chunk counts its own
  // entries per vertex, then fills its rows' slots after those of the chunks before it. Every
  // chunk visits its tets in increasing id, so each row comes out sorted whatever the number of
  // chunks.
  const int chunks = int(std::clamp<int64_t>(std::min<int64_t>(threads, nt / 65536), 1, 64));
  // Per chunk: counts, then next slot; each chunk zeroes its own part on its thread.
  std::vector<Slot, FillLaterAllocator<Slot>> cursor(int64_t(chunks) * nv);
  auto chunk_range = [&](int64_t c) { return std::pair{nt * c / chunks, nt * (c + 1) / chunks}; };
  ParallelFor(chunks, chunks, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      Slot* count = &cursor[c * nv];
      std::fill(count, count + nv, 0);
      const auto [t0, t1] = chunk_range(c);
      cells(t0, t1, [&](int64_t, const int32_t* c4) {
        for (int q = 0; q < 4; ++q) ++count[c4[q]];
      });
    }
  });
  for (int64_t v = 0; v < nv; ++v) {
    int64_t row = 0;
    for (int64_t c = 0; c < chunks; ++c) row += cursor[c * nv + v];
    adj->offsets[v + 1] = adj->offsets[v] + row;
  }
  ParallelFor(nv, chunks, 65536, [&](int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      int64_t slot = adj->offsets[v];
      for (int64_t c = 0; c < chunks; ++c) {
        const int64_t count = cursor[c * nv + v];
        cursor[c * nv + v] = Slot(slot);
        slot += count;
      }
    }
  });
  ParallelFor(chunks, chunks, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      Slot* next = &cursor[c * nv];
      const auto [t0, t1] = chunk_range(c);
      cells(t0, t1, [&](int64_t t, const int32_t* c4) {
        for (int q = 0; q < 4; ++q) adj->tet_ids[next[c4[q]]++] = int32_t(t);
      });
    }
  });
}

template <typename CellsFn>
VertexTetAdjacency BuildAdjacency(const CellsFn& cells, int64_t nv, int64_t nt, int threads) {
  VertexTetAdjacency adj;
  adj.offsets.resize(nv + 1);  // written below, by the row sums
  adj.offsets[0] = 0;
  adj.tet_ids.resize(4 * nt);  // every slot is written by the fill
  if (4 * nt < std::numeric_limits<int32_t>::max()) {
    FillAdjacency<int32_t>(cells, nv, nt, threads, &adj);
  } else {
    FillAdjacency<int64_t>(cells, nv, nt, threads, &adj);
  }
  return adj;
}

}  // namespace

void DropGridCells(TetMesh* mesh) {
  if (!mesh->grid || mesh->cells_dropped) return;
  std::vector<int32_t>().swap(mesh->tets);
  std::vector<uint8_t>().swap(mesh->cell_regions);
  mesh->cells_dropped = true;
}

VertexTetAdjacency BuildVertexTetAdjacency(const TetMesh& mesh, int threads) {
  if (mesh.cells_dropped) {
    return BuildAdjacency(
        [&](int64_t t0, int64_t t1, const auto& f) { mesh.grid->ForEachCell(t0, t1, f); },
        mesh.vertex_count(), mesh.tet_count(), threads);
  }
  return BuildVertexTetAdjacency(mesh.tets.data(), 4, mesh.vertex_count(), mesh.tet_count(),
                                 threads);
}

VertexTetAdjacency BuildVertexTetAdjacency(const int32_t* cells, int64_t stride, int64_t nv,
                                           int64_t nt, int threads) {
  return BuildAdjacency(
      [&](int64_t t0, int64_t t1, const auto& f) {
        for (int64_t t = t0; t < t1; ++t) f(t, cells + stride * t);
      },
      nv, nt, threads);
}

double TetVolume(const TetMesh& mesh, int64_t t) {
  int32_t v[4];
  mesh.Cell(t, v);
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

int64_t TetAcrossFace(const TetMesh& mesh, const VertexTetAdjacency& adj, int64_t t, int32_t a,
                      int32_t b, int32_t c) {
  for (int64_t e = adj.offsets[a]; e < adj.offsets[a + 1]; ++e) {
    const int32_t other = adj.tet_ids[e];
    if (other != t && Contains(&mesh.tets[4 * int64_t(other)], b) &&
        Contains(&mesh.tets[4 * int64_t(other)], c)) {
      return other;
    }
  }
  return -1;
}

BoundarySurface ExtractBoundary(const TetMesh& mesh) {
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(mesh);
  BoundarySurface out;
  out.is_boundary_vertex.assign(mesh.vertex_count(), 0);
  const int64_t nt = mesh.tet_count();
  for (int64_t t = 0; t < nt; ++t) {
    const int32_t* tet = &mesh.tets[4 * t];
    for (const auto& f : kFaces) {
      const int32_t a = tet[f[0]], b = tet[f[1]], c = tet[f[2]];
      if (TetAcrossFace(mesh, adj, t, a, b, c) < 0) {
        out.faces.insert(out.faces.end(), {a, b, c});
        out.is_boundary_vertex[a] = out.is_boundary_vertex[b] = out.is_boundary_vertex[c] = 1;
      }
    }
  }
  return out;
}

}  // namespace decima
