// CPU volume renderer for tetrahedral meshes (paper §3: the original and the simplified mesh
// are rendered the same way and compared pixel by pixel, Eq. 9 and 10).
//
// Model: emission-absorption ray casting. Each ray walks the mesh cell by cell through shared
// faces; inside a tet the mesh's field is linear, so along the ray the scalar is linear between
// the values at the entry and exit points, which are interpolated barycentrically from the
// face's vertices (no resampling onto a grid). The segment is integrated with the transfer
// function's colour c(s) and extinction sigma(s) (1/mm) at sub-samples at most `step_mm` apart:
//     C += T * (1 - exp(-sigma * dl)) * c,   T *= exp(-sigma * dl)
// front to back, and the pixel is C + T * background.
//
// Robustness: all inside/outside decisions are 2D orientation tests of the ray's pixel point
// against projected mesh edges, evaluated for each edge in one canonical vertex order, with
// exact zeros resolved by a symbolic perturbation of the pixel point. Neighbouring tets
// therefore always agree on where a ray crosses, so rays through vertices and edges (common
// in axis-aligned views of grid meshes) neither leak nor loop.
//
// Empty space: tets on whose scalar range the transfer function has zero opacity (air in CT)
// contribute nothing, so rays only walk the "visible" tets. They enter through front-facing
// faces of visible tets that lie on the hull or next to an invisible tet (rasterized per
// image, sorted by depth per pixel), and leave when the next tet is invisible or absent; a
// later entry of the same pixel continues the ray. So non-convex meshes and gaps are handled,
// and the image equals that of walking every tet.
//
// Cell sources: one ray-casting loop reads its cells through a small source type, either a
// RenderableMesh (cells and neighbours stored, 32 bytes per tet) or a RenderableGrid, the
// original 5-tet grid mesh whose cells and neighbours are GridTets's functions of the cell id
// (nothing stored per tet; issue 30). The grid renders exactly as the materialized mesh of the
// same volume (same pixels, tested).
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/io/png.h"
#include "core/mesh/tet_mesh.h"
#include "core/render/camera.h"
#include "core/render/transfer_function.h"
#include "core/volume/volume.h"

namespace decima {

// What rendering needs of a mesh, built once and reused for every view and transfer
// function: vertex positions and scalars, and per tet its 4 vertices plus the 4 neighbours
// across its faces (face q is opposite vertex q; -1 on the boundary), interleaved for locality.
struct RenderableMesh {
  std::vector<float> positions;  // 3 per vertex, LPS mm
  std::vector<float> scalars;    // 1 per vertex
  std::vector<int32_t> cells;    // 8 per tet: v0..v3, n0..n3
  // Boundary faces as (tet, local face q) packed as 4 * tet + q, with their vertices wound so
  // the normal points out of the mesh (3 per face).
  std::vector<int32_t> boundary_faces;
  std::vector<int32_t> boundary_vertices;
  Bounds bounds;
  ScalarRange scalar_range;

  int64_t vertex_count() const { return static_cast<int64_t>(scalars.size()); }
  int64_t tet_count() const { return static_cast<int64_t>(cells.size() / 8); }
};

struct RenderableMeshOptions {
  int threads = 0;  // 0 = hardware concurrency; the result does not depend on it
};

// Validates `mesh` as outside data (sizes consistent, indices in range and distinct per tet,
// finite positions and scalars, no face shared by more than two tets) and builds face
// adjacency by matching faces around their smallest vertex: O(V + T), no global sort.
// Errors: InvalidArgument naming the first problem; Cancelled.
absl::StatusOr<RenderableMesh> BuildRenderableMesh(const TetMesh& mesh,
                                                   const RenderableMeshOptions& options = {},
                                                   const CancelToken* cancel = nullptr);
// The same, consuming `mesh` once its sizes, indices and values are checked (left empty from then
// on, also when a non-manifold face is found later; unchanged when a first check fails): its
// positions and scalars move into the result and its other arrays are freed before the adjacency is
// built, so the mesh, the result and the adjacency are never all resident (on the 5-tet grid mesh
// of a job, about 100 bytes per voxel less at the peak). Same result.
absl::StatusOr<RenderableMesh> BuildRenderableMesh(TetMesh&& mesh,
                                                   const RenderableMeshOptions& options = {},
                                                   const CancelToken* cancel = nullptr);

// The 5-tet mesh of a voxel grid (Tetrahedralize's) as the renderer needs it, without its cells:
// per voxel the position (the floats Tetrahedralize stores, GridVertexPositions) and the scalar,
// 16 bytes, against about 170 per voxel for the RenderableMesh of the same mesh. Cell t and its
// neighbours are grid.Cell(t) and grid.Neighbour(t, q).
struct RenderableGrid {
  GridTets grid;
  std::vector<float> positions;  // 3 per vertex, LPS mm
  std::vector<float> scalars;    // 1 per vertex (the voxel values as float)
  Bounds bounds;
  ScalarRange scalar_range;

  int64_t vertex_count() const { return static_cast<int64_t>(scalars.size()); }
  int64_t tet_count() const { return grid.tet_count(); }
};

// The renderable form of Tetrahedralize(image) without building that mesh. Errors:
// InvalidArgument (a dimension below 2, more cells than 32-bit codes address, a non-finite
// voxel value, naming the voxel); Cancelled.
absl::StatusOr<RenderableGrid> BuildRenderableGrid(const Volume& image,
                                                   const RenderableMeshOptions& options = {},
                                                   const CancelToken* cancel = nullptr);

struct RenderOptions {
  // Largest distance between sub-samples of the transfer function inside one tet segment, mm.
  // Each segment gets at least one (midpoint) sample.
  double step_mm = 0.5;
  // Colour behind the volume, RGB 0..1.
  std::array<float, 3> background{0, 0, 0};
  // Early ray termination: a ray stops once its transmittance is below this (the rest could
  // change its colour by less than half an 8-bit level).
  float min_transmittance = 1.0f / 512;
  // Worker threads over image tiles (0 = hardware concurrency). The image does not depend on it.
  int threads = 0;
};

struct RenderStats {
  int64_t rays_hit = 0;        // rays that entered a visible tet
  int64_t visible_tets = 0;    // tets the transfer function is not zero on (see Render)
  int64_t entry_faces = 0;     // (pixel, entry face) pairs rasterized
  int64_t steps = 0;           // tet segments walked
  int64_t fallback_steps = 0;  // steps where rounding left no consistent exit face
  int64_t lost_rays = 0;       // rays abandoned (no progress in 4096 steps), should be 0
  double raster_seconds = 0;   // projection + boundary rasterization
  double seconds = 0;          // whole Render call
};

struct RenderedImage {
  int width = 0;
  int height = 0;
  std::vector<float> rgb;    // 3 per pixel, rows top to bottom, composited over the background
  std::vector<float> alpha;  // 1 - transmittance per pixel
  // True when no ray met a visible part of the mesh (camera looking away, mesh outside the
  // view, or a transfer function that is transparent on all of the mesh's values): the image is
  // exactly the background everywhere.
  bool empty = true;
  RenderStats stats;

  // 8-bit RGB (rounded), the colours Eq. 9 and 10 compare and WritePng stores.
  Image ToImage() const;
};

// Renders `mesh` with `camera` and `tf`. Every vertex must lie in front of the camera
// (depth > 0); when no vertex does, the result is an empty image (flag `empty`), not an error.
// Thread-safe for concurrent calls on the same mesh. Errors: InvalidArgument for a bad camera
// (size outside 1..8192, non-orthonormal basis, bad fov or width), a mesh crossing the camera
// plane, an invalid transfer function or options; Cancelled.
absl::StatusOr<RenderedImage> Render(const RenderableMesh& mesh, const Camera& camera,
                                     const TransferFunction& tf, const RenderOptions& options = {},
                                     const CancelToken* cancel = nullptr);

// The same for the grid: the same image, pixel for pixel, as rendering the RenderableMesh of
// Tetrahedralize(image).
absl::StatusOr<RenderedImage> Render(const RenderableGrid& grid, const Camera& camera,
                                     const TransferFunction& tf, const RenderOptions& options = {},
                                     const CancelToken* cancel = nullptr);

// Convenience: BuildRenderableMesh then Render (for one view; build once for several).
absl::StatusOr<RenderedImage> Render(const TetMesh& mesh, const Camera& camera,
                                     const TransferFunction& tf, const RenderOptions& options = {},
                                     const CancelToken* cancel = nullptr);

// Bounds and scalar range of a TetMesh's vertices (for cameras and transfer functions).
Bounds MeshBounds(const TetMesh& mesh);
ScalarRange MeshScalarRange(const TetMesh& mesh);

// Writes the 8-bit image as PNG (see WritePng).
absl::Status WriteRenderedPng(const RenderedImage& image, const std::filesystem::path& path);

}  // namespace decima
