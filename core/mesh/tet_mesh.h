// The tetrahedral mesh every later stage works on, as flat arrays (struct of arrays).
//
// Invariants of a valid TetMesh:
//  - positions.size() == 3 * vertex_count(); scalars, labels, interface_distance and
//    vertex_flags have vertex_count() entries (labels/interface_distance may be all 0 / +inf
//    when no segmentation was given);
//  - tets.size() == 4 * tet_count(), every index in [0, vertex_count()), the four distinct;
//  - every tet is positively oriented: dot(p1 - p0, cross(p2 - p0, p3 - p0)) > 0;
//  - cell_regions has tet_count() entries.
// A mesh made by Tetrahedralize also records its grid (`grid`): its cells are GridTets's, so a
// stage may free tets and cell_regions while it does not need them (DropGridCells) and get them
// back (RestoreGridCells, tetrahedralize.h). With the cells dropped, tet_count() still counts them
// and Cell(t) computes them; code that reads `tets` directly must have them restored.
// The mesh is conforming: two tets share a whole face or nothing of that face.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/common/huge_pages.h"
#include "core/mesh/grid_tets.h"

namespace decima {

// Bits of TetMesh::vertex_flags.
enum VertexFlag : uint8_t {
  kFeatureVertex = 1 << 0,           // on an interior boundary (paper §2.2.1)
  kExteriorBoundaryVertex = 1 << 1,  // on the hull of the mesh
};

// Labels and regions are 0..kMaxRegions-1: the segmentation's phases fit in 3 bits.
constexpr int kMaxRegions = 8;

// The label of a point of a cell whose vertices carry `label` and where the point has barycentric
// coordinates `l`: the label whose indicator, interpolated linearly like the field, is largest
// there (the sum of the coordinates of its vertices). Inside a two-label cell the regions then
// meet on a plane (the indicators' level 1/2), the surface a marching-tetrahedra extraction of the
// labels draws. Returns the slot of the first vertex of that label; ties go to the lower slot.
// The metric (core/metrics ResampleOnGrid) and the label guard of the field engine both use it.
inline double LabelWeight(const uint8_t label[4], const double l[4], uint8_t of) {
  return (label[0] == of ? l[0] : 0.0) + (label[1] == of ? l[1] : 0.0) +
         (label[2] == of ? l[2] : 0.0) + (label[3] == of ? l[3] : 0.0);
}
inline int DominantLabelSlot(const uint8_t label[4], const double l[4]) {
  int best = 0;
  double best_weight = LabelWeight(label, l, label[0]);
  for (int c = 1; c < 4; ++c) {
    const double w = LabelWeight(label, l, label[c]);
    if (w > best_weight) best = c, best_weight = w;
  }
  return best;
}

struct TetMesh {
  std::vector<float> positions;           // x, y, z per vertex, LPS mm
  std::vector<float> scalars;             // field value per vertex (the image intensity)
  std::vector<uint8_t> labels;            // region per vertex, below kMaxRegions
  std::vector<float> interface_distance;  // distance to the nearest region interface, voxels
  std::vector<uint8_t> vertex_flags;      // VertexFlag bits
  std::vector<int32_t> tets;              // 4 vertex indices per cell, positively oriented
  std::vector<uint8_t> cell_regions;      // region per cell (see CellRegion in tetrahedralize.h)
  // Set by Tetrahedralize: cell t is grid->Cell(t), whether or not `tets` holds it. Whoever edits
  // the cells of such a mesh resets it.
  std::optional<GridTets> grid;
  // Set by DropGridCells, cleared by RestoreGridCells: `tets` and `cell_regions` are freed and the
  // cells are the grid's. A flag, not "tets is empty", so that a mesh whose cells were cleared
  // (edited) is never read as the grid's.
  bool cells_dropped = false;

  int64_t vertex_count() const { return static_cast<int64_t>(scalars.size()); }
  int64_t tet_count() const {
    return cells_dropped ? grid->tet_count() : static_cast<int64_t>(tets.size() / 4);
  }
  // The four vertices of cell t, from `tets` or, when they are dropped, from the grid.
  void Cell(int64_t t, int32_t out[4]) const {
    if (cells_dropped) {
      grid->Cell(t, out);
    } else {
      for (int k = 0; k < 4; ++k) out[k] = tets[4 * t + k];
    }
  }
  // f(t, cell) for t0 <= t < t1 in order: Cell(t) for a run of cells, without Cell's division per
  // cell when they are dropped.
  template <typename F>
  void ForEachCell(int64_t t0, int64_t t1, F&& f) const {
    if (cells_dropped) {
      grid->ForEachCell(t0, t1, f);
    } else {
      for (int64_t t = t0; t < t1; ++t) f(t, static_cast<const int32_t*>(&tets[4 * t]));
    }
  }
  Eigen::Vector3d Position(int64_t v) const {
    return {positions[3 * v], positions[3 * v + 1], positions[3 * v + 2]};
  }
};

// Frees the cells of a mesh that records its grid (mesh.grid set): tets and cell_regions, 17 bytes
// per cell. Nothing happens to a mesh without a grid.
void DropGridCells(TetMesh* mesh);

// Vertex -> incident tets in compressed sparse rows: tets of vertex v are
// tet_ids[offsets[v] .. offsets[v + 1]), in increasing tet id. The arrays are allocated without
// a zero fill (FillLaterAllocator): the build writes every entry on its threads, and the serial
// zero fill of std::vector was the slowest part of it on large meshes.
struct VertexTetAdjacency {
  std::vector<int64_t, FillLaterAllocator<int64_t>> offsets;  // vertex_count() + 1 entries
  std::vector<int32_t, FillLaterAllocator<int32_t>> tet_ids;
};

// Builds the CSR adjacency in two counting passes (no per-vertex allocation), each row sorted by
// tet id; on up to `threads` threads (large meshes), with the same result on any count. O(V + T).
// Reads the cells through TetMesh::Cell, so also with the cells dropped.
VertexTetAdjacency BuildVertexTetAdjacency(const TetMesh& mesh, int threads = 1);
// The same over any cell array whose tet t has its 4 vertices at cells[stride * t .. + 4): the
// renderer's 8-int cells, so it can free the mesh's own tets before building it.
VertexTetAdjacency BuildVertexTetAdjacency(const int32_t* cells, int64_t stride, int64_t nv,
                                           int64_t nt, int threads = 1);

// Signed volume of tet t in mm^3 (positive for a valid mesh).
double TetVolume(const TetMesh& mesh, int64_t t);

// The tet other than t that holds the face (a, b, c), looked for among a's tets in `adj`; -1 if
// there is none (a face of the boundary).
int64_t TetAcrossFace(const TetMesh& mesh, const VertexTetAdjacency& adj, int64_t t, int32_t a,
                      int32_t b, int32_t c);

// Faces that belong to exactly one tet, 3 vertex indices each, ordered so their normal points out
// of the mesh. Also the set of vertices on them. Works on any conforming mesh (sorts faces).
struct BoundarySurface {
  std::vector<int32_t> faces;
  std::vector<uint8_t> is_boundary_vertex;  // vertex_count() entries, 0/1
};
BoundarySurface ExtractBoundary(const TetMesh& mesh);

}  // namespace decima
