// Decimation of a tetrahedral mesh with three policies:
//  - kField (the job default): greedy half-edge collapses ranked by the error of the
//    piecewise-linear field (4-D quadrics). Surviving vertices keep their position and voxel
//    sample; hull vertices move only inside a box face or along a box edge, so the hull stays the
//    same point set. Interfaces (`interfaces`): by default an interface vertex may go wherever
//    every voxel centre of the input keeps its own label (label mismatch 0, coverage 1), except
//    where three labels meet; with kVoxelFaces it moves only inside a planar patch of its voxel
//    layer or along a straight crease of it, corners never. Every cell stays positive and the
//    mesh conforming, the output does not depend on `threads`. README.md: "The field policy".
//  - kPaper: feature-preserving greedy cell collapse (paper §2.2), described below.
//  - kTetFusion: the TetFusion baseline (Chopra & Meyer 2002) on the paper's engine.
//
// A collapse merges the four vertices of a cell τ into one point: the centroid (rule 1), or a
// vertex of τ that must not move (a feature vertex, rule 2; the vertex shared with a
// cross-region cell, rule 4; an exterior-boundary vertex, rule 5). Every cell sharing two or
// more vertices with τ (the set D(τ)) degenerates and is deleted; every cell sharing exactly one
// (A(τ)) has that vertex moved to the collapse point and must keep a positive volume (rule 6).
//
// Guarantees of the result (kPaper policy), proved by tests/core/simplify:
//  - feature vertices are never moved or removed, so interior boundaries stay exactly where the
//    segmentation put them; exterior-boundary vertices are never moved or removed, so the hull
//    (and the total volume) is unchanged;
//  - every cell is positively oriented with volume >= min_volume_fraction voxels, and the mesh
//    is conforming (each interior face shared by exactly two cells);
//  - the output depends only on the input mesh and the options, never on `threads`.
// core/simplify/README.md lists how the paper's ambiguous points were read.
//
// Greedy loop (§2.2.4), one pass:
//   compute Δε (Eq. 8) for every collapsible cell; sort ascending (ties by cell id);
//   for τ in that order, while removed < target and Δε(τ) <= tolerance:
//     skip τ if it was deleted or locked;
//     check rules 1-6 on the current mesh; if allowed: collapse, delete D(τ), lock A(τ).
// Passes repeat on the surviving cells until the target, the tolerance, no collapsible cell,
// or max_passes stops them.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"

namespace decima {

enum class SimplifyPolicy : uint8_t {
  kPaper,      // rules 1-6 of §2.2.2 and the full error of Eq. (8)
  kTetFusion,  // every interior cell to its centroid, local error only, rule 6, hull kept
  kField,      // field-accurate: half-edge collapses ranked by the field's quadric error
};

// kField: how vertices of two-label cells (the interfaces) may move. README "Interfaces free inside
// their voxels".
enum class InterfaceMode : uint8_t {
  // The default. Any half-edge collapse of an interface vertex is allowed if every voxel centre of
  // the input still lies only in cells that give it its own label (label mismatch 0, coverage 1;
  // the label of a point as core/metrics/fidelity.h defines it), checked exactly on one sample per
  // removed input vertex. Vertices where three or more labels meet stay where they are.
  kFree,
  // The voxel staircase kept as a point set: an interface vertex moves only inside a planar patch
  // or along a straight crease of its voxel layer; corners never move (the behaviour before).
  kVoxelFaces,
};

// Weights of Eq. (8); defaults are the paper's Table 2 (CT-head). Any value >= 0.
struct ErrorWeights {
  double regional = 10;  // ω_r: ε_r, cell variance about the region mean / region variance
  double gradient = 2;   // ω_g: ε_g, mean |s_i - s'| / region standard deviation
  double shape = 1;      // ω_s: ε_s, mean distance of the vertices to the collapse point, voxels
  double volume = 1;     // ω_v: ε_v, cell volume, voxels^3
  double neighbour = 0.5;  // ω_n: ε_n, cell volume / volume of its neighbourhood
};

struct SimplifyOptions {
  SimplifyPolicy policy = SimplifyPolicy::kPaper;
  // Fraction of the input cells to remove, in [0, 0.99]. 0 = no target: run until the error
  // tolerance or no collapsible cell remains.
  double target_reduction = 0.5;
  // Largest predicted error a collapse may have, finite >= 0; 0 means no tolerance.
  // kPaper/kTetFusion: Δε of Eq. (8). kField: the RMS field deviation its quadric predicts, in
  // image units.
  double error_tolerance = 0;
  ErrorWeights weights;
  // Feature vertices: unset, the kFeatureVertex flags as Tetrahedralize set them (with its own
  // feature_threshold_voxels); set, re-derived as |interface_distance| <= this many voxels.
  std::optional<float> feature_threshold_voxels;
  // Grid spacing in mm that makes ε_s, ε_v and the volume guard unit-free ("voxel units": the
  // mean of the three spacings). 0 = estimate as cbrt(5 * mean cell volume), exact for an
  // unsimplified 5-tets-per-cube mesh of an isotropic grid.
  double voxel_size_mm = 0;
  // A collapse is rejected if a moved cell would end with volume below this many voxels^3
  // (rule 6's sign test plus a guard against slivers). Must be > 0.
  double min_volume_fraction = 1e-3;
  // kField, the shape guard: a collapse may not give a cell it changes a dihedral angle below
  // this many degrees, unless that cell already had a smaller one (so cells of the input never
  // block themselves). 0 = no guard. In [0, 30]. README "Shape guard" has what it costs.
  double min_dihedral_degrees = 5;
  // §2.2.4 step 2g (default): after a collapse, lock the cells it changed for the rest of the
  // pass (a pass is then an independent set of collapses; passes repeat). false: no lock;
  // cells whose neighbourhood changed are re-scored when they reach the front of the queue and
  // pushed back if no longer the cheapest, so one pass follows the error order as far as it
  // goes: better fidelity, about 2x the time (README.md has the figures).
  bool lock_neighbours = true;
  // kPaper: when the paper's collapse of τ (all four vertices to the centroid, or onto the
  // vertex that must stay) would flip a neighbour, delete τ by the valid merge with the lowest
  // Δε among: all four at a face centroid, edge midpoint or vertex; three of them at their
  // centroid, an edge midpoint or a vertex; two (an edge) at its midpoint or an end. A vertex
  // that must stay never moves (its merges end on it). false = the paper's collapse only.
  bool widen_collapse_point = true;
  // Passes: each re-queues the cells not collapsed yet whose neighbourhood changed since they
  // were last rejected. 1..10000.
  int max_passes = 64;
  // A pass that removes fewer than this fraction of the input cells ends the loop (the mesh is
  // jammed: later passes gain almost nothing). 0 = run until a pass removes nothing.
  // In [0, 0.5].
  double min_pass_gain = 1e-3;
  // kField: preconditioned conjugate-gradient steps of the least-squares refit of the vertex values
  // to the original samples after the collapses (README "Refit"); 0 keeps every surviving vertex's
  // voxel sample. 0..1000.
  int refit_iterations = 10;
  // kField: record the collapse sequence down to this reduction (the level floor), in [0, 0.99];
  // 0 = none. The run then goes to max(target, floor) and `mesh` is the level at the target taken
  // from the record (levels.h), so every run with the same options and floor gives, at any
  // reduction it recorded, the same mesh as a run to that reduction. The parallel rounds are
  // paced by the floor instead of the target for that (README "Levels").
  double record_levels_to = 0;
  // kField: interfaces free inside their voxels under the label guard (default) or kept as the
  // voxel staircase. Ignored by the other policies.
  InterfaceMode interfaces = InterfaceMode::kFree;
  int threads = 0;  // worker threads (scoring; kField: its slabs too); 0 = hardware concurrency
};

enum class StopReason : uint8_t {
  kTargetReached,    // removed >= target_reduction of the input cells
  kErrorTolerance,   // every remaining collapsible cell predicts more than error_tolerance
  kNoValidCollapse,  // a pass found no collapse the rules and the flip check allow
  kMaxPasses,        // max_passes ran out first
  kStalled,          // the last pass removed fewer than min_pass_gain of the input cells
  // A job's PSNR floor (pipeline::JobSpec::min_psnr) stopped it: the next level searched measured
  // below the floor. Simplify itself never returns it; the job's search of the levels does.
  kPsnrFloor,
};
const char* StopReasonName(StopReason reason);

// "paper", "tetfusion", "field": the one spelling of each policy in files, flags and the API.
const char* SimplifyPolicyName(SimplifyPolicy policy);
// The policy of that name, or nullopt for any other string (case-sensitive).
std::optional<SimplifyPolicy> ParseSimplifyPolicy(std::string_view name);
// "field, paper, tetfusion": every name, for help texts and error messages.
std::string SimplifyPolicyNames();

// "free", "voxel-faces": the one spelling of each interface mode in flags, files and the API.
const char* InterfaceModeName(InterfaceMode mode);
// The mode of that name, or nullopt for any other string (case-sensitive).
std::optional<InterfaceMode> ParseInterfaceMode(std::string_view name);

struct SimplifyPassStats {
  int64_t candidates = 0;      // cells the own-vertex rules allowed at the start of the pass
  int64_t collapses = 0;       // collapses performed
  int64_t cells_removed = 0;   // cells removed by them (τ plus D(τ))
  int64_t rejected_flip = 0;   // rejected by rule 6 (sign or sliver) at every point tried
  int64_t rejected_rule4 = 0;  // rejected by rule 4 (cross-region / feature neighbourhood)
  int64_t requeued = 0;        // re-scored at the front of the queue and pushed back
  int64_t other_point = 0;     // free collapses made at a point other than the centroid
  double last_error = 0;       // Δε of the last collapse of the pass
};

// The collapse sequence of a field-policy run (SimplifyOptions::record_levels_to), from which
// levels.h's ExtractLevel gives the mesh at any recorded reduction. A simplicial map with levels:
// half-edge collapses keep every survivor's attributes, so each collapse is (u, v) and its count.
struct SimplifyLevels {
  int64_t base_vertices = 0;  // of the mesh Simplify was given (the base of every level)
  int64_t base_cells = 0;
  // The refit steps every extracted level gets (SimplifyOptions::refit_iterations of the run).
  int32_t refit_iterations = 0;
  // BaseMeshDigest (levels_io.h) of the base: ExtractLevel refuses another mesh of the same size.
  uint64_t base_digest = 0;
  // true: the run stopped because no collapse was left (or the tolerance stopped it), so a
  // reduction deeper than the last level gives the last level, as a run to it would; false: the
  // run stopped at its floor (SimplifyOptions::record_levels_to), and deeper is unknown.
  bool exhausted = false;
  // Collapse i merged removed_vertex[i] into survivor[i] (base vertex ids) and deleted
  // cells_deleted[i] cells. The order is the run's: every prefix is a valid mesh.
  std::vector<int32_t> removed_vertex;
  std::vector<int32_t> survivor;
  std::vector<uint16_t> cells_deleted;

  int64_t collapses() const { return int64_t(removed_vertex.size()); }
  int64_t cells_removed() const;  // by every collapse
  // The deepest recorded reduction: cells_removed() / base_cells.
  double deepest_reduction() const;
};

struct SimplifyResult {
  TetMesh mesh;  // compacted: no unreferenced vertex, no deleted cell
  // vertex_map[v] for every input vertex v: index in `mesh` of the vertex it became (itself,
  // or the vertex it was merged into), or -1 if it no longer exists.
  std::vector<int32_t> vertex_map;
  int64_t input_cells = 0;
  int64_t output_cells = 0;
  double achieved_reduction = 0;  // 1 - output_cells / input_cells
  bool reached_target = false;
  StopReason stop_reason = StopReason::kTargetReached;
  std::string stop_message;  // one line: why the loop stopped, with the numbers
  int passes = 0;
  int64_t collapses = 0;
  double max_error = 0;  // largest Δε of a performed collapse
  std::vector<SimplifyPassStats> pass_stats;
  // With SimplifyOptions::record_levels_to: every collapse of the run, down to the floor.
  std::optional<SimplifyLevels> levels;
};

// OK if every option is in its documented range, else InvalidArgument whose message names the
// option ("simplify: option target_reduction = 2: ..."). Simplify calls it first; callers that
// take options from outside (the server's job spec) call it where the value enters.
absl::Status ValidateSimplifyOptions(const SimplifyOptions& options);

// Simplifies `mesh` (a valid TetMesh, see tet_mesh.h; every cell positively oriented). The field
// policy without record_levels_to also takes a mesh whose cells are dropped (DropGridCells), the
// same result in 17 bytes per cell less (README "Memory"); the others refuse it. Progress
// stage "simplify": once per pass (kField: once per parallel round, then about every 2 % of the
// target) with metrics {"pass", "cells_removed", "error"}; kField adds one event after its
// set-up and, with the refit, a last one with {"refit_rms_before", "refit_rms_after"}. Returns
// InvalidArgument (naming the field) for an invalid mesh or options, Cancelled if `cancel`
// fired (checked every pass, every round and every 65536 queue entries). Not reaching the target is
// not an error: the result says so (reached_target, stop_reason, stop_message). Thread-safe for
// distinct arguments; uses up to options.threads threads it starts itself.
absl::StatusOr<SimplifyResult> Simplify(const TetMesh& mesh, const SimplifyOptions& options,
                                        const ProgressFn& progress = nullptr,
                                        const CancelToken* cancel = nullptr);

// Whether Simplify with `options` reads the input's cells only through TetMesh::Cell, so a grid
// mesh may come with its cells dropped (DropGridCells, or Tetrahedralize without cells): the
// field engine without a level record. The cell-collapse engine and the level record
// (ExtractLevel, BaseMeshDigest) read `tets`.
bool RunsWithoutCells(const SimplifyOptions& options);

// Simplify(*mesh, ...), with the mesh's cells freed for the run when they can be: a mesh that
// records its grid (Tetrahedralize's), under the field policy without record_levels_to, has its
// tets and cell_regions dropped (DropGridCells: 17 bytes per cell less at the job's peak) and
// restored (RestoreGridCells) before this returns, whatever it returns. The same result as
// Simplify; the mesh is as it was. With `restore_cells` false a caller that needs the cells no
// more keeps them dropped (mesh->cells_dropped says whether they were).
absl::StatusOr<SimplifyResult> SimplifyDroppingCells(TetMesh* mesh, const SimplifyOptions& options,
                                                     const ProgressFn& progress = nullptr,
                                                     const CancelToken* cancel = nullptr,
                                                     bool restore_cells = true);

}  // namespace decima
