#include "core/simplify/stream.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/byte_record.h"
#include "core/common/parallel.h"
#include "core/common/status.h"
#include "core/mesh/tetrahedralize.h"
#include "core/simplify/collapse_engine.h"
#include "core/simplify/field_engine.h"
#include "core/simplify/field_refit.h"

namespace decima {
namespace {

absl::Status Refuse(const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat("simplify (streamed): ", what));
}

// The vertex attributes of `from`'s vertex g appended to `to`.
void AppendVertex(const TetMesh& from, const std::vector<uint8_t>& flags, int64_t g, TetMesh* to) {
  for (int k = 0; k < 3; ++k) to->positions.push_back(from.positions[3 * g + k]);
  to->scalars.push_back(from.scalars[g]);
  to->labels.push_back(from.labels[g]);
  to->interface_distance.push_back(from.interface_distance[g]);
  to->vertex_flags.push_back(flags[g]);
}

// What a streamed run counts across its windows and passes (the pacing in SimplifyStreamed).
struct RunCounters {
  bool measure = true;  // a measuring pass runs
  int measuring_passes = 0;
  double tau = -1;               // the cost threshold
  double band = 0;               // cells removed at costs in (tau / 2, tau] in this measuring pass
  double last_tau = -1;          // the threshold of the last measuring pass
  int64_t measured_removed = 0;  // by the last measuring pass
  int64_t seen_cells = 0;        // original cells of the slabs so far in this pass
  int64_t window_count = 0, peak_window_cells = 0;
  bool stalled = false;  // the last window found no valid collapse left
  // The final pass is the last measuring pass, kept (its count at tau was near enough the target
  // for the last window to make up the rest; see kKeepTolerance).
  bool kept_measuring_pass = false;
  int64_t collapses = 0;
  double max_error = 0;
};

// A label sample (a removed voxel centre) carried to the next window with the carried cell that
// holds it (its index among the carried cells).
struct CarriedSample {
  int32_t vertex;  // grid id
  int32_t cell;
};

// The first field of a window record: its format (2: with RunCounters::kept_measuring_pass; 3:
// with the window's share cost).
constexpr char kWindowRecordTag[] = "decima-stream-window 3";

// Where a measuring window's count reached its share of the target (the cells of its slab times
// the target reduction), or would have: the cost of the collapse that got there or, for a window
// short of it at the threshold, of the queued collapse as many collapses on as it lacked.
struct ShareCost {
  double cost;
  int64_t share;  // the window's share in cells (the estimate's weight)
};

// One window's record (StreamJournal): the run's counters after the window, and what the window
// changed in the run's arrays.
struct WindowRecord {
  int32_t pass = 0;
  int64_t window = 0;
  RunCounters counters;
  std::vector<SimplifyPassStats> pass_stats;   // the window's
  std::vector<int32_t> written;                // cells written out (4 grid ids each)
  std::vector<int32_t> merged;                 // (grid id, survivor) pairs
  std::vector<int32_t> carried;                // the cells carried on, whole
  std::vector<CarriedSample> carried_samples;  // whole
  std::vector<ShareCost> share_cost;           // measuring passes: the window's, if it has one
};

std::string SerializeWindowRecord(const WindowRecord& r, int64_t slabs, int64_t nv) {
  ByteWriter w;
  w.PutString(kWindowRecordTag);
  w.Put(slabs);
  w.Put(nv);
  w.Put(r.pass);
  w.Put(r.window);
  const RunCounters& c = r.counters;
  w.Put<uint8_t>(c.measure);
  w.Put<int32_t>(c.measuring_passes);
  w.Put(c.tau);
  w.Put(c.band);
  w.Put(c.last_tau);
  w.Put(c.measured_removed);
  w.Put(c.seen_cells);
  w.Put(c.window_count);
  w.Put(c.peak_window_cells);
  w.Put<uint8_t>(c.stalled);
  w.Put<uint8_t>(c.kept_measuring_pass);
  w.Put(c.collapses);
  w.Put(c.max_error);
  w.PutVector(r.pass_stats);
  w.PutVector(r.written);
  w.PutVector(r.merged);
  w.PutVector(r.carried);
  w.PutVector(r.carried_samples);
  w.PutVector(r.share_cost);
  return w.Take();
}

// The record of window `window` of pass `pass` of a run over `slabs` slabs and `nv` grid
// vertices, whose window has the grid ids below `window_end`, checked for every index the run
// would follow; InvalidArgument naming the field. (The file's checksum is what proves a record
// intact; this keeps a record that parses from sending the run out of its arrays.)
absl::StatusOr<WindowRecord> ParseWindowRecord(const std::string& bytes, int pass, int64_t window,
                                               int64_t slabs, int64_t nv, int64_t window_end) {
  ByteReader r(bytes, "stream window record");
  WindowRecord w;
  std::string tag;
  int64_t rslabs = 0, rnv = 0;
  DECIMA_RETURN_IF_ERROR(r.GetString("tag", &tag));
  DECIMA_RETURN_IF_ERROR(r.Get("slabs", &rslabs));
  DECIMA_RETURN_IF_ERROR(r.Get("vertices", &rnv));
  DECIMA_RETURN_IF_ERROR(r.Get("pass", &w.pass));
  DECIMA_RETURN_IF_ERROR(r.Get("window", &w.window));
  RunCounters& c = w.counters;
  uint8_t measure = 0, stalled = 0, kept = 0;
  int32_t measuring_passes = 0;
  DECIMA_RETURN_IF_ERROR(r.Get("measure", &measure));
  DECIMA_RETURN_IF_ERROR(r.Get("measuring_passes", &measuring_passes));
  DECIMA_RETURN_IF_ERROR(r.Get("tau", &c.tau));
  DECIMA_RETURN_IF_ERROR(r.Get("band", &c.band));
  DECIMA_RETURN_IF_ERROR(r.Get("last_tau", &c.last_tau));
  DECIMA_RETURN_IF_ERROR(r.Get("measured_removed", &c.measured_removed));
  DECIMA_RETURN_IF_ERROR(r.Get("seen_cells", &c.seen_cells));
  DECIMA_RETURN_IF_ERROR(r.Get("window_count", &c.window_count));
  DECIMA_RETURN_IF_ERROR(r.Get("peak_window_cells", &c.peak_window_cells));
  DECIMA_RETURN_IF_ERROR(r.Get("stalled", &stalled));
  DECIMA_RETURN_IF_ERROR(r.Get("kept_measuring_pass", &kept));
  DECIMA_RETURN_IF_ERROR(r.Get("collapses", &c.collapses));
  DECIMA_RETURN_IF_ERROR(r.Get("max_error", &c.max_error));
  c.measure = measure != 0;
  c.stalled = stalled != 0;
  c.kept_measuring_pass = kept != 0;
  c.measuring_passes = measuring_passes;
  DECIMA_RETURN_IF_ERROR(r.GetVector("pass_stats", &w.pass_stats));
  DECIMA_RETURN_IF_ERROR(r.GetVector("written", &w.written));
  DECIMA_RETURN_IF_ERROR(r.GetVector("merged", &w.merged));
  DECIMA_RETURN_IF_ERROR(r.GetVector("carried", &w.carried));
  DECIMA_RETURN_IF_ERROR(r.GetVector("carried_samples", &w.carried_samples));
  DECIMA_RETURN_IF_ERROR(r.GetVector("share_cost", &w.share_cost));
  DECIMA_RETURN_IF_ERROR(r.Done());
  auto bad = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("stream window record: ", what));
  };
  if (tag != kWindowRecordTag) return bad(absl::StrCat("tag '", tag, "'"));
  if (rslabs != slabs || rnv != nv || w.pass != pass || w.window != window) {
    return bad(absl::StrCat("window ", w.window, " of pass ", w.pass, " of a run of ", rslabs,
                            " slabs over ", rnv, " vertices, expected window ", window, " of pass ",
                            pass, " of ", slabs, " slabs over ", nv));
  }
  auto in_range = [&](const std::vector<int32_t>& ids, size_t stride, size_t at, int64_t lo,
                      int64_t hi) {
    if (ids.size() % stride != 0) return false;
    for (size_t i = at; i < ids.size(); i += stride) {
      if (ids[i] < lo || ids[i] >= hi) return false;
    }
    return true;
  };
  const int64_t ncarried = int64_t(w.carried.size() / 4);
  auto cells_ok = [&](const std::vector<int32_t>& cells) {
    if (cells.size() % 4 != 0 || !in_range(cells, 1, 0, 0, window_end)) return false;
    for (size_t i = 0; i < cells.size(); i += 4) {
      const int32_t* c = &cells[i];
      if (c[0] == c[1] || c[0] == c[2] || c[0] == c[3] || c[1] == c[2] || c[1] == c[3] ||
          c[2] == c[3]) {
        return false;
      }
    }
    return true;
  };
  if (!cells_ok(w.written)) return bad("written: not 4 distinct vertices of the window per cell");
  if (!cells_ok(w.carried) || (window == slabs - 1 && !w.carried.empty())) {
    return bad("carried: not 4 distinct vertices of the window per cell, or carried past the last");
  }
  if (!in_range(w.merged, 2, 0, 0, window_end) || !in_range(w.merged, 2, 1, -1, window_end)) {
    return bad("merged: not (vertex, survivor) pairs of the window");
  }
  for (const CarriedSample& cs : w.carried_samples) {
    if (cs.vertex < 0 || cs.vertex >= window_end || cs.cell < 0 || cs.cell >= ncarried) {
      return bad("carried_samples: not (vertex, carried cell) pairs of the window");
    }
  }
  if (w.share_cost.size() > 1 ||
      (!w.share_cost.empty() && (!(w.share_cost[0].cost >= 0) || w.share_cost[0].share < 0))) {
    return bad("share_cost: at most one (cost >= 0, share >= 0)");
  }
  if (measure > 1 || stalled > 1 || kept > 1 || (kept && measure) || measuring_passes < 0 ||
      measuring_passes > pass || c.seen_cells < 0 || c.window_count < 0 || c.collapses < 0) {
    return bad("counters out of range");
  }
  return w;
}

// The stage's fraction after `slab_fraction` of a pass: the passes done over the passes known to
// run (the one running, and the final one when it is a measuring pass), so that with the usual
// single measuring pass each pass is half the stage and an ETA from the stage's own rate holds;
// the last 5 % is the output and the refit. Another measuring pass lowers this; the caller keeps
// the largest value reported, so the fraction pauses instead of going back.
double PassFraction(bool measure, int measuring_passes, double slab_fraction) {
  const double done = measuring_passes + slab_fraction;
  const double passes = measuring_passes + (measure ? 2.0 : 1.0);
  return 0.95 * done / passes;
}

}  // namespace

absl::StatusOr<SimplifyResult> SimplifyStreamed(const TetMesh& mesh, const SimplifyOptions& options,
                                                int slab_voxels, const ProgressFn& progress,
                                                const CancelToken* cancel, StreamJournal* journal) {
  DECIMA_RETURN_IF_ERROR(ValidateSimplifyOptions(options));
  if (options.policy != SimplifyPolicy::kField) {
    return Refuse(absl::StrCat("policy = ", SimplifyPolicyName(options.policy),
                               ": only the field policy streams"));
  }
  if (options.record_levels_to > 0) {
    return Refuse("record_levels_to > 0: levels are recorded by the in-memory run only");
  }
  if (options.error_tolerance > 0) {
    return Refuse("error_tolerance > 0: a streamed run is paced by target_reduction only");
  }
  if (!(options.target_reduction > 0)) {
    return Refuse("target_reduction = 0: a streamed run needs a target to share among its slabs");
  }
  if (slab_voxels < kMinStreamSlabVoxels) {
    return Refuse(absl::StrCat("stream_slab_voxels = ", slab_voxels, ": at least ",
                               kMinStreamSlabVoxels,
                               " voxel layers per slab (thinner slabs leave a window almost "
                               "nothing it may collapse)"));
  }
  if (!mesh.grid) {
    return Refuse(
        "the mesh records no grid (TetMesh::grid): only Tetrahedralize's grid mesh streams");
  }
  const GridTets& grid = *mesh.grid;
  const int64_t nv = mesh.vertex_count();
  if (grid.vertex_count() != nv || int64_t(mesh.positions.size()) != 3 * nv ||
      int64_t(mesh.labels.size()) != nv || int64_t(mesh.interface_distance.size()) != nv ||
      int64_t(mesh.vertex_flags.size()) != nv) {
    return Refuse(absl::StrCat("the mesh's vertex arrays do not match its grid of ", grid.nx(), "x",
                               grid.ny(), "x", grid.nz(), " vertices"));
  }
  const int64_t cube_layers = grid.nz() - 1;
  if (slab_voxels >= cube_layers) return Simplify(mesh, options, progress, cancel);

  const int threads = ResolveThreads(options.threads);
  const int64_t layer = grid.nx() * grid.ny();
  const int64_t layer_tets = 5 * (grid.nx() - 1) * (grid.ny() - 1);
  const int64_t input_cells = grid.tet_count();

  // What every window shares with the in-memory run: the feature flags of the input grid's cells,
  // the scalar range, the voxel size.
  std::vector<uint8_t> flags;
  simplify_internal::FieldVertexFlags(mesh, options, threads, &flags);
  simplify_internal::FieldWindow window;
  window.flags_complete = true;
  window.scalar_lo = std::numeric_limits<double>::infinity();
  window.scalar_hi = -window.scalar_lo;
  for (float s : mesh.scalars) {
    window.scalar_lo = std::min<double>(window.scalar_lo, s);
    window.scalar_hi = std::max<double>(window.scalar_hi, s);
  }
  SimplifyOptions wopt = options;
  if (wopt.voxel_size_mm <= 0) {
    // The in-memory run's estimate, cbrt(5 * mean cell volume), is the voxel volume's cube root
    // on the grid; a window's carried cells would bias it.
    Eigen::Vector3d p0 = mesh.Position(0),
                    e[3] = {mesh.Position(1) - p0, mesh.Position(grid.nx()) - p0,
                            mesh.Position(layer) - p0};
    wopt.voxel_size_mm = std::cbrt(std::abs(e[0].dot(e[1].cross(e[2]))));
  }
  const bool free_interfaces = options.interfaces == InterfaceMode::kFree;

  std::vector<int32_t> carried;  // 4 grid vertex ids per carried cell
  std::vector<CarriedSample> carried_samples;
  std::vector<int32_t> out_cells;            // written out, grid vertex ids
  std::vector<uint8_t> finalized(nv, 0);     // a vertex of a written-out cell
  std::vector<int32_t> merged_into(nv, -1);  // last window's survivor, grid id
  SimplifyResult result;
  result.input_cells = input_cells;
  const int64_t target = int64_t(std::ceil(options.target_reduction * double(input_cells)));
  // Pacing (README "Streamed simplification"): one cost threshold for every window, as the
  // in-memory run's single queue ends with about every collapse below some cost done.
  // Measuring passes find it: in the first, window 0 removes its share of the target by cells and
  // the cost of its last collapse is the first threshold; in every measuring pass every other
  // window (the last one too) collapses while the queue's cheapest cost is at most the threshold.
  // A Newton step on the cells the pass removed gives the next threshold (below). The final pass
  // collapses up to it in every window but the last, which removes exactly what is left.
  // The counters a window record carries, under the names the loop uses.
  RunCounters run;
  bool& measure = run.measure;
  int& measuring_passes = run.measuring_passes;
  double &tau = run.tau, &band = run.band, &last_tau = run.last_tau;
  int64_t &measured_removed = run.measured_removed, &seen_cells = run.seen_cells;
  int64_t &window_count = run.window_count, &peak_window_cells = run.peak_window_cells;
  bool& stalled = run.stalled;
  constexpr int kMaxMeasuringPasses = 3;
  constexpr double kMeasureTolerance = 0.03;
  // A measuring pass is kept as the final one when, at its last window, the cells left to remove
  // differ from what that window removes at tau by at most this fraction of it: the last window
  // then removes exactly what is left, as in a final pass, and another pass over every window is
  // saved (the passes are most of the stage's time). The share is small because what the last
  // window makes up alone costs fidelity (README "Pacing").
  constexpr double kKeepTolerance = 0.03;
  std::vector<int32_t> local, globals;
  std::vector<uint8_t> frozen;
  std::vector<int32_t> sample_cell, sample_home;
  std::vector<std::pair<float, int32_t>> cost_log;
  std::vector<float> queued_costs;
  std::vector<ShareCost> share_costs;  // the running pass's windows'
  // Slabs of equal depth (at most slab_voxels): a thin last slab would have to make up the
  // windows' shortfall on its own.
  const int64_t slabs = (cube_layers + slab_voxels - 1) / slab_voxels;
  double reported = 0;  // the largest fraction reported

  // What an earlier run saved: the records of the latest pass whose first window is intact, in
  // order, up to the first missing or damaged one. The passes run from start_pass, window start_k.
  int start_pass = 0;
  int64_t start_k = 0;
  std::string resume_note;
  // A window's record applied to the run's arrays and counters: how a window simplified now and
  // one read back both end, so the state a later window reads cannot differ between them.
  auto apply = [&](WindowRecord&& rec) {
    for (int32_t g : rec.written) finalized[g] = 1;
    out_cells.insert(out_cells.end(), rec.written.begin(), rec.written.end());
    for (size_t i = 0; i < rec.merged.size(); i += 2)
      merged_into[rec.merged[i]] = rec.merged[i + 1];
    carried = std::move(rec.carried);
    carried_samples = std::move(rec.carried_samples);
    for (const SimplifyPassStats& st : rec.pass_stats) result.pass_stats.push_back(st);
    share_costs.insert(share_costs.end(), rec.share_cost.begin(), rec.share_cost.end());
    run = rec.counters;
  };
  if (journal) journal->windows_per_pass = slabs;
  if (journal && journal->load) {
    for (int p = kMaxMeasuringPasses; p >= 0 && start_k == 0; --p) {
      for (int64_t k = 0; k < slabs; ++k) {
        const std::optional<std::string> bytes = journal->load(p, k);
        if (!bytes) break;
        const int64_t window_end = (k + 1) * cube_layers / slabs * layer + layer;
        absl::StatusOr<WindowRecord> rec = ParseWindowRecord(*bytes, p, k, slabs, nv, window_end);
        if (!rec.ok()) {
          resume_note = absl::StrCat(" (", rec.status().message(), ": simplified again)");
          break;
        }
        apply(*std::move(rec));
        start_pass = p;
        start_k = k + 1;
      }
    }
    journal->resumed_windows = start_k;
    if (start_k > 0) {
      reported = PassFraction(measure, measuring_passes, double(start_k) / double(slabs));
      Report(progress,
             {"simplify",
              reported,
              absl::StrFormat("resumed after slab %d of %d of the %s%s", start_k, slabs,
                              measure ? absl::StrCat("measuring pass ", measuring_passes + 1)
                                      : std::string("final pass"),
                              resume_note),
              {{"slab", double(start_k)},
               {"slabs", double(slabs)},
               {"resumed_windows", double(start_k)}}});
    }
  }

  for (int pass = start_pass;; ++pass) {
    if (pass > start_pass) {
      carried.clear();
      carried_samples.clear();
      out_cells.clear();
      std::fill(finalized.begin(), finalized.end(), 0);
      std::fill(merged_into.begin(), merged_into.end(), -1);
      seen_cells = window_count = peak_window_cells = 0;
      stalled = false;
      run.collapses = 0;
      run.max_error = 0;
      result.pass_stats.clear();
      share_costs.clear();
      band = 0;
    }
    for (int64_t k = pass == start_pass ? start_k : 0; k < slabs; ++k) {
      DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));
      const int64_t z0 = k * cube_layers / slabs, z1 = (k + 1) * cube_layers / slabs;
      const bool last = z1 == cube_layers;
      const int64_t ncarried = int64_t(carried.size() / 4);
      const int64_t removed_before = seen_cells - int64_t(out_cells.size() / 4) - ncarried;
      seen_cells += (z1 - z0) * layer_tets;

      // The window's vertices: those of its cells and its carried samples, numbered by grid id
      // (so the window keeps the grid's z-major order the engine's slabs and caches expect).
      int64_t lo_id = z0 * layer;
      for (int32_t g : carried) lo_id = std::min<int64_t>(lo_id, g);
      for (const CarriedSample& s : carried_samples) lo_id = std::min<int64_t>(lo_id, s.vertex);
      const int64_t hi_id = (z1 + 1) * layer;  // past the top plane
      local.assign(hi_id - lo_id, -1);
      for (int32_t g : carried) local[g - lo_id] = 0;
      for (const CarriedSample& s : carried_samples) local[s.vertex - lo_id] = 0;
      for (int64_t g = z0 * layer; g < hi_id; ++g) local[g - lo_id] = 0;
      globals.clear();
      for (int64_t i = 0; i < hi_id - lo_id; ++i) {
        if (local[i] < 0) continue;
        local[i] = int32_t(globals.size());
        globals.push_back(int32_t(lo_id + i));
      }
      const int64_t wnv = int64_t(globals.size());
      TetMesh wm;
      wm.positions.reserve(3 * wnv);
      for (int32_t g : globals) AppendVertex(mesh, flags, g, &wm);
      const int64_t wnt = ncarried + (z1 - z0) * layer_tets;
      peak_window_cells = std::max(peak_window_cells, wnt);
      wm.tets.resize(4 * wnt);
      wm.cell_regions.resize(wnt);
      for (int64_t i = 0; i < 4 * ncarried; ++i) wm.tets[i] = local[carried[i] - lo_id];
      grid.ForEachCell(z0 * layer_tets, z1 * layer_tets, [&](int64_t t, const int32_t* c) {
        const int64_t i = ncarried + t - z0 * layer_tets;
        for (int k = 0; k < 4; ++k) wm.tets[4 * i + k] = local[c[k] - lo_id];
      });
      for (int64_t i = 0; i < wnt; ++i) {
        const int32_t* c = &wm.tets[4 * i];
        wm.cell_regions[i] =
            CellRegion(wm.labels[c[0]], wm.labels[c[1]], wm.labels[c[2]], wm.labels[c[3]]);
      }
      std::vector<int32_t>().swap(carried);
      frozen.assign(wnv, 0);
      for (int64_t v = 0; v < wnv; ++v) {
        const int64_t g = globals[v];
        frozen[v] = finalized[g] || (!last && g / layer == z1);
      }
      sample_cell.assign(wnv, -1);
      for (const auto& [g, c] : carried_samples) sample_cell[local[g - lo_id]] = c;
      std::vector<CarriedSample>().swap(carried_samples);

      window.frozen = frozen.data();
      window.sample_cell = free_interfaces ? sample_cell.data() : nullptr;
      window.sample_home = free_interfaces ? &sample_home : nullptr;
      // The window's pacing (see above): the first measuring pass's first window by cells, every
      // other window of either pass up to the threshold, the final pass's last window exactly what
      // is left (with the engine's parallel rounds).
      cost_log.clear();
      window.cost_log = measure ? &cost_log : nullptr;
      const bool at_threshold = measure && !(pass == 0 && k == 0);
      window.queued_costs = at_threshold ? &queued_costs : nullptr;
      window.stop_cost = last && !measure ? -1.0 : tau;
      int64_t window_target = std::clamp<int64_t>(target - removed_before, 0, wnt);
      if (measure && pass == 0 && k == 0) {
        window.stop_cost = std::numeric_limits<double>::infinity();
        window_target = std::clamp<int64_t>(
            int64_t(std::ceil(options.target_reduction * double(seen_cells))), 0, wnt);
      } else if (measure) {
        window_target = wnt;
      }
      SimplifyResult wr;
      SimplifyOptions o = wopt;
      o.refit_iterations = 0;
      DECIMA_RETURN_IF_ERROR(simplify_internal::RunFieldSimplifyWindow(
          wm, o, threads, window_target, window, nullptr, cancel, &wr));
      std::vector<ShareCost> share_cost;
      if (at_threshold) {
        // The window's share cost (ShareCost): from its collapses when it got there, else from
        // its queue, at the cells per collapse it saw. A window with nothing queued has none (no
        // threshold would take it further).
        const int64_t share =
            int64_t(std::ceil(options.target_reduction * double((z1 - z0) * layer_tets)));
        int64_t removed = 0;
        double cost = -1;
        for (const auto& [c, d] : cost_log) {
          removed += d;
          if (removed >= share) {
            cost = c;
            break;
          }
        }
        if (cost < 0 && !queued_costs.empty()) {
          const double per_collapse =
              cost_log.empty() ? 1.0 : std::max(1.0, double(removed) / double(cost_log.size()));
          const size_t n = std::min(queued_costs.size() - 1,
                                    size_t(std::ceil(double(share - removed) / per_collapse)));
          std::nth_element(queued_costs.begin(), queued_costs.begin() + n, queued_costs.end());
          cost = queued_costs[n];
        }
        if (cost >= 0) share_cost.push_back({cost, share});
      }
      if (measure && last) {
        // The pass's count at tau, and what the last window would have to make up to hit the
        // target instead: small enough, and the window is run again to remove exactly what is
        // left, which makes this pass the final one (when the window gets there).
        const int64_t at_tau = wnt - wr.mesh.tet_count();
        const int64_t left = target - removed_before;
        if (left >= 0 && double(std::abs(left - at_tau)) <= kKeepTolerance * double(at_tau)) {
          SimplifyResult exact;
          std::vector<int32_t> exact_home;
          simplify_internal::FieldWindow w = window;
          w.cost_log = nullptr;
          w.queued_costs = nullptr;
          w.stop_cost = -1.0;
          if (free_interfaces) w.sample_home = &exact_home;
          DECIMA_RETURN_IF_ERROR(simplify_internal::RunFieldSimplifyWindow(
              wm, o, threads, std::min<int64_t>(left, wnt), w, nullptr, cancel, &exact));
          if (exact.stop_reason == StopReason::kTargetReached) {
            sample_home.swap(exact_home);
            last_tau = tau;
            measured_removed = removed_before + at_tau;
            measure = false;
            run.kept_measuring_pass = true;
            wr = std::move(exact);
          }
        }
      }
      ++window_count;
      run.collapses += wr.collapses;
      run.max_error = std::max(run.max_error, wr.max_error);
      stalled = wr.stop_reason != StopReason::kTargetReached;

      // Output vertex -> grid id: a survivor is copied by Finish with its own position, and voxel
      // centres are distinct points.
      const int64_t onv = wr.mesh.vertex_count();
      std::vector<int32_t> out_global(onv, -1);
      for (int64_t v = 0; v < wnv; ++v) {
        const int32_t o = wr.vertex_map[v];
        if (o < 0 || out_global[o] >= 0) continue;
        if (wr.mesh.positions[3 * o] == wm.positions[3 * v] &&
            wr.mesh.positions[3 * o + 1] == wm.positions[3 * v + 1] &&
            wr.mesh.positions[3 * o + 2] == wm.positions[3 * v + 2]) {
          out_global[o] = globals[v];
        }
      }
      // The window's record (applied below, and saved): its survivors (a measuring pass's make
      // the output when the pass is kept, above), the cells it writes out and those it carries on.
      WindowRecord record;
      for (int64_t v = 0; v < wnv; ++v) {
        const int32_t o = wr.vertex_map[v];
        if (o < 0) continue;
        record.merged.push_back(globals[v]);
        record.merged.push_back(out_global[o]);
      }
      // Written out: the cells wholly at or below the middle of the slab (all of them at the end).
      const int64_t cut = last ? grid.nz() : z0 + (z1 - z0 + 1) / 2;
      const int64_t ont = wr.mesh.tet_count();
      std::vector<int32_t> carried_index(ont, -1);
      for (int64_t c = 0; c < ont; ++c) {
        int32_t t[4];
        int64_t top = 0;
        for (int k = 0; k < 4; ++k) {
          t[k] = out_global[wr.mesh.tets[4 * c + k]];
          top = std::max<int64_t>(top, t[k] / layer);
        }
        if (top <= cut) {
          record.written.insert(record.written.end(), t, t + 4);
        } else {
          carried_index[c] = int32_t(record.carried.size() / 4);
          record.carried.insert(record.carried.end(), t, t + 4);
        }
      }
      if (free_interfaces) {
        for (int64_t v = 0; v < wnv; ++v) {
          const int32_t h = sample_home[v];
          if (h >= 0 && carried_index[h] >= 0)
            record.carried_samples.push_back({globals[v], carried_index[h]});
        }
      }
      if (measure) {
        if (pass == 0 && k == 0) tau = cost_log.empty() ? 0 : cost_log.back().first;
        for (const auto& [c, d] : cost_log) {
          if (c > tau / 2 && c <= tau) band += d;
        }
      }
      record.pass = pass;
      record.window = k;
      record.counters = run;
      record.pass_stats = std::move(wr.pass_stats);
      record.share_cost = std::move(share_cost);
      if (journal && journal->save)
        journal->save(pass, k, SerializeWindowRecord(record, slabs, nv));
      apply(std::move(record));
      reported = std::max(
          reported, PassFraction(measure, measuring_passes, double(z1) / double(cube_layers)));
      Report(progress,
             {"simplify",
              reported,
              absl::StrFormat("slab %d of %d, %s (z %d..%d, threshold %g): %d cells, %d removed, "
                              "%d written out, %d carried",
                              window_count, slabs,
                              measure ? absl::StrCat("measuring pass ", measuring_passes + 1)
                              : run.kept_measuring_pass
                                  ? absl::StrCat("measuring pass ", measuring_passes + 1,
                                                 " kept as the final pass")
                                  : std::string("final pass"),
                              z0, z1, tau, wnt, wnt - ont, int64_t(out_cells.size() / 4),
                              int64_t(carried.size() / 4)),
              {{"pass", double(window_count)},
               {"slab", double(window_count)},
               {"slabs", double(slabs)},
               {"measuring_pass", measure ? double(measuring_passes + 1) : 0.0},
               {"kept_measuring_pass", run.kept_measuring_pass ? 1.0 : 0.0},
               {"cells_removed",
                double(seen_cells - int64_t(out_cells.size() / 4) - int64_t(carried.size() / 4))},
               {"error", wr.max_error}}});
    }
    if (!measure) break;
    // A Newton step on the removed cells as a function of ln tau, at most a factor of 4 a pass
    // (the count is flat in tau: a 1.5x threshold moves it by ~2 % on the CT head at 80 %), or of
    // 64 while the count misses the target by more than 10 % (a first threshold far off). The
    // slope: from the second measuring pass on, the secant through the last two passes; before,
    // the cells that the collapses in (tau / 2, tau] removed. Another measuring pass while the
    // count misses the target by more than kMeasureTolerance.
    const int64_t measured =
        seen_cells - int64_t(out_cells.size() / 4) - int64_t(carried.size() / 4);
    double slope = band / std::log(2.0);
    if (measuring_passes > 0 && tau != last_tau && tau > 0 && last_tau > 0) {
      const double secant = double(measured - measured_removed) / std::log(tau / last_tau);
      if (secant > 0) slope = secant;
    }
    const double step = slope > 0 ? (double(target) - double(measured)) / slope : 0;
    last_tau = tau;
    // Far from the target (more than 10 %), the count can be flat over decades of tau (ch2better:
    // its empty slabs give 83 % of the target at 8e-5, the rest needs ~10^6 times that), so no
    // clamped Newton step gets there: the next threshold is then the median of the windows'
    // share costs weighted by their shares, when it lies on the side the miss points to.
    const bool far = std::abs(double(measured - target)) > 0.1 * double(target);
    double median_share_cost = -1;
    if (far && !share_costs.empty()) {
      std::vector<ShareCost> sorted = share_costs;
      std::sort(sorted.begin(), sorted.end(),
                [](const ShareCost& a, const ShareCost& b) { return a.cost < b.cost; });
      int64_t total = 0, acc = 0;
      for (const ShareCost& sc : sorted) total += sc.share;
      for (const ShareCost& sc : sorted) {
        acc += sc.share;
        if (2 * acc >= total) {
          median_share_cost = sc.cost;
          break;
        }
      }
    }
    if (far && ((measured < target && median_share_cost > tau) ||
                (measured > target && median_share_cost >= 0 && median_share_cost < tau))) {
      tau = median_share_cost;
    } else {
      const double max_step = std::log(far ? 64.0 : 4.0);
      tau *= std::exp(std::clamp(step, -max_step, max_step));
    }
    measured_removed = measured;
    ++measuring_passes;
    measure = measuring_passes < kMaxMeasuringPasses &&
              std::abs(double(measured - target)) > kMeasureTolerance * double(target);
    Report(progress,
           {"simplify",
            reported,
            absl::StrFormat("measuring pass %d removed %d cells at threshold %g, %.1f%% of the "
                            "target; %s at threshold %g",
                            measuring_passes, measured, last_tau,
                            100.0 * double(measured) / double(std::max<int64_t>(1, target)),
                            measure ? "another measuring pass" : "the final pass", tau),
            {{"measuring_pass", double(measuring_passes)},
             {"measured_cells_removed", double(measured)},
             {"threshold", tau}}});
  }

  // The output: the written-out cells on the grid vertices they use, in grid order. What only the
  // windows needed goes first (the output's cells are renumbered in place).
  std::vector<uint8_t>().swap(finalized);
  std::vector<uint8_t>().swap(flags);
  for (auto* v : {&local, &globals, &sample_cell, &sample_home}) std::vector<int32_t>().swap(*v);
  std::vector<uint8_t>().swap(frozen);
  out_cells.shrink_to_fit();
  std::vector<int32_t> index(nv, -1);
  for (int32_t g : out_cells) index[g] = 0;
  TetMesh& out = result.mesh;
  int32_t n = 0;
  for (int64_t g = 0; g < nv; ++g) {
    if (index[g] < 0) continue;
    index[g] = n++;
    AppendVertex(mesh, mesh.vertex_flags, g, &out);
  }
  out.tets = std::move(out_cells);
  for (int32_t& v : out.tets) v = index[v];
  const int64_t ont = out.tet_count();
  out.cell_regions.resize(ont);
  for (int64_t c = 0; c < ont; ++c) {
    const int32_t* t = &out.tets[4 * c];
    out.cell_regions[c] =
        CellRegion(out.labels[t[0]], out.labels[t[1]], out.labels[t[2]], out.labels[t[3]]);
  }
  result.vertex_map.resize(nv);
  for (int64_t g = 0; g < nv; ++g) {
    // A vertex is merged at most once a window, so its chain has at most `slabs` links; a longer
    // one is a cycle, which only a damaged record could make.
    int32_t r = int32_t(g);
    int64_t links = 0;
    while (merged_into[r] >= 0 && merged_into[r] != r && links++ <= slabs) r = merged_into[r];
    if (links > slabs) {
      return absl::InternalError(absl::StrCat(
          "simplify (streamed): the survivors of grid vertex ", g,
          " form a cycle (a damaged slab record?); the stage must run again without its records"));
    }
    result.vertex_map[g] = index[r];
  }
  std::vector<int32_t>().swap(index);  // the refit needs the room
  std::vector<int32_t>().swap(merged_into);
  DECIMA_RETURN_IF_ERROR(simplify_internal::RefitAndReport(
      mesh, result.vertex_map, &out, options.refit_iterations, threads, cancel, progress));
  result.collapses = run.collapses;
  result.max_error = run.max_error;
  result.output_cells = ont;
  result.achieved_reduction = 1.0 - double(ont) / double(input_cells);
  const int64_t removed = input_cells - ont;
  result.reached_target = removed >= target;
  result.passes = int(window_count);
  result.stop_reason =
      result.reached_target ? StopReason::kTargetReached : StopReason::kNoValidCollapse;
  result.stop_message = absl::StrFormat(
      "%s: removed %d of %d cells (%.2f%%) in %d windows of %d voxel layers (largest %d cells), "
      "cost threshold %g (%s)%s",
      result.reached_target ? "target reached" : "target not reached", removed, input_cells,
      100 * result.achieved_reduction, window_count, slab_voxels, peak_window_cells, tau,
      run.kept_measuring_pass
          ? absl::StrFormat("%d measuring passes, the last kept as the final pass: %d removed at "
                            "the threshold, the last window made up the rest",
                            measuring_passes + 1, measured_removed)
          : absl::StrFormat("%d measuring passes, the last removed %d", measuring_passes,
                            measured_removed),
      stalled ? "; the last window found no valid collapse left" : "");
  return result;
}

}  // namespace decima
