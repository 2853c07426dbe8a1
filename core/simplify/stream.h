// Streamed simplification (issue 30): the field policy over a grid mesh in slabs of voxel layers
// along z, so that the engine's per-vertex state (quadrics, queue records, adjacency, label
// buckets: ~290 bytes per voxel) is held for one window at a time instead of the whole volume.
// README.md "Streamed simplification" has the design and the measurements.
//
// A sliding window (after Vo, Callahan, Lindstrom, Pascucci, Silva, "Streaming simplification of
// tetrahedral meshes", TVCG 2007): window k is the cells carried over from window k-1 plus the
// grid cells of slab k (slab_voxels cube layers). The vertices on its open top plane and those
// shared with cells already written out are frozen (never removed), so the window is simplified
// on its own with the engine's rules unchanged; then the cells lying wholly at or below the middle
// of slab k are written out and the rest carried on. The label guard's samples (removed voxel
// centres) stay in the buckets of the cells that carry them. Every window but the last collapses
// while the queue's cheapest cost is at most one global threshold, found by measuring passes of
// the same windows; the last one removes exactly what is left of the target.
#pragma once

#include <functional>
#include <optional>
#include <string>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima {

// Slabs thinner than this are refused: the frozen top plane and the written-out half would leave
// a window almost nothing to collapse.
inline constexpr int kMinStreamSlabVoxels = 4;

// Where a streamed run keeps its progress, so that a run stopped inside the stage (a job child
// killed, or a server drained) resumes after the last window it finished instead of from the
// first: a stopped run loses at most one window's work. After each window the run saves one
// record: the run's counters and thresholds, the cells that window wrote out and the survivors
// it chose (deltas), and the cells and samples it carried on (whole). The records of one pass,
// read back in order, rebuild the run's state exactly, so a resumed run's result is bit-identical
// to that of a run in one go (the output does not depend on the thread count either).
struct StreamJournal {
  // Saves the record of window `window` (0-based) of pass `pass` (measuring passes first, then the
  // final one). Once window 0 of a pass is saved, the records of earlier passes are not read again.
  // A record that could not be saved only costs a resumed run that window: the caller reports it.
  std::function<void(int pass, int64_t window, const std::string& record)> save;
  // The record saved for (pass, window); nullopt when there is none or it is not intact.
  std::function<std::optional<std::string>(int pass, int64_t window)> load;
  // Out: the windows of a pass, set before the first call of either function.
  int64_t windows_per_pass = 0;
  // Out: the windows read back instead of simplified (0: the run started from its first window).
  int64_t resumed_windows = 0;
};

// Simplify(mesh, options) in slabs of `slab_voxels` cube layers along z. `mesh` must record its
// grid (Tetrahedralize's; its cells may be dropped); options: the field policy, a target
// (target_reduction > 0), no error tolerance, no record_levels_to. slab_voxels >= the grid's
// cube layers (nz - 1): one window, exactly Simplify. The result has SimplifyResult's shape
// (compacted explicit mesh, vertex_map onto it, refit over the whole output); pass_stats holds
// one entry per window. InvalidArgument (naming the option) for what it refuses; the output does
// not depend on options.threads. With `journal`, the run first reads back what an earlier run of
// the same mesh and options saved (a record that does not parse ends the reading: the run goes on
// from the window before it) and saves a record after every window it simplifies.
absl::StatusOr<SimplifyResult> SimplifyStreamed(const TetMesh& mesh, const SimplifyOptions& options,
                                                int slab_voxels,
                                                const ProgressFn& progress = nullptr,
                                                const CancelToken* cancel = nullptr,
                                                StreamJournal* journal = nullptr);

}  // namespace decima
