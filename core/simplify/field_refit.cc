#include "core/simplify/field_refit.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <limits>
#include <vector>

#include "core/common/parallel.h"
#include "core/common/status.h"

namespace decima::simplify_internal {
namespace {

// Where a sample sits: its cell and barycentric weights.
struct Location {
  int32_t cell = -1;
  std::array<float, 4> w{};
};

// Locates every original vertex in `mesh`: samples are bucketed on a uniform grid over their
// bounding box; each cell, in id order, tests the samples of the buckets its bounding box
// overlaps, and the first cell that contains a sample keeps it.
std::vector<Location> LocateSamples(const TetMesh& original, const TetMesh& mesh, int threads,
                                    const CancelToken* cancel, absl::Status* status) {
  const int64_t n = original.vertex_count();
  std::vector<Location> loc(n);
  if (n == 0 || mesh.tet_count() == 0) return loc;
  Eigen::Vector3d lo = original.Position(0), hi = lo;
  for (int64_t v = 1; v < n; ++v) {
    lo = lo.cwiseMin(original.Position(v));
    hi = hi.cwiseMax(original.Position(v));
  }
  // About two samples per bucket.
  const Eigen::Vector3d extent = (hi - lo).cwiseMax(1e-9);
  const double cell_size = std::cbrt(extent.prod() / std::max<double>(1, double(n) / 2));
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
  std::vector<int64_t> bucket(n);
  for (int64_t v = 0; v < n; ++v) {
    const Eigen::Vector3d p = original.Position(v);
    bucket[v] = bucket_of(p, 0) + dims[0] * (bucket_of(p, 1) + dims[1] * bucket_of(p, 2));
    ++start[bucket[v] + 1];
  }
  for (int64_t b = 0; b < buckets; ++b) start[b + 1] += start[b];
  std::vector<int32_t> members(n);
  {
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t v = 0; v < n; ++v) members[fill[bucket[v]]++] = int32_t(v);
  }
  // Cells test in parallel; each sample keeps the lowest containing cell id (an atomic
  // minimum), so the result does not depend on the thread count.
  std::vector<std::atomic<int32_t>> owner(n);
  for (auto& o : owner) o.store(std::numeric_limits<int32_t>::max(), std::memory_order_relaxed);
  std::atomic<bool> cancelled{false};
  ParallelFor(mesh.tet_count(), threads, 4096, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      if ((t & 0xffff) == 0 && cancel != nullptr && cancel->cancelled()) {
        cancelled = true;
        return;
      }
      const int32_t* c = &mesh.tets[4 * t];
      Eigen::Vector3d p[4];
      for (int k = 0; k < 4; ++k) p[k] = mesh.Position(c[k]);
      Eigen::Vector3d blo = p[0], bhi = p[0];
      for (int k = 1; k < 4; ++k) {
        blo = blo.cwiseMin(p[k]);
        bhi = bhi.cwiseMax(p[k]);
      }
      Eigen::Matrix3d e;
      for (int k = 0; k < 3; ++k) e.col(k) = p[k + 1] - p[0];
      const double det = e.determinant();
      if (!(det > 0)) continue;
      const Eigen::Matrix3d inv = e.inverse();
      const double eps = 1e-6;
      for (int64_t bz = bucket_of(blo, 2); bz <= bucket_of(bhi, 2); ++bz) {
        for (int64_t by = bucket_of(blo, 1); by <= bucket_of(bhi, 1); ++by) {
          for (int64_t bx = bucket_of(blo, 0); bx <= bucket_of(bhi, 0); ++bx) {
            const int64_t b = bx + dims[0] * (by + dims[1] * bz);
            for (int64_t i = start[b]; i < start[b + 1]; ++i) {
              const int32_t v = members[i];
              if (owner[v].load(std::memory_order_relaxed) < t) continue;
              const Eigen::Vector3d l = inv * (original.Position(v) - p[0]);
              const double w0 = 1 - l.sum();
              if (w0 < -eps || l.x() < -eps || l.y() < -eps || l.z() < -eps) continue;
              int32_t seen = owner[v].load(std::memory_order_relaxed);
              while (t < seen && !owner[v].compare_exchange_weak(seen, int32_t(t))) {
              }
            }
          }
        }
      }
    }
  });
  if (cancelled) {
    *status = absl::CancelledError("simplify: cancelled");
    return loc;
  }
  // Weights in the winning cell.
  ParallelFor(n, threads, 4096, [&](int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      const int32_t t = owner[v].load(std::memory_order_relaxed);
      if (t == std::numeric_limits<int32_t>::max()) continue;
      const int32_t* c = &mesh.tets[4 * int64_t(t)];
      const Eigen::Vector3d p0 = mesh.Position(c[0]);
      Eigen::Matrix3d e;
      for (int k = 0; k < 3; ++k) e.col(k) = mesh.Position(c[k + 1]) - p0;
      const Eigen::Vector3d l = e.inverse() * (original.Position(v) - p0);
      loc[v].cell = t;
      loc[v].w = {float(1 - l.sum()), float(l.x()), float(l.y()), float(l.z())};
    }
  });
  return loc;
}

}  // namespace

absl::Status RefitValues(const TetMesh& original, TetMesh* simplified, int iterations, int threads,
                         const CancelToken* cancel, RefitStats* stats) {
  absl::Status status;
  const std::vector<Location> loc = LocateSamples(original, *simplified, threads, cancel, &status);
  DECIMA_RETURN_IF_ERROR(status);
  const int64_t n = original.vertex_count(), nv = simplified->vertex_count();
  const std::vector<int32_t>& tets = simplified->tets;
  // CGLS on min |A s - f|^2, A = the barycentric weights of each located sample.
  std::vector<double> s(simplified->scalars.begin(), simplified->scalars.end());
  std::vector<double> r(n, 0), q(n, 0), z(nv), p(nv);
  // The vertices of each located sample's cell, next to its weights (A x reads one record).
  struct Row {
    std::array<int32_t, 4> vertex;
    std::array<float, 4> w;
  };
  std::vector<Row> rows(n);
  ParallelFor(n, threads, 16384, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      if (loc[i].cell < 0) continue;
      const int32_t* c = &tets[4 * int64_t(loc[i].cell)];
      rows[i] = {{c[0], c[1], c[2], c[3]}, loc[i].w};
    }
  });
  auto apply = [&](const std::vector<double>& x, std::vector<double>& out) {  // out = A x
    ParallelFor(n, threads, 16384, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        if (loc[i].cell < 0) continue;
        const Row& row = rows[i];
        double sum = 0;
        for (int k = 0; k < 4; ++k) sum += double(row.w[k]) * x[row.vertex[k]];
        out[i] = sum;
      }
    });
  };
  // A^T as rows per vertex (its samples in increasing order, with their weights), so that
  // out = A^T y runs in parallel over vertices and still adds every vertex's terms in sample
  // order: the same sums, bit for bit, on any thread count.
  std::vector<int64_t> at_start(nv + 1, 0);
  for (int64_t i = 0; i < n; ++i) {
    if (loc[i].cell < 0) continue;
    const int32_t* c = &tets[4 * int64_t(loc[i].cell)];
    for (int k = 0; k < 4; ++k) ++at_start[c[k] + 1];
  }
  for (int64_t v = 0; v < nv; ++v) at_start[v + 1] += at_start[v];
  struct Term {
    int32_t sample;
    float weight;
  };
  std::vector<Term> at_terms(at_start[nv]);
  {
    std::vector<int64_t> fill(at_start.begin(), at_start.end() - 1);
    for (int64_t i = 0; i < n; ++i) {
      if (loc[i].cell < 0) continue;
      const int32_t* c = &tets[4 * int64_t(loc[i].cell)];
      for (int k = 0; k < 4; ++k) at_terms[fill[c[k]]++] = {int32_t(i), loc[i].w[k]};
    }
  }
  auto apply_t = [&](const std::vector<double>& y, std::vector<double>& out) {  // out = A^T y
    ParallelFor(nv, threads, 16384, [&](int64_t v0, int64_t v1) {
      for (int64_t v = v0; v < v1; ++v) {
        double sum = 0;
        for (int64_t j = at_start[v]; j < at_start[v + 1]; ++j) {
          sum += double(at_terms[j].weight) * y[at_terms[j].sample];
        }
        out[v] = sum;
      }
    });
  };
  RefitStats st;
  apply(s, q);
  double rr = 0;
  for (int64_t i = 0; i < n; ++i) {
    if (loc[i].cell < 0) {
      ++st.unlocated;
      continue;
    }
    ++st.samples;
    r[i] = double(original.scalars[i]) - q[i];
    rr += r[i] * r[i];
  }
  st.rms_before = st.samples > 0 ? std::sqrt(rr / double(st.samples)) : 0;
  apply_t(r, z);
  p = z;
  double zz = 0;
  for (double x : z) zz += x * x;
  const double stop = 1e-12 * std::max(1.0, zz);
  for (int it = 0; it < iterations && zz > stop; ++it) {
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));
    apply(p, q);
    double qq = 0;
    for (int64_t i = 0; i < n; ++i) {
      if (loc[i].cell >= 0) qq += q[i] * q[i];
    }
    if (!(qq > 0)) break;
    const double alpha = zz / qq;
    for (int64_t v = 0; v < nv; ++v) s[v] += alpha * p[v];
    for (int64_t i = 0; i < n; ++i) {
      if (loc[i].cell >= 0) r[i] -= alpha * q[i];
    }
    apply_t(r, z);
    double zz_new = 0;
    for (double x : z) zz_new += x * x;
    const double beta = zz_new / zz;
    zz = zz_new;
    for (int64_t v = 0; v < nv; ++v) p[v] = z[v] + beta * p[v];
    st.iterations = it + 1;
  }
  rr = 0;
  for (int64_t i = 0; i < n; ++i) {
    if (loc[i].cell >= 0) rr += r[i] * r[i];
  }
  st.rms_after = st.samples > 0 ? std::sqrt(rr / double(st.samples)) : 0;
  for (int64_t v = 0; v < nv; ++v) simplified->scalars[v] = static_cast<float>(s[v]);
  if (stats) *stats = st;
  return absl::OkStatus();
}

}  // namespace decima::simplify_internal
