#include "core/simplify/levels.h"

#include <algorithm>
#include <cmath>
#include <numeric>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/parallel.h"
#include "core/common/status.h"
#include "core/mesh/tetrahedralize.h"
#include "core/simplify/field_refit.h"
#include "core/simplify/levels_io.h"

namespace decima {

int64_t SimplifyLevels::cells_removed() const {
  return std::accumulate(cells_deleted.begin(), cells_deleted.end(), int64_t{0});
}

double SimplifyLevels::deepest_reduction() const {
  return base_cells > 0 ? double(cells_removed()) / double(base_cells) : 0;
}

absl::Status ValidateLevels(const SimplifyLevels& levels) {
  auto bad = [](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("levels: ", what));
  };
  if (levels.base_vertices < 0 || levels.base_vertices > std::numeric_limits<int32_t>::max() ||
      levels.base_cells < 0) {
    return bad(absl::StrCat("base counts ", levels.base_vertices, " vertices, ", levels.base_cells,
                            " cells: expected 0..2^31-1 vertices, >= 0 cells"));
  }
  if (levels.refit_iterations < 0 || levels.refit_iterations > 1000) {
    return bad(absl::StrCat("refit_iterations = ", levels.refit_iterations, ": expected 0..1000"));
  }
  const size_t n = levels.removed_vertex.size();
  if (levels.survivor.size() != n || levels.cells_deleted.size() != n) {
    return bad(absl::StrCat(n, " removed vertices, ", levels.survivor.size(), " survivors and ",
                            levels.cells_deleted.size(),
                            " deleted-cell counts: expected one of each per collapse"));
  }
  // Each vertex is removed once at most and never used after: a later collapse naming it would
  // not be a simplicial map of the mesh before it.
  std::vector<uint8_t> gone(size_t(levels.base_vertices), 0);
  int64_t removed = 0;
  for (size_t i = 0; i < n; ++i) {
    const int32_t u = levels.removed_vertex[i], v = levels.survivor[i];
    if (u < 0 || u >= levels.base_vertices || v < 0 || v >= levels.base_vertices || u == v) {
      return bad(absl::StrCat("collapse ", i, ": ", u, " -> ", v,
                              ": expected two different vertex ids in [0, ", levels.base_vertices,
                              ")"));
    }
    if (gone[u] || gone[v]) {
      return bad(absl::StrCat("collapse ", i, ": ", u, " -> ", v, ": vertex ", gone[u] ? u : v,
                              " was removed by an earlier collapse"));
    }
    gone[u] = 1;
    removed += levels.cells_deleted[i];
  }
  if (removed > levels.base_cells) {
    return bad(absl::StrCat("the collapses delete ", removed, " cells of ", levels.base_cells));
  }
  return absl::OkStatus();
}

absl::StatusOr<SimplifyResult> ExtractLevel(const TetMesh& base, const SimplifyLevels& levels,
                                            double reduction, int threads,
                                            const ProgressFn& progress, const CancelToken* cancel) {
  DECIMA_RETURN_IF_ERROR(ValidateLevels(levels));
  if (base.vertex_count() != levels.base_vertices || base.tet_count() != levels.base_cells) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "levels: recorded on a mesh of %d vertices and %d cells, given one of %d and %d",
        levels.base_vertices, levels.base_cells, base.vertex_count(), base.tet_count()));
  }
  if (BaseMeshDigest(base) != levels.base_digest) {
    return absl::InvalidArgumentError(
        "levels: recorded on another mesh of the same size (its digest differs): a level record "
        "applies only to the mesh its run simplified");
  }
  const double deepest = levels.deepest_reduction();
  if (!(reduction >= 0 && reduction <= 0.99) || (!levels.exhausted && reduction > deepest)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "levels: reduction %g is outside the recorded range (0, %.4f]%s", reduction,
        levels.exhausted ? 0.99 : deepest,
        levels.exhausted ? "" : " (the run recorded its collapses down to that reduction)"));
  }
  // 0 is Simplify's "no target": as far as the collapses go, which only an exhausted record knows.
  if (reduction == 0 && !levels.exhausted) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "levels: reduction 0 (no target: every collapse there is) is outside the recorded range "
        "(0, %.4f]: the run stopped at its floor",
        deepest));
  }
  threads = ResolveThreads(threads);
  SimplifyResult result;
  result.input_cells = levels.base_cells;
  // The same target as Simplify's, and the shortest prefix that reaches it.
  const bool has_target = reduction > 0;
  const int64_t target = int64_t(std::ceil(reduction * double(levels.base_cells)));
  int64_t k = 0, removed = 0;
  if (has_target) {
    while (k < levels.collapses() && removed < target) removed += levels.cells_deleted[k++];
  } else {
    k = levels.collapses();
    removed = levels.cells_removed();
  }
  result.collapses = k;
  // The representative of every vertex at level k: the survivor of its collapse, followed on
  // (survivors collapse later), with the paths halved as they are walked.
  const int64_t nv = levels.base_vertices, nt = levels.base_cells;
  std::vector<int32_t> rep(nv);
  std::iota(rep.begin(), rep.end(), 0);
  for (int64_t i = 0; i < k; ++i) rep[levels.removed_vertex[i]] = levels.survivor[i];
  auto find = [&](int32_t v) {
    while (rep[v] != v) {
      rep[v] = rep[rep[v]];
      v = rep[v];
    }
    return v;
  };
  for (int64_t v = 0; v < nv; ++v) rep[v] = find(int32_t(v));
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));
  // One pass over the cells: a cell lives iff its four representatives differ (the collapse
  // that made two of them equal deleted it). A vertex lives iff a live cell holds it.
  std::vector<uint8_t> live_cell(nt, 0);
  std::vector<int32_t> index(nv, -1);
  int64_t cells = 0;
  for (int64_t t = 0; t < nt; ++t) {
    const int32_t* c = &base.tets[4 * t];
    const int32_t a = rep[c[0]], b = rep[c[1]], d = rep[c[2]], e = rep[c[3]];
    if (a == b || a == d || a == e || b == d || b == e || d == e) continue;
    live_cell[t] = 1;
    ++cells;
    index[a] = index[b] = index[d] = index[e] = 0;
  }
  if (nt - cells != removed) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "levels: the first %d collapses should delete %d cells of this mesh, they delete %d: "
        "the record is not of this mesh",
        k, removed, nt - cells));
  }
  TetMesh& out = result.mesh;
  int64_t n = 0;
  for (int64_t v = 0; v < nv; ++v) {
    if (index[v] < 0) continue;
    index[v] = int32_t(n++);
  }
  out.positions.resize(3 * n);
  out.scalars.resize(n);
  out.labels.resize(n);
  out.interface_distance.resize(n);
  out.vertex_flags.resize(n);
  for (int64_t v = 0; v < nv; ++v) {
    const int32_t i = index[v];
    if (i < 0) continue;
    for (int j = 0; j < 3; ++j) out.positions[3 * i + j] = base.positions[3 * v + j];
    out.scalars[i] = base.scalars[v];
    out.labels[i] = base.labels[v];
    out.interface_distance[i] = base.interface_distance[v];
    out.vertex_flags[i] = base.vertex_flags[v];
  }
  out.tets.resize(4 * cells);
  out.cell_regions.resize(cells);
  int64_t i = 0;
  for (int64_t t = 0; t < nt; ++t) {
    if (!live_cell[t]) continue;
    const int32_t* c = &base.tets[4 * t];
    for (int j = 0; j < 4; ++j) out.tets[4 * i + j] = index[rep[c[j]]];
    out.cell_regions[i] = CellRegion(base.labels[rep[c[0]]], base.labels[rep[c[1]]],
                                     base.labels[rep[c[2]]], base.labels[rep[c[3]]]);
    ++i;
  }
  result.vertex_map.resize(nv);
  for (int64_t v = 0; v < nv; ++v) result.vertex_map[v] = index[rep[v]];
  live_cell = {};
  index = {};
  rep = {};
  DECIMA_RETURN_IF_ERROR(simplify_internal::RefitAndReport(
      base, result.vertex_map, &out, levels.refit_iterations, threads, cancel, progress));
  result.output_cells = cells;
  result.achieved_reduction = nt > 0 ? 1.0 - double(cells) / double(nt) : 0;
  result.reached_target = has_target && removed >= target;
  result.stop_reason = result.reached_target || !has_target ? StopReason::kTargetReached
                                                            : StopReason::kNoValidCollapse;
  result.passes = 1;
  result.stop_message =
      absl::StrFormat("%s: level of %d of %d recorded collapses: removed %d of %d cells (%.2f%%)",
                      result.reached_target ? "target reached" : "target not reached", k,
                      levels.collapses(), removed, nt, 100 * result.achieved_reduction);
  return result;
}

}  // namespace decima
