// How much a simplified mesh still says what the original volume said: the field resampled on
// the original grid (RMSE, PSNR, max error, coverage), region labels (Dice), the feature
// vertices (moved or removed), cell quality (inverted, degenerate, min dihedral angle),
// conformity (faces shared by one, two, or three or more cells) and size.
//
// Resampling: every original grid point is located in the simplified mesh and the field is
// interpolated barycentrically in its containing cell (the mesh's piecewise-linear field). A
// point lying in several cells (on a shared face, edge or vertex) takes the one with the lowest
// cell id, so the result does not depend on the thread count. Its label is the cell's dominant
// label there (DominantLabelSlot, tet_mesh.h): the label whose indicator, interpolated
// barycentrically like the field, is largest (ties to the lower slot).
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/volume/volume.h"

namespace decima {

// The simplified mesh resampled at every grid point (x fastest, the Volume's order).
struct GridResample {
  std::vector<float> values;    // interpolated field, 0 where not covered
  std::vector<uint8_t> labels;  // resampled label, 0 where not covered
  std::vector<int32_t> cell;    // containing cell, -1 where not covered
};

// Locates every grid point of `grid` (only its geometry is used) in `mesh`: each cell visits
// the grid points inside its bounding box (the grid itself is the bucket structure, so no
// search tree is built) and keeps those whose barycentric coordinates are all >= -tolerance.
// O(cells * points per cell box). Errors: InvalidArgument for an inconsistent mesh or a grid
// that is not a valid volume geometry; Cancelled if `cancel` fired.
absl::StatusOr<GridResample> ResampleOnGrid(const Volume& grid, const TetMesh& mesh,
                                            int threads = 0, double tolerance = 1e-5,
                                            const CancelToken* cancel = nullptr);

// The field's error on the original grid: the figures MeasureFidelity reports as coverage, rmse,
// max_abs_error, value_range and psnr_db, computed by the same code (MeasureFidelity calls this),
// so a search that stops on a PSNR floor stops on the number metrics.json shows.
struct FieldError {
  int64_t grid_points = 0, covered_points = 0;
  double coverage = 0;  // covered / grid points
  double rmse = 0;      // image units, over the covered points
  double max_abs_error = 0;
  double value_range = 0;  // max - min of the image
  double psnr_db = 0;      // 20 log10(range / rmse); +infinity when rmse == 0
};

// Resamples `mesh` on `image`'s grid (ResampleOnGrid) and compares the field with the image's
// values. `resample` (when given) receives the resampling, for callers that measure more on it.
// Errors as ResampleOnGrid's.
absl::StatusOr<FieldError> MeasureFieldError(const Volume& image, const TetMesh& mesh,
                                             int threads = 0, double inside_tolerance = 1e-5,
                                             const CancelToken* cancel = nullptr,
                                             GridResample* resample = nullptr);

// The feature-vertex counts of FidelityMetrics (feature_vertices, _moved, _removed): from the
// original mesh's positions and vertex_flags, Simplify's vertex_map and the simplified mesh's
// positions, nothing else. A caller that releases the original before measuring (a job, issue 30:
// its vertex arrays are 22 bytes per voxel) counts them first and passes them in
// FidelityOptions::feature_counts.
struct FeatureVertexCounts {
  int64_t vertices = 0;  // kFeatureVertex in the original
  int64_t moved = 0;     // survive at another position
  int64_t removed = 0;   // gone, or merged with another feature vertex
};
// Errors: InvalidArgument when vertex_map or vertex_flags do not have one entry per original
// vertex (naming them).
absl::StatusOr<FeatureVertexCounts> CountFeatureVertices(const TetMesh& original,
                                                         const std::vector<int32_t>& vertex_map,
                                                         const TetMesh& simplified);

struct FidelityOptions {
  // Ground-truth labels (uint8 on the image grid), e.g. the segmentation; enables Dice, the
  // label mismatch and the interface RMSE. nullptr: those stay empty / 0.
  const Volume* labels = nullptr;
  // The mesh before simplification and Simplify's vertex_map (input vertex -> output vertex or
  // -1); together they enable the feature-vertex counts.
  const TetMesh* original = nullptr;
  const std::vector<int32_t>* vertex_map = nullptr;
  // Or the counts themselves, made before (CountFeatureVertices) with the same result; with
  // them, original and vertex_map stay nullptr.
  const FeatureVertexCounts* feature_counts = nullptr;
  // Bytes of the written mesh file (the writer lives in core/mesh); 0 = unknown.
  int64_t mesh_bytes = 0;
  // A cell with 0 <= volume < this * voxel volume counts as degenerate.
  double degenerate_volume_fraction = 1e-4;
  double inside_tolerance = 1e-5;  // barycentric tolerance of the point location
  int threads = 0;                 // 0 = hardware concurrency; results do not depend on it
};

struct RegionDice {
  int label = 0;
  int64_t truth_points = 0;  // grid points with this ground-truth label
  int64_t mesh_points = 0;   // grid points whose resampled label is this
  int64_t both = 0;
  double dice = 0;  // 2 both / (truth + mesh); 1 when both are 0
};

struct FidelityMetrics {
  int64_t vertices = 0, cells = 0;
  // Field on the original grid, over the covered points.
  int64_t grid_points = 0, covered_points = 0;
  double coverage = 0;  // covered / grid points
  double rmse = 0;      // image units
  double max_abs_error = 0;
  double value_range = 0;  // max - min of the image
  double psnr_db = 0;      // 20 log10(range / rmse); +infinity when rmse == 0
  // Labels (with FidelityOptions::labels); an uncovered point has no label.
  std::vector<RegionDice> dice;  // every label present in truth or mesh, ascending
  double mean_dice = 0;          // over the truth labels
  double label_mismatch = 0;     // fraction of grid points whose label differs from truth
  double interface_rmse = 0;     // field RMSE at covered points next to a truth interface
  int64_t interface_points = 0;  //   (a 6-neighbour with another truth label)
  // How far the mesh's interfaces lie from the segmentation's zero level, in voxels: over the
  // vertices of cells that hold two labels (the resampled label boundary lies inside those
  // cells), the largest and the mean |interface_distance| the mesh carries (the level set's
  // distance at the vertex). One side of the Hausdorff distance to the zero surface, sampled at
  // vertices (README "Interface distance"); 0 when the mesh has no two-label cell or no distances.
  double interface_distance_max_voxels = 0;
  double interface_distance_mean_voxels = 0;
  int64_t interface_vertices = 0;
  // Feature vertices (with original + vertex_map, or feature_counts).
  int64_t feature_vertices = 0;          // kFeatureVertex in the original
  int64_t feature_vertices_moved = 0;    // survive at another position
  int64_t feature_vertices_removed = 0;  // gone, or merged with another feature vertex
  // Cell quality.
  int64_t inverted_cells = 0;    // volume < 0
  int64_t degenerate_cells = 0;  // 0 <= volume < degenerate_volume_fraction voxels^3
  double min_dihedral_deg = 0;   // over all cells
  // Conformity (CountFaces): a valid mesh has no face in three or more cells, and its two cells
  // of an interior face lie on opposite sides of it.
  int64_t boundary_faces = 0;     // faces of exactly one cell
  int64_t interior_faces = 0;     // faces of exactly two cells
  int64_t nonmanifold_faces = 0;  // faces of three or more cells
  int64_t folded_faces = 0;       // interior faces whose two cells lie on the same side
  double boundary_area_mm2 = 0;   // area of the boundary faces (grows with holes and T-joints)
  bool manifold = false;          // nonmanifold_faces == 0 && folded_faces == 0
  // Size.
  int64_t mesh_bytes = 0, voxel_bytes = 0;
  double bytes_ratio = 0;  // mesh_bytes / voxel_bytes (0 when mesh_bytes is unknown)
};

// Measures `simplified` against the original `image` (and options). Errors: InvalidArgument
// (naming the field) for inconsistent meshes, labels not on the image grid, or a vertex map of
// the wrong size; Cancelled. Thread-safe for distinct arguments.
absl::StatusOr<FidelityMetrics> MeasureFidelity(const Volume& image, const TetMesh& simplified,
                                                const FidelityOptions& options = {},
                                                const CancelToken* cancel = nullptr);

// Cell quality only (no grid): inverted / degenerate counts and the smallest dihedral angle.
struct MeshQuality {
  int64_t inverted_cells = 0, degenerate_cells = 0;
  double min_dihedral_deg = 0;
};
MeshQuality MeasureQuality(const TetMesh& mesh, double degenerate_volume_mm3);

// How the cells share their faces (a face is a set of 3 vertex indices; geometry is not
// compared, so two cells meeting along a face with different vertices count as two boundary
// faces, and the boundary area then exceeds the hull's).
struct FaceCounts {
  int64_t boundary_faces = 0;     // in exactly one cell
  int64_t interior_faces = 0;     // in exactly two cells
  int64_t nonmanifold_faces = 0;  // in three or more cells
  // Interior faces whose two cells see them with the same orientation, i.e. both cells lie on
  // the same side of the face (a fold; in a positively oriented conforming mesh this is 0).
  int64_t folded_faces = 0;
  double boundary_area_mm2 = 0;
};
// Groups the faces around their smallest vertex (vertex -> tet CSR adjacency, then a sort of
// each vertex's few faces), so it needs 4 bytes per cell corner plus 8 per vertex and no global
// sort. O(T log(faces per vertex)). The counts do not depend on `threads` (0 = hardware
// concurrency); the area is summed per thread range, so its last bits may. Vertex indices must
// be in range (MeasureFidelity checks this; callers of CountFaces must too).
FaceCounts CountFaces(const TetMesh& mesh, int threads = 0);

}  // namespace decima
