// The engine behind SimplifyPolicy::kField: greedy half-edge collapses ranked by the error of
// the piecewise-linear field (4-D quadrics, Garland & Zhou 2005 "Quadric-based simplification
// in any dimension", specialised to a scalar field over a fixed-position tetrahedral mesh).
// Internal to core/simplify; simplify.h states the guarantees, README.md the design.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima::simplify_internal {

// Runs the field policy on `mesh` (already validated) until `target` cells are removed, the
// error tolerance stops it (`tolerance` > 0: an RMS field error in image units) or no valid
// collapse is left. Fills every field of `result` (not result->levels). Cancelled if `cancel`
// fires. `levels` not null: every collapse is appended to it in an order whose every prefix is a
// valid mesh (the serial loop's order; a parallel round's slabs merged by cost), and its counts
// and `exhausted` are set; the run then depends on `target` only through the rounds' pacing.
absl::Status RunFieldSimplify(const TetMesh& mesh, const SimplifyOptions& options, int threads,
                              int64_t target, double tolerance, const ProgressFn& progress,
                              const CancelToken* cancel, SimplifyResult* result,
                              SimplifyLevels* levels = nullptr);

// A window of a streamed simplification (stream.h): a part of the mesh whose open boundary is
// frozen. Every pointer is per input vertex of the window's mesh and may be null.
struct FieldWindow {
  // 1: the vertex is never removed (it may be a survivor): the window's open top plane and the
  // vertices shared with cells already written out. A collapse changes only the cells around the
  // removed vertex, so the window's result is a valid part of the whole mesh.
  const uint8_t* frozen = nullptr;
  // InterfaceMode::kFree: for a vertex of no cell (a voxel centre removed in an earlier window),
  // the cell whose label-guard bucket lists it at set-up; -1 for the others.
  const int32_t* sample_cell = nullptr;
  // The vertex flags already hold ApplyFeatureThreshold and the two-label cells of the input grid
  // (the window's carried cells are simplified ones, whose labels would flag other vertices).
  bool flags_complete = true;
  // The whole volume's scalar range (the tie break between equal costs is scaled by it).
  double scalar_lo = 0, scalar_hi = 1;
  // Pacing by a cost threshold (the streamed run's): >= 0, the serial loop alone (no parallel
  // rounds) runs until the target is reached or the queue's cheapest cost exceeds this (infinity:
  // the target alone); -1: the engine's usual rounds and loop, up to the target.
  double stop_cost = -1;
  // Out, if set: the serial loop's collapses in order, (queue cost, cells removed) each.
  std::vector<std::pair<float, int32_t>>* cost_log = nullptr;
  // Out, if set: the costs of the collapses still queued when the run stopped (what the next ones
  // would cost, before the collapses between them change it).
  std::vector<float>* queued_costs = nullptr;
  // Out, InterfaceMode::kFree: per input vertex, the output cell whose bucket lists it (-1: none,
  // e.g. a surviving vertex).
  std::vector<int32_t>* sample_home = nullptr;
};

// The vertex flags the field policy works with: `mesh`'s, with ApplyFeatureThreshold, and
// kFeatureVertex on every vertex of a cell that holds two labels. On `threads`; the result does
// not depend on them. A streamed run computes them once on the whole grid (FieldWindow).
void FieldVertexFlags(const TetMesh& mesh, const SimplifyOptions& options, int threads,
                      std::vector<uint8_t>* flags);

// RunFieldSimplify of one window (no levels, no tolerance). Frozen vertices are never removed.
absl::Status RunFieldSimplifyWindow(const TetMesh& mesh, const SimplifyOptions& options,
                                    int threads, int64_t target, const FieldWindow& window,
                                    const ProgressFn& progress, const CancelToken* cancel,
                                    SimplifyResult* result);

// What the field policy's rules say of one half-edge collapse u -> v of the input mesh, for tests
// that drive a single collapse (CheckFieldCollapse).
enum class FieldCollapseCheck {
  kAllowed,
  kNotATarget,    // the constraint rules (hull, voxel layers, junctions) do not let u go to v
  kInvalid,       // rule 6 (volume, a vertex's last cell) or the shape guard refuses it
  kLabelChanged,  // InterfaceMode::kFree: a voxel centre would leave the mesh or get another label
  kTopologyChanged,  // kFree, every label kept: a label region might change its topology
};
FieldCollapseCheck CheckFieldCollapse(const TetMesh& mesh, const SimplifyOptions& options,
                                      int32_t u, int32_t v);

// Per input vertex, 1 if the constraint rules pin it (no target at all) in the input mesh: under
// InterfaceMode::kVoxelFaces the corners of the voxel staircase, under kFree the junctions of
// three or more labels; hull corners under both.
std::vector<uint8_t> PinnedFieldVertices(const TetMesh& mesh, const SimplifyOptions& options);

// The axis (0, 1, 2) the parallel rounds cut into slabs of `width` mm, for n vertices at
// `positions` (x, y, z each) inside the box [lo, hi]. The longest axis, since a shorter one gives
// fewer or thinner slabs; among the axes at least 0.9 of the longest, the one whose slabs split
// the vertex ids into the fewest runs. A slab whose vertices are a few long ranges of ids keeps
// its thread's loads in fewer pages and cache lines than one made of thousands of short rows
// (the grid's numbering with slabs along x: core/simplify/README.md, "Slab axis and slab width").
int SlabAxis(const float* positions, int64_t n, const float lo[3], const float hi[3], double width,
             int threads);

}  // namespace decima::simplify_internal
