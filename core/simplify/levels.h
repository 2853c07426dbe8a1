// Levels of detail from one simplification: the collapse sequence of a run, as a simplicial map
// with levels (Guéziec/Taubin "simplicial maps"; Hoppe's progressive meshes run backwards), from
// which the mesh at any recorded reduction is one pass over the base mesh's cells.
//
// Only the field policy records levels. Its collapses are half-edge collapses u -> v: u
// disappears, v keeps its position, value, label and flags, so a collapse is fully described by
// the pair (u, v) and the number of cells it deleted; no survivor attribute ever changes. The
// refit of the vertex values (field_refit.h) depends on the level's cells, so ExtractLevel runs
// it for the level, as Simplify does after its collapses.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/progress.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima {

// SimplifyLevels is declared in simplify.h (SimplifyResult holds one).

// OK if the arrays agree with each other and with the counts (same lengths, vertex ids in
// [0, base_vertices), u != v, no vertex removed twice or used after its removal, cells removed
// <= base_cells), else InvalidArgument saying which. ExtractLevel calls it; readers of files
// call it on what they read.
absl::Status ValidateLevels(const SimplifyLevels& levels);

// The mesh at `reduction` (a fraction of base cells to remove, as SimplifyOptions::
// target_reduction): the shortest prefix of the collapses that removes at least
// ceil(reduction * base_cells) cells, applied to `base` in one pass over its cells (each vertex
// through its representative at that level, degenerate cells dropped, vertices and cells
// compacted in base order, cell regions from the labels), then the refit. The same mesh,
// vertex_map and counts Simplify returns for a run that made those collapses. `base` must be
// the mesh the levels were recorded on (its counts are checked). The recorded range is
// (0, deepest_reduction()]; a reduction above it is refused with the range (InvalidArgument)
// unless levels.exhausted, which gives the last level (reached_target false, as a run to it
// would end). 0 means "no target" as in SimplifyOptions: the last level of an exhausted record,
// refused otherwise. Thread count as SimplifyOptions::threads; progress stage "simplify".
absl::StatusOr<SimplifyResult> ExtractLevel(const TetMesh& base, const SimplifyLevels& levels,
                                            double reduction, int threads = 0,
                                            const ProgressFn& progress = nullptr,
                                            const CancelToken* cancel = nullptr);

}  // namespace decima
