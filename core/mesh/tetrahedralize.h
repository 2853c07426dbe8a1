// Regular grid -> tetrahedral mesh, 5 tets per cube (paper §2, "simple tetrahedralization").
//
// One mesh vertex per voxel centre (so a 128x128x53 volume gives 868,352 vertices and
// 127*127*52*5 = 4,193,540 tets, the paper's Table 1). Each cube is split into a central tet
// and four corner tets; the split alternates with the parity of (i + j + k) so that the diagonal
// of every shared face matches in both neighbouring cubes and the mesh is conforming.
#pragma once

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/volume/volume.h"

namespace decima {

struct TetrahedralizeOptions {
  // Region label per voxel (uint8, same grid as the image) or nullptr: all labels 0.
  const Volume* labels = nullptr;
  // Distance of every voxel to the nearest interface, in voxels (voxel_count() floats), or
  // nullptr: +infinity everywhere.
  const float* interface_distance = nullptr;
  // Vertices with |interface_distance| <= this are flagged kFeatureVertex (paper §2.2.1;
  // default half a voxel: exactly the voxels touching an interface).
  float feature_threshold_voxels = 0.5f;
  // Worker threads (0 = hardware concurrency). The output does not depend on it.
  int threads = 0;
  // false: the cells (tets, cell_regions: 17 bytes per cell) are not written and the mesh comes
  // with cells_dropped set, as after DropGridCells; RestoreGridCells writes them. For a caller
  // whose readers take cells through TetMesh::Cell (a job's plain field run, issue 30).
  bool cells = true;
};

// Builds the mesh with positions in LPS mm (volume geometry applied), scalars = voxel values as
// float, labels / interface distance / flags per vertex, cell regions, and exterior-boundary
// flags for the vertices on the box faces. Tets are positively oriented also when the direction
// matrix has determinant -1. Errors: InvalidArgument if any dimension is < 2, the labels are
// not on the image grid, or the tet count would exceed int32 indexing.
absl::StatusOr<TetMesh> Tetrahedralize(const Volume& image,
                                       const TetrahedralizeOptions& options = {},
                                       const ProgressFn& progress = nullptr,
                                       const CancelToken* cancel = nullptr);

// The vertex positions Tetrahedralize stores (voxel centres in LPS mm, 3 floats per voxel into
// `out`), for code that needs the grid's vertices without the mesh (the renderer's original,
// issue 30): one function, so both get the same floats (a different evaluation order once gave
// 1-ulp depth differences). On `threads` threads (0: all); the result does not depend on it.
void GridVertexPositions(const Volume& image, float* out, int threads = 0);

// Writes back the cells DropGridCells freed (tets and cell_regions, from mesh->grid and the
// labels), the same as Tetrahedralize wrote; on `threads` threads (0: all). Nothing happens
// unless the cells are dropped.
void RestoreGridCells(TetMesh* mesh, int threads = 0);

// Region of a cell from its vertex labels: the most frequent label, ties to the smaller one.
// Inline: the simplifier's error terms ask for it for every scored cell.
inline uint8_t CellRegion(uint8_t a, uint8_t b, uint8_t c, uint8_t d) {
  if (a == b && b == c && c == d) return a;
  const uint8_t v[4] = {a, b, c, d};
  uint8_t best = 255;
  int best_count = 0;
  for (int i = 0; i < 4; ++i) {
    int count = 0;
    for (int j = 0; j < 4; ++j) count += v[j] == v[i];
    if (count > best_count || (count == best_count && v[i] < best)) {
      best = v[i];
      best_count = count;
    }
  }
  return best;
}

}  // namespace decima
