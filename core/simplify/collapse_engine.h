// The collapse engine behind Simplify(): mesh state during decimation, one collapse at a time.
// Internal to core/simplify; exposed so the tests can drive single collapses on hand-built
// meshes (a rejected collapse must leave the mesh untouched).
//
// State invariants between calls:
//  - mesh.tets holds every cell of the pass (dead ones flagged in `dead_`), vertex ids global
//    (the input's numbering; merged vertices are unreferenced and point to their survivor in
//    `parent_`);
//  - adjacency_ lists, for every vertex, the live cells that contain it, except for vertices of
//    cells collapsed or locked in this pass, which are never queried again in the pass (a cell
//    is only collapsed if no collapse of the pass touched any of its vertices).
#pragma once

#include <cstdint>
#include <vector>

#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima::simplify_internal {

enum class Outcome : uint8_t {
  kCollapsed,
  kDead,                   // the cell was deleted earlier in the pass
  kLocked,                 // the cell is in A(σ) of a collapse σ of this pass (§2.2.4 step 2g)
  kUnchanged,              // rejected (rule 4 or 6) before, and nothing around it changed since
  kTwoFeatureVertices,     // rule 2
  kCrossRegion,            // rule 3
  kTwoBoundaryVertices,    // rule 5
  kBoundaryCell,           // TetFusion keeps every cell touching the hull
  kPinnedConflict,         // two different vertices must stay (feature / boundary / rule 4)
  kCrossRegionNeighbours,  // rule 4: no common vertex with the cross-region neighbours
  kFeatureNeighbourhood,   // rule 4: A(τ) holds > 1 feature cell and > 1 feature vertex
  kFlip,                   // rule 6: a cell of A(τ) would flip or become a sliver
};
const char* OutcomeName(Outcome o);

// Where a cell collapses and what it is predicted to cost.
struct CellPlan {
  Outcome outcome = Outcome::kCollapsed;  // kCollapsed = allowed so far
  int8_t target_slot = -1;                // -1 centroid, else 0..3: the vertex that stays
  float error = 0;                        // Δε of Eq. (8) (or the local part for TetFusion)
};

struct CollapseResult {
  Outcome outcome = Outcome::kCollapsed;
  int32_t survivor = -1;      // global id of the vertex at the collapse point
  int32_t cells_removed = 0;  // 1 + |D(τ)|
  float error = 0;
};

class CollapseEngine {
 public:
  // `mesh` must be valid (checked by Simplify). Feature flags are re-derived here if
  // options.feature_threshold_voxels >= 0.
  CollapseEngine(TetMesh mesh, const SimplifyOptions& options);

  // Drops the cells deleted so far, rebuilds adjacency, neighbourhood volumes and the
  // cross-region marks, and unlocks every cell. Cell ids are positions in mesh().tets.
  void BeginPass(int threads);

  // Own-vertex rules (2, 3, 5, rule 4 estimated from the pass-start marks) and Δε.
  CellPlan PlanCell(int32_t cell) const;

  // Checks all rules on the current mesh and performs the collapse if they allow it.
  CollapseResult TryCollapse(int32_t cell);

  // Scores every live cell (in parallel) and returns the collapsible ones sorted by
  // (error, cell id); errors in `errors` (same order).
  void SortedCandidates(int threads, std::vector<int32_t>* cells, std::vector<float>* errors);

  // Compacts vertices and cells; fills the vertex map (input vertex -> output vertex or -1).
  void Finish(TetMesh* out, std::vector<int32_t>* vertex_map);

  const TetMesh& mesh() const { return mesh_; }
  int64_t live_cells() const { return live_cells_; }
  bool dead(int32_t cell) const { return dead_[cell] != 0; }

 private:
  struct Neighbour {
    int32_t cell;
    uint8_t shared_mask;  // bit k: τ's slot k is a vertex of this cell
  };
  bool IsFeature(int32_t v) const { return (mesh_.vertex_flags[v] & kFeatureVertex) != 0; }
  bool IsBoundary(int32_t v) const {
    return (mesh_.vertex_flags[v] & kExteriorBoundaryVertex) != 0;
  }
  bool IsCrossRegionCell(const int32_t* tet) const;
  double CellVolume(const int32_t* tet) const;
  // Δε for collapsing `tet` to slot (or centroid when -1).
  float PlanError(const int32_t* tet, double volume, int slot) const;
  // Lowest ω_g ε_g + ω_s ε_s among the slots in `mask`, ties to the lower vertex id.
  int BestSlot(const int32_t* tet, unsigned mask) const;
  // Fills a_set_ / d_set_. With a collapse point `p` (slot as in CellPlan) it also runs rule 6
  // and stops early, returning false, at the first cell of A(τ) that would flip.
  bool GatherNeighbours(int32_t cell, int slot, const float* p);
  // One Gauss-Seidel sweep (vertex id order) moving every normal vertex whose star lies in one
  // region towards the volume centroid of its star, if that raises the star's worst mean-ratio
  // quality and keeps every cell above the volume guard; the value there is interpolated in the
  // current mesh. Returns the number of vertices moved.
  int64_t SmoothVertices();

  TetMesh mesh_;
  SimplifyOptions options_;
  double voxel_ = 1, voxel_volume_ = 1, min_volume_ = 0;
  int pass_ = 0;  // passes begun
  // Region statistics of the input (Eq. 5): mean and variance per label.
  double region_mean_[256] = {}, region_var_[256] = {}, region_std_[256] = {};
  double global_std_ = 1;        // of all input values: ε_g's unit for TetFusion
  std::vector<int32_t> parent_;  // per vertex: itself, or the vertex it merged into
  std::vector<uint8_t> dead_;    // per cell
  // Skipping hopeless retries: a cell rejected by rule 4 or 6 at clock value r is retried only
  // once a vertex of it has touched_ >= r (a collapse changed a cell around that vertex).
  uint64_t clock_ = 0;
  std::vector<uint64_t> rejected_at_;  // per cell, 0 = never rejected
  std::vector<uint64_t> touched_;      // per vertex
  std::vector<uint8_t> locked_;        // per cell, this pass
  std::vector<float> cell_volume_;     // per cell, pass start
  std::vector<double> star_volume_;    // per vertex: volume of its incident cells, pass start
  std::vector<uint8_t> cross_touch_;   // per vertex: in a cross-region cell, pass start
  VertexTetAdjacency adjacency_;
  int64_t live_cells_ = 0;
  // Scratch of TryCollapse, allocated once.
  std::vector<Neighbour> a_set_, d_set_;
  // Scratch of SortedCandidates.
  std::vector<uint32_t> keys_, keys_tmp_, sort_keys_, sort_count_;
  std::vector<int32_t> ids_tmp_;
};

}  // namespace decima::simplify_internal
