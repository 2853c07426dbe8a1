// Multiphase level-set segmentation: Samson, Blanc-Feraud, Aubert, Zerubia, "A level set model
// for image classification" (IJCV 2000), as used in paper §2.1, Eqs. (3)-(4).
//
// Data layout and invariants (per level set phi_i, a dense float array over the grid):
//  - phi_i is a signed distance (voxel units, positive inside region i) within the narrow band
//    |phi_i| < W and exactly +-W beyond it;
//  - `band` lists, ascending, the 8x8x8 blocks holding a voxel with |phi_i| < W: every loop
//    over the interface visits only these blocks, so the cost follows the interface area;
//  - only voxels with |phi_i| < alpha move (delta_alpha vanishes elsewhere), so between two
//    re-initializations an interface moves at most about alpha and stays inside the band;
//  - s0/s1/s2 hold sum_x H(phi_i) * (1, I, I^2) over the whole grid, updated incrementally by
//    every evolution step and recomputed after each re-initialization; they give the class
//    means c_i without a pass over the volume per iteration.
// Determinism: every parallel loop writes disjoint voxels and its per-block partial sums are
// added in block order, so results do not depend on the thread count or schedule.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <memory>
#include <numeric>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/bit_set.h"
#include "core/segment/internal.h"
#include "core/segment/segment.h"

namespace decima {
namespace {

// The share of the "segment" stage's progress given to its set-up (k-means, initial level sets).
constexpr double kSetupShare = 0.05;

using segment_internal::ResolveThreads;

constexpr int kBlock = 8;  // block edge in voxels (the unit of the narrow band lists)

struct Grid {
  int64_t n[3];
  int64_t stride[3];
  int64_t count;
  double h[3];  // spacing in voxel units (spacing / smallest spacing of a non-flat axis)
  double inv_h[3], inv_4h[3], inv_h2[3];  // 1 / h, 1 / (4 h), 1 / h^2: the stencils multiply
  bool active[3];                         // axis has more than one voxel
  int64_t nb[3];                          // blocks per axis
  int64_t block_count;
};

Grid MakeGrid(const Volume& image) {
  Grid g;
  double hmin = std::numeric_limits<double>::infinity();
  for (int c = 0; c < 3; ++c) {
    g.n[c] = image.dims[c];
    g.active[c] = image.dims[c] > 1;
    if (g.active[c]) hmin = std::min(hmin, image.spacing[c]);
  }
  if (!std::isfinite(hmin)) hmin = image.spacing.minCoeff();
  for (int c = 0; c < 3; ++c) {
    g.h[c] = image.spacing[c] / hmin;
    g.inv_h[c] = 1.0 / g.h[c];
    g.inv_4h[c] = 0.25 / g.h[c];
    g.inv_h2[c] = 1.0 / (g.h[c] * g.h[c]);
    g.nb[c] = (g.n[c] + kBlock - 1) / kBlock;
  }
  g.stride[0] = 1;
  g.stride[1] = g.n[0];
  g.stride[2] = g.n[0] * g.n[1];
  g.count = g.n[0] * g.n[1] * g.n[2];
  g.block_count = g.nb[0] * g.nb[1] * g.nb[2];
  return g;
}

// Calls f(index, i, j, k) for every voxel of block `b`, x fastest.
template <typename F>
inline void ForBlock(const Grid& g, int64_t b, F&& f) {
  const int64_t bi = b % g.nb[0], bj = (b / g.nb[0]) % g.nb[1], bk = b / (g.nb[0] * g.nb[1]);
  const int64_t i0 = bi * kBlock, j0 = bj * kBlock, k0 = bk * kBlock;
  const int64_t i1 = std::min(i0 + kBlock, g.n[0]), j1 = std::min(j0 + kBlock, g.n[1]),
                k1 = std::min(k0 + kBlock, g.n[2]);
  for (int64_t k = k0; k < k1; ++k)
    for (int64_t j = j0; j < j1; ++j) {
      int64_t idx = i0 + g.n[0] * (j + g.n[1] * k);
      for (int64_t i = i0; i < i1; ++i, ++idx) f(idx, i, j, k);
    }
}

inline int64_t BlockOf(const Grid& g, int64_t i, int64_t j, int64_t k) {
  return i / kBlock + g.nb[0] * (j / kBlock + g.nb[1] * (k / kBlock));
}

// Samson's regularized Heaviside and Dirac of half width alpha:
//   H(s) = (1 + s/alpha + sin(pi s/alpha)/pi) / 2,  delta(s) = (1 + cos(pi s/alpha)) / (2 alpha)
// for |s| < alpha (0/1 and 0 beyond). They are evaluated for every band voxel and level set in
// every iteration, so they come from a table with linear interpolation (error < 1e-6).
class SmoothedStep {
 public:
  explicit SmoothedStep(double alpha) : alpha_(alpha), scale_(kSamples / (2 * alpha)) {
    for (int q = 0; q <= kSamples + 1; ++q) {
      const double s = std::min(alpha, -alpha + q / scale_);
      h_[q] = 0.5 * (1.0 + s / alpha + std::sin(M_PI * s / alpha) / M_PI);
      d_[q] = (1.0 + std::cos(M_PI * s / alpha)) / (2.0 * alpha);
    }
  }
  double H(double s) const {
    if (s >= alpha_) return 1.0;
    if (s <= -alpha_) return 0.0;
    return Lerp(h_, s);
  }
  double Delta(double s) const {
    if (std::abs(s) >= alpha_) return 0.0;
    return Lerp(d_, s);
  }

 private:
  static constexpr int kSamples = 4096;
  double Lerp(const double* t, double s) const {
    const double u = (s + alpha_) * scale_;
    const int q = std::min(kSamples - 1, static_cast<int>(u));
    const double f = u - q;
    return t[q] + f * (t[q + 1] - t[q]);
  }
  double alpha_, scale_;
  double h_[kSamples + 2], d_[kSamples + 2];
};

// Neighbour offsets of a voxel with Neumann (clamp) boundaries: a missing neighbour is the
// voxel itself, which makes the normal derivative zero on the border and a 1-voxel-thick axis
// behave as 2D.
struct Offsets {
  int64_t m[3], p[3];
};
inline Offsets NeighbourOffsets(const Grid& g, int64_t i, int64_t j, int64_t k) {
  const int64_t c[3] = {i, j, k};
  Offsets o;
  for (int a = 0; a < 3; ++a) {
    o.m[a] = c[a] > 0 ? -g.stride[a] : 0;
    o.p[a] = c[a] < g.n[a] - 1 ? g.stride[a] : 0;
  }
  return o;
}

// Curvature div(grad phi / |grad phi|) in conservative form: normals on the six faces of the
// voxel (difference across the face, central differences averaged along the other axes), then
// their divergence. Unlike the non-conservative formula this does not vanish at isolated
// extrema (a one-voxel island has curvature -2 per axis), which is what removes noise specks.
inline double Curvature(const float* phi, const Grid& g, int64_t x, const Offsets& o) {
  constexpr double kEps = 1e-6;
  // x's central differences along every axis, shared by the four faces across the other axes.
  double across_x[3];
  for (int b = 0; b < 3; ++b) across_x[b] = double(phi[x + o.p[b]]) - phi[x + o.m[b]];
  double kappa = 0.0;
  for (int a = 0; a < 3; ++a) {
    if (!g.active[a]) continue;
    double face_normal[2];
    for (int side = 0; side < 2; ++side) {
      const int64_t off = side ? o.p[a] : o.m[a];
      if (off == 0) {  // border: no flux through it
        face_normal[side] = 0.0;
        continue;
      }
      const int64_t y = x + off;
      const double ga = (side ? double(phi[y]) - phi[x] : double(phi[x]) - phi[y]) * g.inv_h[a];
      double n2 = ga * ga;
      for (int b = 0; b < 3; ++b) {
        if (b == a || !g.active[b]) continue;
        // Central difference along b averaged over the two voxels of the face (y differs from
        // x only along a, so x's clamped offsets along b are y's too).
        const double gb = (across_x[b] + (double(phi[y + o.p[b]]) - phi[y + o.m[b]])) * g.inv_4h[b];
        n2 += gb * gb;
      }
      face_normal[side] = ga / (std::sqrt(n2) + kEps);
    }
    kappa += (face_normal[1] - face_normal[0]) * g.inv_h[a];
  }
  return kappa;
}

struct LevelSet {
  std::vector<float> phi;
  std::vector<int64_t> band;  // ascending block indices with some |phi| < W
  double s0 = 0, s1 = 0, s2 = 0;
};

// The input's voxel values in its own type, read as double: the evolution reads the image
// directly instead of holding a float copy of it (one float per voxel less for integer scans).
class ImageValues {
 public:
  explicit ImageValues(const Volume& v) : data_(v.bytes.data()), type_(v.type) {}
  double operator[](int64_t x) const {
    switch (type_) {
      case VoxelType::kUInt8:
        return static_cast<const uint8_t*>(data_)[x];
      case VoxelType::kInt8:
        return static_cast<const int8_t*>(data_)[x];
      case VoxelType::kUInt16:
        return static_cast<const uint16_t*>(data_)[x];
      case VoxelType::kInt16:
        return static_cast<const int16_t*>(data_)[x];
      case VoxelType::kUInt32:
        return static_cast<const uint32_t*>(data_)[x];
      case VoxelType::kInt32:
        return static_cast<const int32_t*>(data_)[x];
      case VoxelType::kFloat32:
        return static_cast<const float*>(data_)[x];
      case VoxelType::kFloat64:
        return static_cast<const double*>(data_)[x];
    }
    return 0.0;
  }

 private:
  const void* data_;
  VoxelType type_;
};

struct Context {
  Grid g;
  int k = 0;
  double alpha = 0, width = 0, dt = 0, beta = 0, inv_s2 = 0, voxel_volume = 1;
  std::vector<double> nu, e, c;
  const ImageValues* image = nullptr;
  uint8_t* labels = nullptr;
  std::vector<LevelSet> ls;
  std::vector<double> region_sums;  // per label: voxels, sum I, sum I^2 (3 K values)
  int threads = 1;
  std::unique_ptr<SmoothedStep> step;
};

// The buckets of the untidy priority queue of the fast marching: a stack of fixed-size chunks
// per bucket, chunks recycled through a free list, so the memory follows the entries pending
// at any time (within one chunk per bucket) instead of the sum of the vectors' capacities.
class BucketQueue {
 public:
  explicit BucketQueue(int64_t buckets) : head_(buckets, kNone) {}
  void Push(int64_t bucket, uint32_t x) {
    int32_t c = head_[bucket];
    if (c == kNone || chunks_[c]->count == kChunkEntries) {
      const int32_t fresh = NewChunk();
      chunks_[fresh]->next = c;
      head_[bucket] = c = fresh;
    }
    Chunk& chunk = *chunks_[c];
    chunk.ids[chunk.count++] = x;
  }
  // Moves every entry of `bucket` to *out (replacing its contents) and empties the bucket.
  void Drain(int64_t bucket, std::vector<uint32_t>* out) {
    out->clear();
    for (int32_t c = head_[bucket]; c != kNone;) {
      const Chunk& chunk = *chunks_[c];
      out->insert(out->end(), chunk.ids, chunk.ids + chunk.count);
      free_.push_back(c);
      c = chunk.next;
    }
    head_[bucket] = kNone;
  }

 private:
  static constexpr int32_t kNone = -1;
  static constexpr uint32_t kChunkEntries = 510;  // a chunk is 2 KB
  struct Chunk {
    uint32_t count = 0;
    int32_t next = kNone;
    uint32_t ids[kChunkEntries];
  };
  int32_t NewChunk() {
    if (!free_.empty()) {
      const int32_t c = free_.back();
      free_.pop_back();
      chunks_[c]->count = 0;
      return c;
    }
    chunks_.push_back(std::make_unique<Chunk>());
    return static_cast<int32_t>(chunks_.size() - 1);
  }
  std::vector<int32_t> head_;
  std::vector<std::unique_ptr<Chunk>> chunks_;
  std::vector<int32_t> free_;
};

// Sorts voxel indices ascending: LSD radix sort, 11-bit digits, only as many digits as the
// largest index needs.
void SortIndices(std::vector<uint32_t>* v, std::vector<uint32_t>* scratch) {
  uint32_t max_value = 0;
  for (const uint32_t x : *v) max_value = std::max(max_value, x);
  scratch->resize(v->size());
  constexpr int kBits = 11, kRadix = 1 << kBits;
  uint32_t count[kRadix];
  for (int shift = 0; shift < 32 && (max_value >> shift) != 0; shift += kBits) {
    std::fill(count, count + kRadix, 0u);
    for (const uint32_t x : *v) ++count[(x >> shift) & (kRadix - 1)];
    uint32_t sum = 0;
    for (int d = 0; d < kRadix; ++d) {
      const uint32_t c = count[d];
      count[d] = sum;
      sum += c;
    }
    for (const uint32_t x : *v) (*scratch)[count[(x >> shift) & (kRadix - 1)]++] = x;
    v->swap(*scratch);
  }
}

// First-order upwind Eikonal update |grad u| = 1 at voxel x from its accepted neighbours
// (anisotropic spacing h).
inline double EikonalUpdate(const Grid& g, const BitSet& accepted, const float* phi, int64_t x,
                            const Offsets& o) {
  double a[3], w[3];
  int m = 0;
  for (int c = 0; c < 3; ++c) {
    if (!g.active[c]) continue;
    double best = std::numeric_limits<double>::infinity();
    if (o.m[c] != 0 && accepted.Test(x + o.m[c]))
      best = std::min<double>(best, std::abs(phi[x + o.m[c]]));
    if (o.p[c] != 0 && accepted.Test(x + o.p[c]))
      best = std::min<double>(best, std::abs(phi[x + o.p[c]]));
    if (std::isfinite(best)) {
      a[m] = best;
      w[m] = g.inv_h2[c];
      ++m;
    }
  }
  if (m == 0) return std::numeric_limits<double>::infinity();
  // Sort the (a, w) pairs by a.
  for (int p = 1; p < m; ++p)
    for (int q = p; q > 0 && a[q] < a[q - 1]; --q) {
      std::swap(a[q], a[q - 1]);
      std::swap(w[q], w[q - 1]);
    }
  double u = a[0] + 1.0 / std::sqrt(w[0]);
  double sw = w[0], swa = w[0] * a[0], swa2 = w[0] * a[0] * a[0];
  for (int p = 1; p < m && u > a[p]; ++p) {
    sw += w[p];
    swa += w[p] * a[p];
    swa2 += w[p] * a[p] * a[p];
    const double disc = swa * swa - sw * (swa2 - 1.0);
    u = (swa + std::sqrt(std::max(0.0, disc))) / sw;
  }
  return u;
}

// Seeds of the re-initialization of phi_i: the voxels of `blocks` next to the boundary of the
// current region {labels == i}, with their signed distance estimate to it (positive inside).
// The boundary is the zero set of psi_i = phi_i - max_{j != i} phi_j, which is >= 0 exactly where
// label == i (label = argmax): for a voxel x whose 6-neighbour y lies on the other side, the
// crossing is at the fraction |psi_x| / (|psi_x| + |psi_y|) of the step (clamped to
// [kMinFrac, 1 - kMinFrac], so no seed is 0 and every voxel keeps a strict sign), and the
// distances t_c to the crossings along the axes combine as 1 / sqrt(sum_c t_c^-2) (the distance
// to the plane through them). Reads every phi_j: run before any phi is rewritten.
std::vector<std::pair<uint32_t, float>> ReinitSeeds(const Context& ctx, int i,
                                                    const std::vector<int64_t>& blocks) {
  constexpr double kMinFrac = 0.02;
  const Grid& g = ctx.g;
  const int k = ctx.k;
  const uint8_t* labels = ctx.labels;
  // psi_i at voxel x (>= 0 iff labels[x] == i).
  auto psi = [&](int64_t x) -> double {
    const double pi = ctx.ls[i].phi[x];
    if (labels[x] != i) return std::min(0.0, pi - ctx.ls[labels[x]].phi[x]);
    double other = -std::numeric_limits<double>::infinity();
    for (int j = 0; j < k; ++j)
      if (j != i) other = std::max<double>(other, ctx.ls[j].phi[x]);
    return std::max(0.0, pi - other);
  };
  std::vector<std::pair<uint32_t, float>> seeds;
  for (int64_t b : blocks) {
    ForBlock(g, b, [&](int64_t x, int64_t ii, int64_t jj, int64_t kk) {
      const Offsets o = NeighbourOffsets(g, ii, jj, kk);
      const bool inside = labels[x] == i;
      bool boundary = false;
      for (int c = 0; c < 3 && !boundary; ++c)
        boundary = (o.m[c] != 0 && (labels[x + o.m[c]] == i) != inside) ||
                   (o.p[c] != 0 && (labels[x + o.p[c]] == i) != inside);
      if (!boundary) return;
      const double px = std::abs(psi(x));
      double inv = 0.0;
      for (int c = 0; c < 3; ++c) {
        if (!g.active[c]) continue;
        double t = std::numeric_limits<double>::infinity();
        for (int side = 0; side < 2; ++side) {
          const int64_t off = side ? o.p[c] : o.m[c];
          if (off == 0 || (labels[x + off] == i) == inside) continue;
          const double py = std::abs(psi(x + off));
          const double frac = px + py > 0 ? px / (px + py) : 0.5;
          t = std::min(t, std::clamp(frac, kMinFrac, 1.0 - kMinFrac) * g.h[c]);
        }
        if (std::isfinite(t)) inv += 1.0 / (t * t);
      }
      const double d = 1.0 / std::sqrt(inv);
      seeds.emplace_back(static_cast<uint32_t>(x), static_cast<float>(inside ? d : -d));
    });
  }
  return seeds;
}

// Re-initializes phi_i to the signed distance to the boundary of the current region
// {labels == i} (positive inside) within the band, by fast marching (Sethian) from `seeds`
// (ReinitSeeds). Every voxel of `blocks` is first reset to +-W by its label, and the march gives
// voxels the sign of their label, so afterwards phi_i > 0 exactly on region i: the argmax labels
// are unchanged (re-initialization preserves the partition; it only removes overlaps and vacuum
// and restores |grad phi| = 1). `blocks` must hold every voxel whose label or phi_i changed since
// the last re-initialization (the label blocks); voxels elsewhere are +-W with their label's sign
// already. s0/s1/s2 are left to ComputeHeavisideSums (a sequential pass costs less than
// tracking every write of the march). Runs on one thread; level sets run in parallel.
void Reinitialize(Context& ctx, int i, const std::vector<int64_t>& blocks,
                  std::vector<std::pair<uint32_t, float>> seeds) {
  const Grid& g = ctx.g;
  LevelSet& ls = ctx.ls[i];
  float* phi = ls.phi.data();
  const double W = ctx.width;
  const uint8_t* labels = ctx.labels;

  // 1. Reset the blocks to +-W by label, then place the seeds.
  for (int64_t b : blocks) {
    ForBlock(g, b, [&](int64_t x, int64_t, int64_t, int64_t) {
      const float before = phi[x];
      const float after = labels[x] == i ? static_cast<float>(W) : static_cast<float>(-W);
      if (before != after) phi[x] = after;
    });
  }
  // 2. Fast marching outwards on both sides until the distance reaches W, with an "untidy"
  // priority queue (Yatziv, Bartesaghi, Sapiro 2006): buckets of width kBucket processed in
  // order. O(1) per operation instead of a heap's O(log n); the ordering error, and so the
  // distance error, stays below kBucket voxels.
  constexpr double kBucket = 0.02;
  const int64_t bucket_count = static_cast<int64_t>(W / kBucket) + 2;
  BucketQueue queue(bucket_count);
  auto bucket_of = [&](double d) {
    return std::min<int64_t>(bucket_count - 1, static_cast<int64_t>(d / kBucket));
  };
  for (const auto& [x, d] : seeds) {
    phi[x] = d;
    queue.Push(bucket_of(std::abs(d)), x);
  }
  seeds.clear();
  seeds.shrink_to_fit();
  // One bit per voxel: the accepted flags of this level set only, so the K marches running in
  // parallel never write to the same cache line.
  BitSet accepted(g.count);
  std::vector<uint8_t> in_band(g.block_count, 0);
  // A bucket is processed in batches sorted by voxel index: popping in push order walks the
  // volume at random and waits on memory for every neighbour; in index order the neighbours of
  // nearby voxels share cache lines. (Any order within a bucket is allowed by the untidy queue.)
  const uint32_t nx = static_cast<uint32_t>(g.n[0]), ny = static_cast<uint32_t>(g.n[1]);
  constexpr size_t kPrefetchAhead = 16;
  const int64_t sy = g.stride[1], sz = g.stride[2];
  const int64_t prefetch_offsets[] = {0,       -sy,    sy,       -sz,     sz,       -2 * sy, 2 * sy,
                                      -2 * sz, 2 * sz, -sy - sz, sy - sz, -sy + sz, sy + sz};
  std::vector<uint32_t> batch, sort_scratch;
  for (int64_t current = 0; current < bucket_count; ++current) {
    for (;;) {
      queue.Drain(current, &batch);
      if (batch.empty()) break;
      SortIndices(&batch, &sort_scratch);
      const size_t batch_size = batch.size();
      for (size_t e = 0; e < batch_size; ++e) {
        const uint32_t x32 = batch[e];
        // The Eikonal updates around x read the 3x3x3 neighbourhood and a voxel beyond each
        // face: fetch the lines of a voxel a few entries ahead (this loop waits on memory).
        if (e + kPrefetchAhead < batch_size) {
          const int64_t ahead = batch[e + kPrefetchAhead];
          for (const int64_t off : prefetch_offsets) {
            const int64_t y = ahead + off;
            if (y >= 0 && y < g.count) __builtin_prefetch(phi + y);
          }
        }
        const int64_t x = x32;
        if (accepted.Test(x)) continue;
        accepted.Set(x);
        // 32-bit divisions (voxel indices fit uint32): several times cheaper than 64-bit ones.
        const uint32_t row = x32 / nx;
        const int64_t xi = x32 - row * nx, xj = row % ny, xk = row / ny;
        in_band[BlockOf(g, xi, xj, xk)] = 1;
        const Offsets o = NeighbourOffsets(g, xi, xj, xk);
        for (int c = 0; c < 3; ++c) {
          for (int side = 0; side < 2; ++side) {
            const int64_t off = side ? o.p[c] : o.m[c];
            if (off == 0) continue;
            const int64_t y = x + off;
            if (accepted.Test(y)) continue;
            // y's coordinates from x's (no integer divisions in the hot loop).
            int64_t yc[3] = {xi, xj, xk};
            yc[c] += side ? 1 : -1;
            const double u =
                EikonalUpdate(g, accepted, phi, y, NeighbourOffsets(g, yc[0], yc[1], yc[2]));
            if (u < W && u < std::abs(phi[y])) {
              // Every value written keeps the sign of the voxel's label (reset, seeds, march).
              const float after = static_cast<float>(phi[y] > 0 ? u : -u);
              phi[y] = after;
              queue.Push(std::max(current, bucket_of(u)), static_cast<uint32_t>(y));
            }
          }
        }
      }
    }
  }

  // 3. The new band.
  ls.band.clear();
  for (int64_t b = 0; b < g.block_count; ++b)
    if (in_band[b]) ls.band.push_back(b);
}

// Re-initializes every phi_i from the current labels (ReinitSeeds, then Reinitialize), the K
// level sets in parallel. `blocks` as for Reinitialize.
void ReinitializeAll(Context& ctx, const std::vector<int64_t>& blocks) {
  const int k = ctx.k;
  std::vector<std::vector<std::pair<uint32_t, float>>> seeds(k);
  // Seeds read every phi_j, so they are all computed before any phi is rewritten.
#pragma omp parallel for schedule(dynamic, 1) num_threads(std::min(ctx.threads, k))
  for (int i = 0; i < k; ++i) seeds[i] = ReinitSeeds(ctx, i, blocks);
#pragma omp parallel for schedule(dynamic, 1) num_threads(std::min(ctx.threads, k))
  for (int i = 0; i < k; ++i) Reinitialize(ctx, i, blocks, std::move(seeds[i]));
}

// phi_i = the exact signed distance to the k-means region i (clamped to +-W) and its band: the
// start of the evolution. A speckled k-means partition has seeds almost everywhere, which
// made the fast-marching start the slowest and largest step; the separable distance transform
// costs a few linear passes and one scratch float per voxel.
void InitializeFromLabels(Context& ctx) {
  const Grid& g = ctx.g;
  const std::array<int64_t, 3> dims = {g.n[0], g.n[1], g.n[2]};
  const float W = static_cast<float>(ctx.width);
  for (int i = 0; i < ctx.k; ++i) {
    LevelSet& ls = ctx.ls[i];
    ls.phi.resize(g.count);
    segment_internal::RegionSignedDistance(ctx.labels, dims, g.h, i, W, ls.phi.data(), ctx.threads);
    std::vector<uint8_t> in_band(g.block_count, 0);
    const float* phi = ls.phi.data();
#pragma omp parallel for schedule(dynamic, 16) num_threads(ctx.threads)
    for (int64_t b = 0; b < g.block_count; ++b) {
      bool any = false;
      ForBlock(g, b, [&](int64_t x, int64_t, int64_t, int64_t) { any |= std::abs(phi[x]) < W; });
      in_band[b] = any;
    }
    ls.band.clear();
    for (int64_t b = 0; b < g.block_count; ++b)
      if (in_band[b]) ls.band.push_back(b);
  }
}

// s0/s1/s2 of every level set from scratch: sum_x H(phi_i) (1, I, I^2) over the grid, in fixed
// chunks added in order (deterministic for any thread count).
void ComputeHeavisideSums(Context& ctx) {
  const int64_t n = ctx.g.count;
  constexpr int64_t kChunk = 1 << 16;
  const int64_t chunks = (n + kChunk - 1) / kChunk;
  std::vector<double> part(3 * chunks);
  for (LevelSet& ls : ctx.ls) {
    const float* phi = ls.phi.data();
#pragma omp parallel for schedule(static) num_threads(ctx.threads)
    for (int64_t q = 0; q < chunks; ++q) {
      double a0 = 0, a1 = 0, a2 = 0;
      for (int64_t x = q * kChunk; x < std::min(n, (q + 1) * kChunk); ++x) {
        const double h = ctx.step->H(phi[x]);
        if (h == 0.0) continue;
        const double v = (*ctx.image)[x];
        a0 += h;
        a1 += h * v;
        a2 += h * v * v;
      }
      part[3 * q] = a0;
      part[3 * q + 1] = a1;
      part[3 * q + 2] = a2;
    }
    ls.s0 = ls.s1 = ls.s2 = 0;
    for (int64_t q = 0; q < chunks; ++q) {
      ls.s0 += part[3 * q];
      ls.s1 += part[3 * q + 1];
      ls.s2 += part[3 * q + 2];
    }
  }
}

// Sorted union of the band lists (and `extra`, if given).
std::vector<int64_t> BandUnion(const Context& ctx, const std::vector<int64_t>* extra) {
  std::vector<uint8_t> mark(ctx.g.block_count, 0);
  for (const LevelSet& ls : ctx.ls)
    for (int64_t b : ls.band) mark[b] = 1;
  if (extra)
    for (int64_t b : *extra) mark[b] = 1;
  std::vector<int64_t> out;
  for (int64_t b = 0; b < ctx.g.block_count; ++b)
    if (mark[b]) out.push_back(b);
  return out;
}

// One explicit step of Eq. (4) for level set i (Jacobi within phi_i, using the current values
// of the other level sets).
// `next` is scratch for the new values of the band blocks only (kBlock^3 floats per band block,
// in ForBlock order), so the Jacobi copy costs memory in proportion to the band, not the volume.
void EvolveLevelSet(Context& ctx, int i, std::vector<float>& next) {
  const Grid& g = ctx.g;
  LevelSet& ls = ctx.ls[i];
  const int64_t nb = static_cast<int64_t>(ls.band.size());
  std::vector<double> ds(3 * nb, 0.0);
  const double alpha = ctx.alpha, W = ctx.width;
  const int k = ctx.k;
  float* phi = ls.phi.data();
  constexpr int64_t kBlockVoxels = int64_t{kBlock} * kBlock * kBlock;
  if (static_cast<int64_t>(next.size()) < nb * kBlockVoxels) {
    // Grow without keeping the old contents: a resize would hold both buffers at once.
    std::vector<float>().swap(next);
    next.resize(nb * kBlockVoxels);
  }
  // Per-voxel constants of the loop in locals: through ctx the compiler reloads them after every
  // store to `out`, which it cannot prove does not alias them.
  const float* phis[8];
  double fit_scale[8], class_mean[8];
  for (int j = 0; j < k; ++j) {
    phis[j] = ctx.ls[j].phi.data();
    fit_scale[j] = ctx.e[j] * ctx.inv_s2;
    class_mean[j] = ctx.c[j];
  }
  const ImageValues& image = *ctx.image;
  const SmoothedStep& step = *ctx.step;
  const double nu = ctx.nu[i], beta = ctx.beta, dt = ctx.dt;

#pragma omp parallel for schedule(dynamic, 4) num_threads(ctx.threads)
  for (int64_t q = 0; q < nb; ++q) {
    float* out = next.data() + q * kBlockVoxels;
    int64_t t = 0;
    ForBlock(g, ls.band[q], [&](int64_t x, int64_t ii, int64_t jj, int64_t kk) {
      const double p = phi[x];
      if (std::abs(p) >= alpha) {
        out[t++] = static_cast<float>(p);
        return;
      }
      const Offsets o = NeighbourOffsets(g, ii, jj, kk);
      const double kappa = Curvature(phi, g, x, o);
      const double delta = step.Delta(p);
      // Fitting force relative to the best class at this voxel (see README: subtracting the
      // per-voxel minimum leaves the partition-constrained energy unchanged).
      const double v = image[x];
      double fit_i = 0.0, fit_min = std::numeric_limits<double>::infinity();
      double sum_h = 0.0;
      for (int j = 0; j < k; ++j) {
        const double r = v - class_mean[j];
        const double f = fit_scale[j] * r * r;
        if (j == i) fit_i = f;
        fit_min = std::min(fit_min, f);
        sum_h += step.H(j == i ? p : phis[j][x]);
      }
      const double force = nu * kappa - (fit_i - fit_min) - beta * (sum_h - 1.0);
      out[t++] = static_cast<float>(std::clamp(p + dt * delta * force, -W, W));
    });
  }

#pragma omp parallel for schedule(dynamic, 4) num_threads(ctx.threads)
  for (int64_t q = 0; q < nb; ++q) {
    double d0 = 0, d1 = 0, d2 = 0;
    const float* out = next.data() + q * kBlockVoxels;
    int64_t t = 0;
    ForBlock(g, ls.band[q], [&](int64_t x, int64_t, int64_t, int64_t) {
      const float before = phi[x], after = out[t++];
      if (before == after) return;
      const double dh = ctx.step->H(after) - ctx.step->H(before);
      const double v = (*ctx.image)[x];
      d0 += dh;
      d1 += dh * v;
      d2 += dh * v * v;
      phi[x] = after;
    });
    ds[3 * q] = d0;
    ds[3 * q + 1] = d1;
    ds[3 * q + 2] = d2;
  }
  for (int64_t q = 0; q < nb; ++q) {
    ls.s0 += ds[3 * q];
    ls.s1 += ds[3 * q + 1];
    ls.s2 += ds[3 * q + 2];
  }
}

// Relabels the voxels of `blocks` by argmax_i phi_i (ties: lowest i). Returns the number of
// changed labels and keeps ctx.region_sums (per label: voxels, sum I, sum I^2) exact.
int64_t Relabel(Context& ctx, const std::vector<int64_t>& blocks) {
  const int64_t nb = static_cast<int64_t>(blocks.size());
  const int k = ctx.k;
  std::vector<int64_t> changed(nb, 0);
  std::vector<double> sums(nb * 3 * k, 0.0);  // per block: per label (d count, d I, d I^2)
#pragma omp parallel for schedule(dynamic, 4) num_threads(ctx.threads)
  for (int64_t q = 0; q < nb; ++q) {
    int64_t ch = 0;
    double* d = sums.data() + q * 3 * k;
    ForBlock(ctx.g, blocks[q], [&](int64_t x, int64_t, int64_t, int64_t) {
      int best = 0;
      float best_v = ctx.ls[0].phi[x];
      for (int j = 1; j < k; ++j) {
        const float v = ctx.ls[j].phi[x];
        if (v > best_v) {
          best_v = v;
          best = j;
        }
      }
      const int old = ctx.labels[x];
      if (old != best) {
        const double v = (*ctx.image)[x];
        d[3 * old] -= 1;
        d[3 * old + 1] -= v;
        d[3 * old + 2] -= v * v;
        d[3 * best] += 1;
        d[3 * best + 1] += v;
        d[3 * best + 2] += v * v;
        ctx.labels[x] = static_cast<uint8_t>(best);
        ++ch;
      }
    });
    changed[q] = ch;
  }
  int64_t total = 0;
  for (int64_t q = 0; q < nb; ++q) {
    total += changed[q];
    for (int t = 0; t < 3 * k; ++t) ctx.region_sums[t] += sums[q * 3 * k + t];
  }
  return total;
}

// Interface of the current labels: the voxel faces between two different labels with the lower
// voxel in `blocks` (every interface face lies there: labels differ only next to a band).
// Returns the face count; *length gets the sum over faces of the face area (voxel units) x the
// mean nu of its two regions, the length term of Eq. (3) for the partition.
int64_t InterfaceFaces(const Context& ctx, const std::vector<int64_t>& blocks, double* length) {
  const Grid& g = ctx.g;
  const int64_t nb = static_cast<int64_t>(blocks.size());
  const uint8_t* labels = ctx.labels;
  const double area[3] = {g.h[1] * g.h[2], g.h[0] * g.h[2], g.h[0] * g.h[1]};
  std::vector<double> len(nb, 0.0);
  int64_t total = 0;
#pragma omp parallel for schedule(dynamic, 4) num_threads(ctx.threads) reduction(+ : total)
  for (int64_t q = 0; q < nb; ++q) {
    int64_t f = 0;
    double l = 0.0;
    auto face = [&](uint8_t a, uint8_t b, int axis) {
      if (a == b) return;
      ++f;
      l += 0.5 * (ctx.nu[a] + ctx.nu[b]) * area[axis];
    };
    ForBlock(g, blocks[q], [&](int64_t x, int64_t ii, int64_t jj, int64_t kk) {
      const uint8_t lx = labels[x];
      if (ii + 1 < g.n[0]) face(lx, labels[x + 1], 0);
      if (jj + 1 < g.n[1]) face(lx, labels[x + g.stride[1]], 1);
      if (kk + 1 < g.n[2]) face(lx, labels[x + g.stride[2]], 2);
    });
    total += f;
    len[q] = l;
  }
  *length = 0.0;
  for (double l : len) *length += l;
  return total;
}

}  // namespace

absl::Status ValidateSegmentOptions(const SegmentOptions& o) {
  const int k = o.regions;
  if (k < 2 || k > 8) {
    return absl::InvalidArgumentError(absl::StrCat("segment: regions = ", k, ", expected 2 to 8"));
  }
  if (!o.class_means.empty()) {
    if (static_cast<int>(o.class_means.size()) != k) {
      return absl::InvalidArgumentError(absl::StrCat(
          "segment: class_means has ", o.class_means.size(), " values, expected regions = ", k));
    }
    for (size_t a = 0; a < o.class_means.size(); ++a) {
      if (!std::isfinite(o.class_means[a])) {
        return absl::InvalidArgumentError(
            absl::StrCat("segment: class_means[", a, "] is not finite"));
      }
      for (size_t b = 0; b < a; ++b)
        if (o.class_means[a] == o.class_means[b]) {
          return absl::InvalidArgumentError(absl::StrCat("segment: class_means[", b, "] and [", a,
                                                         "] are equal (", o.class_means[a], ")"));
        }
    }
  }
  auto nonneg = [](double v, const std::string& name) -> absl::Status {
    if (!std::isfinite(v) || v < 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("segment: ", name, " = ", v, ", expected a finite value >= 0"));
    }
    return absl::OkStatus();
  };
  DECIMA_RETURN_IF_ERROR(nonneg(o.curvature_weight, "curvature_weight (nu)"));
  DECIMA_RETURN_IF_ERROR(nonneg(o.fitting_weight, "fitting_weight (e)"));
  DECIMA_RETURN_IF_ERROR(nonneg(o.overlap_weight, "overlap_weight (beta)"));
  for (const auto* vec : {&o.curvature_weights, &o.fitting_weights}) {
    const bool nu = vec == &o.curvature_weights;
    const std::string name = nu ? "curvature_weights" : "fitting_weights";
    if (!vec->empty() && static_cast<int>(vec->size()) != k) {
      return absl::InvalidArgumentError(absl::StrCat("segment: ", name, " has ", vec->size(),
                                                     " values, expected 0 or regions = ", k));
    }
    for (size_t a = 0; a < vec->size(); ++a)
      DECIMA_RETURN_IF_ERROR(nonneg((*vec)[a], absl::StrCat(name, "[", a, "]")));
  }
  {
    double emax = o.fitting_weights.empty() ? o.fitting_weight : 0.0;
    for (double v : o.fitting_weights) emax = std::max(emax, v);
    if (!(emax > 0)) {
      return absl::InvalidArgumentError(
          "segment: fitting_weight (e) is 0 for every region; the segmentation would ignore the "
          "image");
    }
  }
  if (!std::isfinite(o.alpha) || o.alpha <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("segment: alpha = ", o.alpha, ", expected a finite value > 0 (voxels)"));
  }
  if (!std::isfinite(o.dt) || o.dt < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("segment: dt = ", o.dt, ", expected >= 0 (0 = automatic)"));
  }
  if (o.reinit_interval < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("segment: reinit_interval = ", o.reinit_interval, ", expected >= 1"));
  }
  if (o.max_iterations < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("segment: max_iterations = ", o.max_iterations, ", expected >= 0"));
  }
  if (!(o.convergence_threshold >= 0 && o.convergence_threshold < 1)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "segment: convergence_threshold = ", o.convergence_threshold, ", expected in [0, 1)"));
  }
  if (o.convergence_window < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("segment: convergence_window = ", o.convergence_window, ", expected >= 1"));
  }
  if (o.threads < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("segment: threads = ", o.threads, ", expected >= 0 (0 = all cores)"));
  }
  return absl::OkStatus();
}

namespace {

// ValidateSegmentOptions plus what depends on the grid.
absl::Status ValidateOptions(const SegmentOptions& o, const Volume& image) {
  DECIMA_RETURN_IF_ERROR(Validate(image, "segment: image"));
  DECIMA_RETURN_IF_ERROR(ValidateSegmentOptions(o));
  const double dt_max = MaxStableTimeStep(o, image);
  if (o.dt > dt_max) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "segment: dt = %g breaks the stability bound dt <= %g (1 / (2 nu sum_c h_c^-2 / alpha + "
        "beta / (2 alpha^2)) for nu = %g, beta = %g, alpha = %g); lower dt or use 0 (automatic)",
        o.dt, dt_max,
        o.curvature_weights.empty()
            ? o.curvature_weight
            : *std::max_element(o.curvature_weights.begin(), o.curvature_weights.end()),
        o.overlap_weight, o.alpha));
  }
  if (o.band_width != 0) {
    const Grid g = MakeGrid(image);
    const double need =
        o.alpha + std::max({g.h[0] * g.active[0], g.h[1] * g.active[1], g.h[2] * g.active[2], 1.0});
    if (!std::isfinite(o.band_width) || o.band_width < need) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "segment: band_width = %g, expected 0 (automatic) or >= alpha + largest spacing ratio "
          "= %g voxels",
          o.band_width, need));
    }
  }
  return absl::OkStatus();
}

}  // namespace

double MaxStableTimeStep(const SegmentOptions& o, const Volume& image) {
  const Grid g = MakeGrid(image);
  double sum_inv = 0;
  for (int c = 0; c < 3; ++c)
    if (g.active[c]) sum_inv += 1.0 / (g.h[c] * g.h[c]);
  double nu = o.curvature_weight;
  if (!o.curvature_weights.empty())
    nu = *std::max_element(o.curvature_weights.begin(), o.curvature_weights.end());
  if (!(o.alpha > 0)) return 0.0;
  const double rate = 2.0 * nu * sum_inv / o.alpha + o.overlap_weight / (2.0 * o.alpha * o.alpha);
  return rate > 0 ? 1.0 / rate : std::numeric_limits<double>::infinity();
}

namespace segment_internal {

int ForecastIterations(const std::vector<double>& history, int quiet, const SegmentOptions& o) {
  const int done = static_cast<int>(history.size());
  const int at_most = std::max(o.max_iterations, done + 1);
  if (quiet >= o.convergence_window) return std::min(done, at_most);  // converged
  // The first iterations say little: the first changes few labels (the interfaces have not
  // started to move), so a quiet start would promise convergence at the third.
  if (done < 4) return at_most;
  if (quiet > 0) return std::clamp(done + o.convergence_window - quiet, done + 1, at_most);
  if (!(o.convergence_threshold > 0)) return at_most;
  // The changes shrink roughly geometrically once the interfaces have found their edges, with
  // spikes after each re-initialization: the rate is the least-squares slope of log(fraction)
  // over the last few iterations (the first, before the interfaces moved, left out).
  const int span = std::min(8, done - 1);  // at least 3, as done >= 4
  std::array<double, 8> y;
  double mean_x = 0, mean_y = 0;
  for (int i = 0; i < span; ++i) {
    y[i] = std::log(std::max(history[done - span + i], 1e-12));
    mean_x += i;
    mean_y += y[i];
  }
  mean_x /= span;
  mean_y /= span;
  double sxy = 0, sxx = 0;
  for (int i = 0; i < span; ++i) {
    sxy += (i - mean_x) * (y[i] - mean_y);
    sxx += (i - mean_x) * (i - mean_x);
  }
  const double slope = sxy / sxx;  // log of the rate per iteration
  if (!(slope < std::log(0.98))) return at_most;
  const double fitted_last = mean_y + slope * (span - 1 - mean_x);
  const double to_threshold =
      std::max(0.0, std::ceil((std::log(o.convergence_threshold) - fitted_last) / slope));
  const double forecast = done + to_threshold + o.convergence_window;
  return static_cast<int>(std::clamp<double>(forecast, done + 1, at_most));
}

}  // namespace segment_internal

absl::StatusOr<SegmentResult> Segment(const Volume& image, const SegmentOptions& o,
                                      const ProgressFn& progress, const CancelToken* cancel) {
  DECIMA_RETURN_IF_ERROR(ValidateOptions(o, image));
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));
  const int k = o.regions;
  const int threads = ResolveThreads(o.threads);
  Context ctx;
  ctx.g = MakeGrid(image);
  ctx.k = k;
  ctx.threads = threads;
  const int64_t n = ctx.g.count;

  // The float image of the set-up (k-means, initial partition, noise level): the input itself
  // when it is float32, else a converted copy, freed before the level sets are allocated (the
  // evolution reads the input through ImageValues).
  std::vector<float> copy;
  if (image.type != VoxelType::kFloat32) copy = image.ToFloat();
  const float* values = image.type == VoxelType::kFloat32 ? image.data<float>() : copy.data();
  const ImageValues image_values(image);
  ctx.image = &image_values;
  SegmentResult result;
  DECIMA_ASSIGN_OR_RETURN(result.labels, MakeVolume(image.dims, VoxelType::kUInt8, image.spacing));
  result.labels.origin = image.origin;
  result.labels.direction = image.direction;
  result.labels.modality = "SEG";
  ctx.labels = result.labels.mutable_data<uint8_t>();

  // The set-up (k-means, the initial level sets) is reported as the first few percent of the
  // stage, so a watcher sees it moving before the first iteration.
  auto report_setup = [&](double fraction, const char* message) {
    Progress p;
    p.stage = "segment";
    p.fraction = fraction;
    p.message = message;
    p.metrics = {{"iteration", 0}};
    Report(progress, p);
  };
  report_setup(0, "k-means of the intensities");
  // Class means: given (and fixed), or k-means (then updated unless fix_class_means).
  bool fixed = true;
  if (o.class_means.empty()) {
    const bool integer_valued =
        image.type != VoxelType::kFloat32 && image.type != VoxelType::kFloat64;
    DECIMA_ASSIGN_OR_RETURN(auto km,
                            segment_internal::RunKMeans(values, n, k, integer_valued, cancel));
    ctx.c = km.means;
    fixed = o.fix_class_means;
  } else {
    ctx.c = o.class_means;
  }
  segment_internal::AssignNearest(values, n, ctx.c, ctx.labels, threads);
  {
    // Per-label sums of the initial partition (then kept by Relabel), for the reported energy.
    constexpr int64_t kChunk = 1 << 16;
    const int64_t chunks = (n + kChunk - 1) / kChunk;
    std::vector<double> part(chunks * 3 * k, 0.0);
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t q = 0; q < chunks; ++q) {
      double* d = part.data() + q * 3 * k;
      for (int64_t x = q * kChunk; x < std::min(n, (q + 1) * kChunk); ++x) {
        const double v = values[x];
        double* r = d + 3 * ctx.labels[x];
        r[0] += 1;
        r[1] += v;
        r[2] += v * v;
      }
    }
    ctx.region_sums.assign(3 * k, 0.0);
    for (int64_t q = 0; q < chunks; ++q)
      for (int t = 0; t < 3 * k; ++t) ctx.region_sums[t] += part[q * 3 * k + t];
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));

  // Noise normalization: the pooled within-class variance of the initial partition, floored
  // at (5% of the smallest class-mean gap)^2 so noise-free images stay well scaled.
  double min_gap = std::numeric_limits<double>::infinity();
  for (int a = 0; a < k; ++a)
    for (int b = 0; b < a; ++b) min_gap = std::min(min_gap, std::abs(ctx.c[a] - ctx.c[b]));
  const double var = std::max(segment_internal::PooledVariance(values, n, ctx.labels, ctx.c),
                              std::pow(0.05 * min_gap, 2));
  ctx.inv_s2 = 1.0 / var;
  result.within_class_sigma = std::sqrt(var);
  values = nullptr;
  std::vector<float>().swap(copy);

  ctx.alpha = o.alpha;
  ctx.step = std::make_unique<SmoothedStep>(o.alpha);
  ctx.beta = o.overlap_weight;
  {
    const Grid& g = ctx.g;
    double hmax = 1.0;
    for (int c = 0; c < 3; ++c)
      if (g.active[c]) hmax = std::max(hmax, g.h[c]);
    ctx.width = o.band_width > 0 ? o.band_width : o.alpha + 1.5 * hmax;
    ctx.voxel_volume = g.h[0] * g.h[1] * g.h[2];
  }
  ctx.dt = o.dt > 0 ? o.dt : 0.9 * MaxStableTimeStep(o, image);
  ctx.nu.assign(k, o.curvature_weight);
  ctx.e.assign(k, o.fitting_weight);
  if (!o.curvature_weights.empty()) ctx.nu = o.curvature_weights;
  if (!o.fitting_weights.empty()) ctx.e = o.fitting_weights;

  int iteration = 0;
  bool converged = false;
  double energy = 0.0;
  if (o.max_iterations > 0) {
    report_setup(kSetupShare / 2, "initial level sets");
    ctx.ls.resize(k);
    InitializeFromLabels(ctx);
    DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));
    ComputeHeavisideSums(ctx);
    std::vector<float> next;  // band-sized scratch of EvolveLevelSet
    std::vector<int64_t> label_blocks = BandUnion(ctx, nullptr);
    int quiet = 0;
    int64_t reinit_changed = 0;  // labels the last re-initialization changed (0 by design)
    std::vector<double> interface_history;  // for the forecast of the iteration count
    double reported_fraction = kSetupShare;
    while (iteration < o.max_iterations) {
      ++iteration;
      for (int i = 0; i < k; ++i) EvolveLevelSet(ctx, i, next);
      if (!fixed) {
        for (int i = 0; i < k; ++i)
          if (ctx.ls[i].s0 > 0.5) ctx.c[i] = ctx.ls[i].s1 / ctx.ls[i].s0;
      }
      const int64_t changed = Relabel(ctx, label_blocks);
      // Reported energy: Eq. (3) of the current partition (sharp H, so no overlap term; the
      // length is the voxel-face area of the interfaces). Unlike the smoothed energy of the phi_i
      // it is not changed by a re-initialization, which keeps the partition.
      double length = 0.0;
      const int64_t faces = InterfaceFaces(ctx, label_blocks, &length);
      double fitting = 0.0;
      for (int i = 0; i < k; ++i) {
        const double* r = &ctx.region_sums[3 * i];
        fitting += ctx.e[i] * ctx.inv_s2 *
                   std::max(0.0, r[2] - 2.0 * ctx.c[i] * r[1] + ctx.c[i] * ctx.c[i] * r[0]);
      }
      energy = ctx.voxel_volume * fitting + length;
      const double changed_fraction = static_cast<double>(changed) / static_cast<double>(n);
      // Convergence is measured against the interface, not the volume: the changes happen only
      // next to it, so a whole-volume fraction would need a different threshold per image size
      // and shape.
      const double interface_fraction =
          static_cast<double>(changed) / static_cast<double>(std::max<int64_t>(1, faces));
      quiet = interface_fraction < o.convergence_threshold ? quiet + 1 : 0;
      interface_history.push_back(interface_fraction);
      const int expected = segment_internal::ForecastIterations(interface_history, quiet, o);
      // Never backwards: a forecast that grows holds the bar until the iterations catch up.
      reported_fraction =
          std::max(reported_fraction, kSetupShare + (1 - kSetupShare) * iteration / expected);
      Progress p;
      p.stage = "segment";
      p.fraction = std::min(reported_fraction, 0.99);
      p.message = absl::StrFormat("iteration %d of about %d: %d labels changed, energy %.6g",
                                  iteration, expected, changed, energy);
      p.metrics = {{"iteration", iteration},
                   {"energy", energy},
                   {"changed_fraction", changed_fraction},
                   {"interface_changed_fraction", interface_fraction},
                   {"reinit_changed_labels", static_cast<double>(reinit_changed)},
                   {"expected_iterations", expected}};
      reinit_changed = 0;
      Report(progress, p);
      DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));
      if (quiet >= o.convergence_window) {
        converged = true;
        break;
      }
      if (iteration % o.reinit_interval == 0) {
        // label_blocks holds every band since the last re-initialization, so every voxel whose
        // phi or label changed since then.
        // Labels are unchanged, and every voxel outside the new bands is +-W with its label's
        // sign, so only the new bands need relabelling from now on.
        // The Jacobi scratch is not needed during the re-initialization: freeing it keeps the
        // fast-marching queues from adding to the peak memory.
        std::vector<float>().swap(next);
        ReinitializeAll(ctx, label_blocks);
        ComputeHeavisideSums(ctx);
        // Safety net and witness of that invariant: relabel by argmax once (reported).
        reinit_changed = Relabel(ctx, label_blocks);
        label_blocks = BandUnion(ctx, nullptr);
      }
    }
  } else {
    converged = true;
  }
  result.iterations = iteration;
  result.converged = converged;
  result.energy = energy;
  result.class_means = ctx.c;
  // Free the level sets before the distance transform (peak memory).
  ctx.ls.clear();
  ctx.ls.shrink_to_fit();
  segment_internal::CountRegions(k, &result);
  DECIMA_RETURN_IF_ERROR(ComputeInterfaceDistance(result.labels, &result.interface_distance_voxels,
                                                  &result.interface_distance_mm, threads, cancel));
  return result;
}

}  // namespace decima
