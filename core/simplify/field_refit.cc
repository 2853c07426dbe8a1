#include "core/simplify/field_refit.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <limits>
#include <optional>
#include <vector>

#include "absl/strings/str_format.h"
#include "core/common/parallel.h"
#include "core/common/status.h"

namespace decima::simplify_internal {
namespace {

// A sample's row of A: the vertices of the simplified cell it lies in and its barycentric
// weights there, in units of 1 / kWeightUnit, summing to kWeightUnit exactly. vertex[0] == -1:
// outside every cell. 24 bytes (issue 30: the rows are the refit's peak on a clinical scan):
// 16-bit weights are within 7.6e-6 of the cell's coordinates, a row's value within 3e-5 of the
// value range, far below the fit's own residual (README "Refit"). Storing the cell id instead of
// its vertices would save 12 bytes more, but the cells are not in sample order: the CGLS passes
// then miss the cache on every row and the refit took twice the time on Colin27.
constexpr double kWeightUnit = 65535.0;
struct Row {
  std::array<int32_t, 4> vertex{-1, -1, -1, -1};
  std::array<uint16_t, 4> w{};
  bool located() const { return vertex[0] >= 0; }
};

Row AtVertex(int32_t m) { return Row{{m, m, m, m}, {uint16_t(kWeightUnit), 0, 0, 0}}; }

// The row of a sample in cell t of `mesh` with barycentric weights w (each >= -1e-6, summing to
// 1): the weights rounded to units, the first one taking up the rounding so that they sum to the
// unit exactly (a constant field stays exact); taken from the largest when it would go negative.
Row InCell(const TetMesh& mesh, int64_t t, const std::array<float, 4>& w) {
  const int32_t* c = &mesh.tets[4 * t];
  Row row{{c[0], c[1], c[2], c[3]}, {}};
  int32_t q[4], sum = 0;
  for (int k = 1; k < 4; ++k) {
    q[k] = int32_t(std::lround(std::clamp(double(w[k]), 0.0, 1.0) * kWeightUnit));
    sum += q[k];
  }
  q[0] = int32_t(kWeightUnit) - sum;
  if (q[0] < 0) {
    int32_t* largest = std::max_element(q + 1, q + 4);
    *largest += q[0];
    q[0] = 0;
  }
  for (int k = 0; k < 4; ++k) row.w[k] = uint16_t(q[k]);
  return row;
}

// The CGLS sums: in fixed blocks (core/common BlockSum), so the thread count changes nothing.
template <typename F>
double BlockSum(int64_t n, int threads, F&& f) {
  return decima::BlockSum(n, threads, 16384, std::forward<F>(f));
}

// The barycentric coordinates of x in cell t of `mesh`, times the cell's determinant (b[k] for
// its k-th vertex); returns the determinant (not positive: a degenerate or inverted cell).
double ScaledCoordinates(const TetMesh& mesh, int64_t t, const Eigen::Vector3d& x, double b[4]) {
  const int32_t* c = &mesh.tets[4 * t];
  const Eigen::Vector3d p0 = mesh.Position(c[0]);
  const Eigen::Vector3d e0 = mesh.Position(c[1]) - p0, e1 = mesh.Position(c[2]) - p0,
                        e2 = mesh.Position(c[3]) - p0, d = x - p0;
  // The rows of the inverse of [e0 e1 e2] are these cross products over the determinant.
  const Eigen::Vector3d r0 = e1.cross(e2), r1 = e2.cross(e0), r2 = e0.cross(e1);
  const double det = e0.dot(r0);
  b[1] = r0.dot(d);
  b[2] = r1.dot(d);
  b[3] = r2.dot(d);
  b[0] = det - b[1] - b[2] - b[3];
  return det;
}

// Barycentric weights of x in cell t of `mesh` if the cell holds x (to 1e-6), else nullopt.
std::optional<std::array<float, 4>> WeightsIn(const TetMesh& mesh, int64_t t,
                                              const Eigen::Vector3d& x) {
  double b[4];
  const double det = ScaledCoordinates(mesh, t, x, b);
  if (!(det > 0)) return std::nullopt;
  const double eps = 1e-6 * det;
  if (b[1] < -eps || b[2] < -eps || b[3] < -eps || b[0] < -eps) return std::nullopt;
  return std::array<float, 4>{float(b[0] / det), float(b[1] / det), float(b[2] / det),
                              float(b[3] / det)};
}

// A cell of `mesh` that holds x, found by walking from cell t through the face x lies furthest
// beyond into the cell on its other side; -1 if the walk leaves the mesh or takes more than
// kMaxSteps (it can circle in a mesh that is not Delaunay).
int32_t Walk(const TetMesh& mesh, const VertexTetAdjacency& star, int32_t t,
             const Eigen::Vector3d& x) {
  constexpr int kMaxSteps = 64;
  for (int step = 0; step < kMaxSteps; ++step) {
    double b[4];
    const double det = ScaledCoordinates(mesh, t, x, b);
    if (!(det > 0)) return -1;
    const int k = int(std::min_element(b, b + 4) - b);
    if (b[k] >= -1e-6 * det) return t;
    const int32_t* c = &mesh.tets[4 * int64_t(t)];
    const int64_t next =
        TetAcrossFace(mesh, star, t, c[(k + 1) % 4], c[(k + 2) % 4], c[(k + 3) % 4]);
    if (next < 0) return -1;
    t = int32_t(next);
  }
  return -1;
}

// Locates every original vertex in `mesh`, where `vertex_map` (may be empty) says which vertex
// of `mesh` each became. A vertex that survived where it was is that vertex, weight 1 (about
// half the samples). A collapsed one nearly always lies in a cell around the vertex it became
// (a valid collapse keeps the union of the two stars; later collapses nearby can move that
// boundary): those cells are tried first, in id order, and the first that holds the sample
// keeps it. For the rest a walk from there finds a cell that holds the sample (README
// "Refit"). What the walk does not find is bucketed on a uniform grid over the bounding box;
// each cell, in id order, tests the samples of the buckets its bounding box overlaps, and the
// first cell that contains a sample keeps it.
std::vector<Row> LocateSamples(const TetMesh& original, const TetMesh& mesh,
                               const std::vector<int32_t>& vertex_map, int threads,
                               const CancelToken* cancel, absl::Status* status, int64_t* walked,
                               int64_t* searched) {
  const int64_t n = original.vertex_count();
  std::vector<Row> rows(n);
  if (n == 0 || mesh.tet_count() == 0) return rows;
  std::atomic<int64_t> walks{0};
  if (int64_t(vertex_map.size()) == n) {
    const VertexTetAdjacency star = BuildVertexTetAdjacency(mesh, threads);
    ParallelFor(n, threads, 4096, [&](int64_t v0, int64_t v1) {
      for (int64_t v = v0; v < v1; ++v) {
        const int32_t m = vertex_map[v];
        if (m < 0 || m >= mesh.vertex_count()) continue;
        const float* p = &original.positions[3 * v];
        const float* q = &mesh.positions[3 * int64_t(m)];
        if (p[0] == q[0] && p[1] == q[1] && p[2] == q[2]) {
          rows[v] = AtVertex(m);
          continue;
        }
        const Eigen::Vector3d x = original.Position(v);
        for (int64_t i = star.offsets[m]; i < star.offsets[m + 1]; ++i) {
          const int32_t t = star.tet_ids[i];
          if (auto w = WeightsIn(mesh, t, x)) {
            rows[v] = InCell(mesh, t, *w);
            break;
          }
        }
        if (rows[v].located() || star.offsets[m] == star.offsets[m + 1]) continue;
        // Later collapses nearby moved the boundary of m's cells past the sample: walk there
        // from m's first cell. Where the sample lies on the boundary of the cell the walk
        // ends in, the lowest id among the cells around that cell's vertices that hold it.
        const int32_t t = Walk(mesh, star, star.tet_ids[star.offsets[m]], x);
        if (t < 0) continue;  // left to the whole-mesh search
        walks.fetch_add(1, std::memory_order_relaxed);
        int32_t found = t;
        std::array<float, 4> found_w = *WeightsIn(mesh, t, x);  // Walk checked that t holds x
        if (*std::min_element(found_w.begin(), found_w.end()) < 1e-4f) {
          const int32_t* c = &mesh.tets[4 * int64_t(t)];
          for (int k = 0; k < 4; ++k) {
            for (int64_t j = star.offsets[c[k]]; j < star.offsets[c[k] + 1]; ++j) {
              const int32_t other = star.tet_ids[j];
              if (other >= found) break;  // rows are in id order
              if (auto w = WeightsIn(mesh, other, x)) {
                found = other;
                found_w = *w;
              }
            }
          }
        }
        rows[v] = InCell(mesh, found, found_w);
      }
    });
  }
  *walked = walks.load();
  if (cancel != nullptr && cancel->cancelled()) {
    *status = absl::CancelledError("simplify: cancelled");
    return rows;
  }
  std::vector<int32_t> search;
  for (int64_t v = 0; v < n; ++v) {
    if (!rows[v].located()) search.push_back(int32_t(v));
  }
  const int64_t ns = int64_t(search.size());
  *searched = ns;
  if (ns == 0) return rows;
  Eigen::Vector3d lo = original.Position(search[0]), hi = lo;
  for (int32_t v : search) {
    lo = lo.cwiseMin(original.Position(v));
    hi = hi.cwiseMax(original.Position(v));
  }
  // About two samples per bucket.
  const Eigen::Vector3d extent = (hi - lo).cwiseMax(1e-9);
  const double cell_size = std::cbrt(extent.prod() / std::max<double>(1, double(ns) / 2));
  std::array<int64_t, 3> dims;
  for (int k = 0; k < 3; ++k) {
    dims[k] = std::clamp<int64_t>(int64_t(std::ceil(extent[k] / cell_size)), 1, 4096);
  }
  auto bucket_of = [&](const Eigen::Vector3d& p, int k) {
    return std::clamp<int64_t>(int64_t((p[k] - lo[k]) / extent[k] * double(dims[k])), 0,
                               dims[k] - 1);
  };
  const int64_t buckets = dims[0] * dims[1] * dims[2];
  std::vector<int64_t> start(buckets + 1, 0);
  std::vector<int64_t> bucket(ns);
  for (int64_t i = 0; i < ns; ++i) {
    const Eigen::Vector3d p = original.Position(search[i]);
    bucket[i] = bucket_of(p, 0) + dims[0] * (bucket_of(p, 1) + dims[1] * bucket_of(p, 2));
    ++start[bucket[i] + 1];
  }
  for (int64_t b = 0; b < buckets; ++b) start[b + 1] += start[b];
  std::vector<int32_t> members(ns);
  {
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t i = 0; i < ns; ++i) members[fill[bucket[i]]++] = int32_t(i);  // index into search
  }
  // Cells test in parallel; each sample keeps the lowest containing cell id (an atomic
  // minimum), so the result does not depend on the thread count.
  std::vector<std::atomic<int32_t>> owner(ns);  // per entry of `search`
  for (auto& o : owner) o.store(std::numeric_limits<int32_t>::max(), std::memory_order_relaxed);
  std::atomic<bool> cancelled{false};
  ParallelFor(mesh.tet_count(), threads, 4096, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      if ((t & 0xffff) == 0 && cancel != nullptr && cancel->cancelled()) {
        cancelled = true;
        return;
      }
      const int32_t* c = &mesh.tets[4 * t];
      Eigen::Vector3d blo = mesh.Position(c[0]), bhi = blo;
      for (int k = 1; k < 4; ++k) {
        blo = blo.cwiseMin(mesh.Position(c[k]));
        bhi = bhi.cwiseMax(mesh.Position(c[k]));
      }
      for (int64_t bz = bucket_of(blo, 2); bz <= bucket_of(bhi, 2); ++bz) {
        for (int64_t by = bucket_of(blo, 1); by <= bucket_of(bhi, 1); ++by) {
          for (int64_t bx = bucket_of(blo, 0); bx <= bucket_of(bhi, 0); ++bx) {
            const int64_t b = bx + dims[0] * (by + dims[1] * bz);
            for (int64_t i = start[b]; i < start[b + 1]; ++i) {
              const int32_t j = members[i];
              if (owner[j].load(std::memory_order_relaxed) < t) continue;
              if (!WeightsIn(mesh, t, original.Position(search[j]))) continue;
              int32_t seen = owner[j].load(std::memory_order_relaxed);
              while (t < seen && !owner[j].compare_exchange_weak(seen, int32_t(t))) {
              }
            }
          }
        }
      }
    }
  });
  if (cancelled) {
    *status = absl::CancelledError("simplify: cancelled");
    return rows;
  }
  // Weights in the winning cell.
  ParallelFor(ns, threads, 4096, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const int32_t v = search[i];
      const int32_t t = owner[i].load(std::memory_order_relaxed);
      if (t == std::numeric_limits<int32_t>::max()) continue;
      rows[v] = InCell(mesh, t, *WeightsIn(mesh, t, original.Position(v)));  // it held v
    }
  });
  return rows;
}

}  // namespace

absl::Status RefitValues(const TetMesh& original, const std::vector<int32_t>& vertex_map,
                         TetMesh* simplified, int iterations, int threads,
                         const CancelToken* cancel, RefitStats* stats) {
  RefitStats st;
  absl::Status status;
  const std::vector<Row> rows = LocateSamples(original, *simplified, vertex_map, threads, cancel,
                                              &status, &st.walked, &st.searched);
  DECIMA_RETURN_IF_ERROR(status);
  const int64_t n = original.vertex_count(), nv = simplified->vertex_count();
  // Preconditioned CGLS on min |A s - f|^2, A = the barycentric weights of each located sample.
  // Per sample only its row is stored (24 bytes; the refit's peak on a clinical scan): A x is
  // computed where it is read, the residual f - A s too (twice a step in all, where a stored
  // residual would cost 8 bytes a sample and a pass to update it), and A^T is never stored (see
  // scatter). An unlocated sample adds nothing to any of them.
  auto row_dot = [&](int64_t i, const std::vector<double>& x) {  // (A x)_i, 0 if unlocated
    const Row& row = rows[i];
    if (!row.located()) return 0.0;
    double sum = 0;
    for (int k = 0; k < 4; ++k) sum += double(row.w[k]) * x[row.vertex[k]];
    return sum * (1.0 / kWeightUnit);
  };
  // out[v] = the sum over the samples of v's non-zero weights of term(weight, value(sample)),
  // added in sample order: the order of a serial scatter, so the result is the same bit for bit
  // on any thread count. Each thread owns a range of vertices and scans the range of samples that
  // touch them: the samples and the vertices are both in grid order, so the ranges of two
  // threads overlap only by the cells that straddle their boundary.
  const int chunks = std::max(1, threads);
  std::vector<int64_t> chunk_vertex(chunks + 1), chunk_lo(chunks, n), chunk_hi(chunks, 0);
  for (int c = 0; c <= chunks; ++c) chunk_vertex[c] = nv * c / chunks;
  auto chunk_of = [&](int32_t v) {  // the c with chunk_vertex[c] <= v < chunk_vertex[c + 1]
    return int(std::upper_bound(chunk_vertex.begin() + 1, chunk_vertex.end() - 1, int64_t(v)) -
               (chunk_vertex.begin() + 1));
  };
  for (int64_t i = 0; i < n; ++i) {
    if (!rows[i].located()) continue;
    for (int k = 0; k < 4; ++k) {
      if (rows[i].w[k] == 0) continue;
      const int c = chunk_of(rows[i].vertex[k]);
      chunk_lo[c] = std::min(chunk_lo[c], i);
      chunk_hi[c] = std::max(chunk_hi[c], i + 1);
    }
  }
  auto scatter = [&](std::vector<double>& out, auto&& value, auto&& term) {
    ParallelFor(chunks, threads, 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) {
        const int64_t v0 = chunk_vertex[c], v1 = chunk_vertex[c + 1];
        std::fill(out.begin() + v0, out.begin() + v1, 0.0);
        for (int64_t i = chunk_lo[c]; i < chunk_hi[c]; ++i) {
          const Row& row = rows[i];
          if (!row.located()) continue;
          const double y = value(i);
          for (int k = 0; k < 4; ++k) {
            const int32_t v = row.vertex[k];
            if (row.w[k] != 0 && v >= v0 && v < v1) {
              out[v] += term(double(row.w[k]) * (1.0 / kWeightUnit), y);
            }
          }
        }
      }
    });
  };
  auto apply_t = [&](auto&& value, std::vector<double>& out) {  // out = A^T y, y_i = value(i)
    scatter(out, value, [](double w, double y) { return w * y; });
  };
  // Element-wise updates in parallel (each index written by one thread).
  auto each = [&](int64_t count, auto&& fn) {
    ParallelFor(count, threads, 65536, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) fn(i);
    });
  };
  for (int64_t i = 0; i < n; ++i) rows[i].located() ? ++st.samples : ++st.unlocated;
  std::vector<double> s(simplified->scalars.begin(), simplified->scalars.end());
  auto residual = [&](int64_t i) {  // (f - A s)_i, 0 if unlocated
    return rows[i].located() ? double(original.scalars[i]) - row_dot(i, s) : 0.0;
  };
  auto residual_norm2 = [&] {
    return BlockSum(n, threads, [&](int64_t i) {
      const double r = residual(i);
      return r * r;
    });
  };
  st.rms_before = st.samples > 0 ? std::sqrt(residual_norm2() / double(st.samples)) : 0;
  // Jacobi preconditioner: 1 / (A^T A)_vv, the sum of a vertex's squared weights. The columns
  // of A differ a lot (a vertex that survived in place has its own sample at weight 1, a vertex
  // of a large cell many small weights); scaled, CGLS converges in a few steps (README
  // "Refit"). A vertex with no sample gets 0: its value is never changed.
  std::vector<double> inv_diag(nv), z(nv), h(nv), p(nv);
  scatter(
      inv_diag, [](int64_t) { return 0.0; }, [](double w, double) { return w * w; });
  each(nv, [&](int64_t v) { inv_diag[v] = inv_diag[v] > 0 ? 1.0 / inv_diag[v] : 0.0; });
  apply_t(residual, z);  // z = A^T (f - A s)
  each(nv, [&](int64_t v) { h[v] = inv_diag[v] * z[v]; });
  p = h;
  double zz = BlockSum(nv, threads, [&](int64_t v) { return z[v] * h[v]; });
  const double stop = 1e-12 * std::max(1.0, zz);
  for (int it = 0; it < iterations && zz > stop; ++it) {
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));
    const double qq = BlockSum(n, threads, [&](int64_t i) {  // |A p|^2
      const double q = row_dot(i, p);
      return q * q;
    });
    if (!(qq > 0)) break;
    const double alpha = zz / qq;
    each(nv, [&](int64_t v) { s[v] += alpha * p[v]; });
    apply_t(residual, z);
    each(nv, [&](int64_t v) { h[v] = inv_diag[v] * z[v]; });
    const double zz_new = BlockSum(nv, threads, [&](int64_t v) { return z[v] * h[v]; });
    const double beta = zz_new / zz;
    zz = zz_new;
    each(nv, [&](int64_t v) { p[v] = h[v] + beta * p[v]; });
    st.iterations = it + 1;
  }
  st.rms_after = st.samples > 0 ? std::sqrt(residual_norm2() / double(st.samples)) : 0;
  for (int64_t v = 0; v < nv; ++v) simplified->scalars[v] = static_cast<float>(s[v]);
  if (stats) *stats = st;
  return absl::OkStatus();
}

absl::Status RefitAndReport(const TetMesh& original, const std::vector<int32_t>& vertex_map,
                            TetMesh* simplified, int iterations, int threads,
                            const CancelToken* cancel, const ProgressFn& progress) {
  if (iterations <= 0) return absl::OkStatus();
  RefitStats refit;
  DECIMA_RETURN_IF_ERROR(
      RefitValues(original, vertex_map, simplified, iterations, threads, cancel, &refit));
  Report(progress,
         {"simplify",
          1.0,
          absl::StrFormat("values refit to %d samples in %d steps: RMS %.3g -> %.3g", refit.samples,
                          refit.iterations, refit.rms_before, refit.rms_after),
          {{"refit_rms_before", refit.rms_before}, {"refit_rms_after", refit.rms_after}}});
  return absl::OkStatus();
}

}  // namespace decima::simplify_internal
