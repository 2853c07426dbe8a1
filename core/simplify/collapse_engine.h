// The collapse engine behind Simplify(): mesh state during decimation and the greedy queue.
// Internal to core/simplify; exposed so the tests can drive single collapses on hand-built
// meshes (a rejected collapse must leave the mesh untouched).
//
// State invariants between calls:
//  - mesh_.tets holds every input cell; deleted ones are flagged in dead_. A live cell's four
//    vertex ids are live vertices (a merged vertex is never referenced again; parent_ points to
//    the vertex it merged into).
//  - The cells around a live vertex v are the live cells among the adjacency rows of every
//    vertex of v's merge class (v itself and the vertices merged into it, linked by
//    VertexRow::class_next). Rows are compacted lazily: a walk drops the dead cells it meets. A
//    live cell appears exactly once among them (a cell holding two members of one class would be
//    degenerate, and those are deleted).
//  - cell_volume_ holds the current volume of every live cell, VertexStar::star_volume the
//    sum over the live cells around every live vertex (both updated by each collapse).
//  - star_[v].touched is the clock value of the last collapse that changed a cell around v;
//    scored_at_[c] / rejected_at_[c] the clock when c's error was computed / c was rejected.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "core/common/bit_set.h"
#include "core/common/huge_pages.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima::simplify_internal {

enum class Outcome : uint8_t {
  kCollapsed,
  kDead,                   // the cell was deleted earlier
  kLocked,                 // paper mode: in A(σ) of a collapse σ of this pass (§2.2.4 step 2g)
  kUnchanged,              // rejected (rule 4 or 6) before, and nothing around it changed since
  kTwoFeatureVertices,     // rule 2
  kCrossRegion,            // rule 3
  kTwoBoundaryVertices,    // rule 5
  kBoundaryCell,           // TetFusion keeps every cell touching the hull
  kPinnedConflict,         // two different vertices must stay (feature / boundary / rule 4)
  kCrossRegionNeighbours,  // rule 4: no common vertex with the cross-region neighbours
  kFeatureNeighbourhood,   // rule 4: A(τ) holds > 1 feature cell and > 1 feature vertex
  kFlip,                   // rule 6: a cell of A(τ) would flip or become a sliver
  kRequeued,               // the only valid point costs more than the next cell in the queue
};
const char* OutcomeName(Outcome o);

// With SimplifyOptions::feature_threshold_voxels set, re-derives the kFeatureVertex bit of every
// vertex from its interface distance (both engines see features through this); unset: no-op.
void ApplyFeatureThreshold(const SimplifyOptions& options,
                           const std::vector<float>& interface_distance,
                           std::vector<uint8_t>* flags);

// True for the outcomes that can never change for a cell (its vertices can only gain feature
// or boundary vertices, and cross-region cells are never created): such cells leave the queue
// for good.
bool IsPermanent(Outcome o);

// Where a cell collapses and what it is predicted to cost (from the cell alone).
struct CellPlan {
  Outcome outcome = Outcome::kCollapsed;  // kCollapsed = allowed so far
  int8_t target_slot = -1;  // -1 free point (rule 1), else 0..3: the vertex that stays
  float error = 0;          // Δε of Eq. (8) at the centroid or the kept vertex
};

struct CollapseResult {
  Outcome outcome = Outcome::kCollapsed;
  int32_t survivor = -1;      // global id of the vertex at the collapse point
  int32_t cells_removed = 0;  // 1 + |D(τ)|
  float error = 0;            // Δε of the point used (or of the best valid point, kRequeued)
  // Row of the free merge table: 0 the paper's rule 1 (all four to the centroid), > 0 a widened
  // merge; -1 onto a vertex that must stay (rules 2, 4, 5), < -1 a widened merge onto it.
  int8_t point = -1;
  int8_t merged = 4;  // vertices of τ merged (4 = the paper's collapse; 2 or 3 widened)
};

struct EnginePassStats {
  int64_t candidates = 0, collapses = 0, cells_removed = 0, rejected_flip = 0, rejected_rule4 = 0;
  int64_t requeued = 0;     // popped with a stale or too low key and pushed back
  int64_t other_point = 0;  // collapses to a point other than the centroid / pinned vertex
  double last_error = 0, max_error = 0;
  bool tolerance_hit = false;
};

class CollapseEngine {
 public:
  // `mesh` must be valid (checked by Simplify). Feature flags are re-derived here if
  // options.feature_threshold_voxels is set. `threads` only speeds up the set-up.
  CollapseEngine(TetMesh mesh, const SimplifyOptions& options, int threads = 1);

  // Starts a pass: every live cell that may collapse and was not rejected since its
  // neighbourhood last changed is scored (in parallel) and sorted by (Δε, cell id); locks are
  // cleared. Returns the number of queued cells.
  int64_t BeginPass(int threads);

  // Runs the greedy loop of §2.2.4 on the pass's queue until `max_removed` cells were removed
  // in total, the queue is empty, or the next Δε exceeds `tolerance` (> 0). Errors: Cancelled.
  absl::Status RunPass(int64_t max_removed, double tolerance, const CancelToken* cancel,
                       EnginePassStats* stats);

  // Own-vertex rules (2, 3, 5; rule 4 estimated from the set-up marks) and Δε on the current
  // mesh.
  CellPlan PlanCell(int32_t cell) const;

  // Checks all rules on the current mesh and performs the collapse if they allow it. With
  // `next_key`, a collapse whose valid point costs more than that is not made (kRequeued).
  CollapseResult TryCollapse(int32_t cell, float next_key = 3.4e38f);

  // Compacts vertices and cells; fills the vertex map (input vertex -> output vertex or -1).
  void Finish(TetMesh* out, std::vector<int32_t>* vertex_map);

  const TetMesh& mesh() const { return mesh_; }
  int64_t live_cells() const { return live_cells_; }
  int64_t removed_cells() const { return mesh_.tet_count() - live_cells_; }
  bool dead(int32_t cell) const { return IsDead(cell); }

 private:
  struct Neighbour {
    int32_t cell;
    uint8_t shared_mask;  // bit k: τ's slot k is a vertex of this cell
    uint8_t pos[4];       // for a shared slot k: the position of τ's vertex k in this cell
    double n[3], d;       // A(τ) only: 6 * volume with the shared vertex at p is n . p + d
  };
  bool IsFeature(int32_t v) const { return (mesh_.vertex_flags[v] & kFeatureVertex) != 0; }
  bool IsBoundary(int32_t v) const {
    return (mesh_.vertex_flags[v] & kExteriorBoundaryVertex) != 0;
  }
  bool IsDead(int32_t c) const { return dead_.Test(c); }
  void Kill(int32_t c) { dead_.Set(c); }
  bool IsLocked(int32_t c) const { return locked_.Test(c); }
  void Lock(int32_t c) { locked_.Set(c); }
  bool IsCrossRegionCell(const int32_t* tet) const;
  double CellVolume(const int32_t* tet) const;
  uint32_t LastTouch(int32_t cell) const;
  // The terms of Eq. (8) that do not depend on the collapse point (ε_r, ε_v, ε_n).
  struct PointFreeError {
    uint8_t region;
    double e_r, e_v, e_n;
  };
  PointFreeError PointFreeTerms(const int32_t* tet, double volume) const;
  // Δε (Eq. 8) of deleting `tet` (of signed volume `volume`) by merging its vertices in `mask`
  // into the point with barycentric weights `w` (sum 1, zero outside the mask). ε_g and ε_s
  // sum over the merged vertices only (the others keep their value and place).
  float MergeError(const int32_t* tet, const PointFreeError& base, unsigned mask,
                   const double* w) const;
  float MergeError(const int32_t* tet, double volume, unsigned mask, const double* w) const {
    return MergeError(tet, PointFreeTerms(tet, volume), mask, w);
  }
  // Lowest ω_g ε_g + ω_s ε_s among the slots in `mask`, ties to the lower vertex id.
  int BestSlot(const int32_t* tet, unsigned mask) const;
  // Fills a_set_ / d_set_ with the live cells around τ's vertices.
  void GatherNeighbours(int32_t cell);
  // 6 * volume of neighbour `n` with τ's vertex `slot` (one of its vertices) moved to p.
  double MovedVolume6(const Neighbour& n, int slot, const float* p) const;
  // Rule 6 for merging τ's vertices in `mask` at p: every cell that keeps exactly one merged
  // vertex, and not the one at `fixed_slot` (or -1), must keep at least the guard volume.
  // Also rejects merges that would delete every cell around a feature or boundary vertex.
  bool MergeValid(unsigned mask, int fixed_slot, const float* p) const;
  bool OrphansPinnedVertex(unsigned mask, int fixed_slot) const;
  void PushKey(uint32_t key, int32_t cell);

  TetMesh mesh_;
  SimplifyOptions options_;
  double voxel_ = 1, voxel_volume_ = 1, min_volume_ = 0;
  // Region statistics of the input (Eq. 5): mean and variance per label.
  double region_mean_[256] = {}, region_var_[256] = {}, region_std_[256] = {};
  double global_std_ = 1;  // of all input values: ε_g's unit for TetFusion
  int64_t live_cells_ = 0;
  uint32_t clock_ = 1;  // collapses made + 1

  // Per vertex.
  std::vector<int32_t> parent_;  // itself, or the vertex it merged into
  // Per-vertex state in two 16-byte records, each read together: collapses and the walks of
  // the cells around a vertex are bound by memory latency.
  struct VertexRow {     // what a walk of the cells around a vertex reads
    int32_t begin;       // adjacency row start in adj_ids_ (input CSR; 4 * cells fits int32)
    int32_t count;       // live prefix length of the row after compaction
    int32_t class_next;  // next member of the merge class, -1 at the end
    int32_t class_tail;  // last member (valid for live vertices)
  };
  struct VertexStar {    // what a collapse updates around the vertices it changes
    double star_volume;  // sum of the volumes of the live cells around the vertex
    int32_t valence;     // live cells around the vertex
    uint32_t touched;    // clock of the last collapse that changed a cell around the vertex
  };
  std::vector<VertexRow> rows_;
  std::vector<VertexStar> star_;
  std::vector<int32_t, FillLaterAllocator<int32_t>> adj_ids_;
  std::vector<uint8_t> cross_touch_;  // in a cross-region cell at set-up (a superset later)
  // Per cell.
  BitSet dead_;                     // deleted cells
  std::vector<uint8_t> permanent_;  // an IsPermanent outcome: never queued again
  std::vector<float> cell_volume_;
  std::vector<uint32_t> scored_at_, rejected_at_;
  BitSet locked_;  // paper mode: locked in this pass

  // The pass's queue: cells sorted by (key, id), then a min-heap of re-pushed (key, id).
  std::vector<int32_t> order_;
  std::vector<uint32_t> order_keys_;
  std::vector<std::pair<uint32_t, int32_t>> heap_;

  // Scratch, allocated once.
  std::vector<Neighbour> a_set_, d_set_;
  std::vector<int32_t> gather_ids_;
  int32_t current_ = 0;  // τ of the gathered sets
  std::vector<uint32_t> keys_, keys_tmp_, sort_count_;
  std::vector<int32_t> ids_tmp_;
};

}  // namespace decima::simplify_internal
