// Interface distance of a label volume: exact Euclidean distance from every voxel centre to the
// nearest voxel-centred interface point, i.e. the centre of a face shared by two 6-neighbours
// with different labels.
//
// Face centres lie on three lattices offset by half a voxel along one axis each. For each
// lattice we run the separable squared-distance transform of Felzenszwalb & Huttenlocher
// (lower envelope of parabolas) along the two unshifted axes, then once more along the shifted
// axis, where the parabolas are rooted at half-integer positions and evaluated at the integer
// voxel positions; the minimum over the three lattices is the answer. Cost: 9 linear passes
// per metric, one scratch float per voxel.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/segment/internal.h"
#include "core/segment/segment.h"

namespace decima {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

struct LineScratch {
  std::vector<double> f;
  std::vector<int64_t> v;
  std::vector<double> z;
  void Resize(int64_t n) {
    f.resize(n);
    v.resize(n);
    z.resize(n + 1);
  }
};

// out[p * out_stride] (= or min=) min_q w (p - (q + offset))^2 + f[q] for p in [0, nout), over
// the finite f[q], q in [0, nin). Writes +inf if no f is finite.
void Envelope1D(const double* f, int64_t nin, double offset, double w, float* out,
                int64_t out_stride, int64_t nout, bool take_min, LineScratch& s) {
  int64_t k = -1;
  for (int64_t q = 0; q < nin; ++q) {
    if (!std::isfinite(f[q])) continue;
    const double rq = q + offset;
    while (k >= 0) {
      const int64_t p = s.v[k];
      const double rp = p + offset;
      const double x = ((f[q] + w * rq * rq) - (f[p] + w * rp * rp)) / (2 * w * (rq - rp));
      if (x <= s.z[k]) {
        --k;
      } else {
        ++k;
        s.v[k] = q;
        s.z[k] = x;
        break;
      }
    }
    if (k < 0) {
      k = 0;
      s.v[0] = q;
      s.z[0] = -std::numeric_limits<double>::infinity();
    }
  }
  if (k < 0) {
    if (!take_min)
      for (int64_t p = 0; p < nout; ++p) out[p * out_stride] = kInf;
    return;
  }
  const int64_t last = k;
  s.z[last + 1] = std::numeric_limits<double>::infinity();
  int64_t j = 0;
  for (int64_t p = 0; p < nout; ++p) {
    while (s.z[j + 1] < p) ++j;
    const double d = p - (s.v[j] + offset);
    const float val = static_cast<float>(w * d * d + f[s.v[j]]);
    float& o = out[p * out_stride];
    o = take_min ? std::min(o, val) : val;
  }
}

}  // namespace

namespace segment_internal {

// Squared distance to the face centres of lattice `a`, min-combined into d2 (dims). The faces
// are those between two different labels, or with region >= 0 those between region and the
// rest.
void ShiftedLatticeEdt(const uint8_t* labels, const std::array<int64_t, 3>& dims, int a,
                       const double w[3], int region, std::vector<float>& g, float* d2,
                       int threads) {
  std::array<int64_t, 3> ld = dims;
  ld[a] -= 1;
  const int64_t stride[3] = {1, dims[0], dims[0] * dims[1]};
  const int64_t lstride[3] = {1, ld[0], ld[0] * ld[1]};
  // Seeds: face (m, m+1) along a with different labels.
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t kk = 0; kk < ld[2]; ++kk) {
    for (int64_t jj = 0; jj < ld[1]; ++jj) {
      for (int64_t ii = 0; ii < ld[0]; ++ii) {
        const int64_t x = ii + dims[0] * (jj + dims[1] * kk);
        const uint8_t l0 = labels[x], l1 = labels[x + stride[a]];
        const bool differ = region < 0 ? l0 != l1 : (l0 == region) != (l1 == region);
        g[ii + ld[0] * (jj + ld[1] * kk)] = differ ? 0.0f : kInf;
      }
    }
  }
  // Passes along the unshifted axes, in place on the lattice, then the shifted axis into d2.
  auto pass = [&](int c, bool final_pass) {
    const std::array<int64_t, 3>& n = ld;
    const int64_t nout = final_pass ? dims[c] : n[c];
    const double offset = final_pass ? 0.5 : 0.0;
    float* out = final_pass ? d2 : g.data();
    const int64_t* ostride = final_pass ? stride : lstride;
    if (c == 0) {  // lines along x are contiguous
      const int64_t lines = n[1] * n[2];
#pragma omp parallel num_threads(threads)
      {
        LineScratch s;
        s.Resize(std::max(n[c], dims[c]) + 1);
#pragma omp for schedule(static)
        for (int64_t line = 0; line < lines; ++line) {
          const int64_t u = line % n[1], t = line / n[1];
          const int64_t base = u * lstride[1] + t * lstride[2];
          for (int64_t m = 0; m < n[0]; ++m) s.f[m] = g[base + m];
          const int64_t obase = u * ostride[1] + t * ostride[2];
          Envelope1D(s.f.data(), n[0], offset, w[0], &out[obase], 1, nout, final_pass, s);
        }
      }
      return;
    }
    // Along y or z a line is strided: take kTile neighbouring lines along x at once, so every
    // row read or written is a run of contiguous floats instead of one float per cache line.
    constexpr int64_t kTile = 16;
    const int o = 3 - c;  // the other axis that is not x
    const int64_t tiles = (n[0] + kTile - 1) / kTile, items = tiles * n[o];
#pragma omp parallel num_threads(threads)
    {
      LineScratch s;
      s.Resize(std::max(n[c], dims[c]) + 1);
      std::vector<double> f(kTile * n[c]);
      std::vector<float> result(kTile * nout);
#pragma omp for schedule(static)
      for (int64_t item = 0; item < items; ++item) {
        const int64_t i0 = (item % tiles) * kTile, oi = item / tiles;
        const int64_t count = std::min(kTile, n[0] - i0);
        const int64_t lbase = i0 + oi * lstride[o], obase = i0 + oi * ostride[o];
        for (int64_t m = 0; m < n[c]; ++m) {
          const float* row = &g[lbase + m * lstride[c]];
          for (int64_t j = 0; j < count; ++j) f[j * n[c] + m] = row[j];
        }
        if (final_pass) {  // min-combined with the other lattices
          for (int64_t p = 0; p < nout; ++p) {
            const float* row = &out[obase + p * ostride[c]];
            for (int64_t j = 0; j < count; ++j) result[j * nout + p] = row[j];
          }
        }
        for (int64_t j = 0; j < count; ++j) {
          Envelope1D(&f[j * n[c]], n[c], offset, w[c], &result[j * nout], 1, nout, final_pass, s);
        }
        for (int64_t p = 0; p < nout; ++p) {
          float* row = &out[obase + p * ostride[c]];
          for (int64_t j = 0; j < count; ++j) row[j] = result[j * nout + p];
        }
      }
    }
  };
  for (int c = 0; c < 3; ++c)
    if (c != a) pass(c, false);
  pass(a, true);
}

namespace {

// The voxels of a volume seen along one axis: `outer` slabs of `len` rows of `inner`
// contiguous floats (inner = the axis stride). Along x rows are single voxels, so the passes
// below take lines there instead of rows.
struct AxisRows {
  int64_t outer, len, inner;
};
AxisRows RowsAlong(const std::array<int64_t, 3>& dims, int axis) {
  const int64_t inner = axis == 0 ? 1 : (axis == 1 ? dims[0] : dims[0] * dims[1]);
  return {dims[0] * dims[1] * dims[2] / (inner * dims[axis]), dims[axis], inner};
}

// Runs f(slab, column begin, column end) over the slabs and column chunks of `rows` in
// parallel; along x (inner == 1) a work item is a run of whole lines instead.
template <typename F>
void ForColumnChunks(const AxisRows& rows, int threads, F&& f) {
  constexpr int64_t kChunk = 2048;
  const int64_t chunks = (rows.inner + kChunk - 1) / kChunk;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int64_t w = 0; w < rows.outer * chunks; ++w) {
    const int64_t slab = w / chunks, c0 = (w % chunks) * kChunk;
    f(slab, c0, std::min(rows.inner, c0 + kChunk));
  }
}

// g = squared distance along `axis` (weight h^2) to the nearest face between `region` and the
// rest on the same line, +inf beyond `clamp`.
void LineFaceDistance(const uint8_t* labels, const std::array<int64_t, 3>& dims, int axis, double h,
                      int region, float clamp, float* g, int threads) {
  const AxisRows rows = RowsAlong(dims, axis);
  const float step = static_cast<float>(h);
  // One line along x, or the columns [c0, c1) of the rows of a slab along y or z: stride
  // `along` between positions, `across` between neighbouring lines.
  auto run = [&](int64_t base, int64_t along, int64_t across, int64_t lines) {
    std::vector<float> back(lines);
    auto in = [&](int64_t x) { return labels[x] == region; };
    // Forward: distance to the nearest face before p (in g); backward: after p (in back).
    for (int64_t c = 0; c < lines; ++c) g[base + c * across] = kInf;
    for (int64_t p = 1; p < rows.len; ++p)
      for (int64_t c = 0; c < lines; ++c) {
        const int64_t x = base + p * along + c * across;
        g[x] = in(x - along) != in(x) ? 0.5f * step : g[x - along] + step;
      }
    std::fill(back.begin(), back.end(), kInf);
    for (int64_t p = rows.len - 1; p >= 0; --p)
      for (int64_t c = 0; c < lines; ++c) {
        const int64_t x = base + p * along + c * across;
        if (p + 1 < rows.len) back[c] = in(x) != in(x + along) ? 0.5f * step : back[c] + step;
        const float d = std::min(g[x], back[c]);
        g[x] = d <= clamp ? d * d : kInf;
      }
  };
  if (axis == 0) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t line = 0; line < rows.outer; ++line) run(line * rows.len, 1, 0, 1);
  } else {
    ForColumnChunks(rows, threads, [&](int64_t slab, int64_t c0, int64_t c1) {
      run(slab * rows.len * rows.inner + c0, rows.inner, 1, c1 - c0);
    });
  }
}

// In place along `axis`: g(p) = min over |t| <= reach of g(p + t) + (t h)^2, where
// reach = floor(clamp / h): values beyond the clamp are not needed.
void WindowMin(const std::array<int64_t, 3>& dims, int axis, double h, float clamp, float* g,
               int threads) {
  const AxisRows rows = RowsAlong(dims, axis);
  const int64_t reach = std::min<int64_t>(static_cast<int64_t>(clamp / h), rows.len - 1);
  if (reach <= 0) return;
  std::vector<float> add(reach + 1);
  for (int64_t t = 0; t <= reach; ++t) add[t] = static_cast<float>(t * t * h * h);
  if (axis == 0) {
#pragma omp parallel num_threads(threads)
    {
      std::vector<float> line(rows.len);
#pragma omp for schedule(static)
      for (int64_t l = 0; l < rows.outer; ++l) {
        float* row = g + l * rows.len;
        std::copy(row, row + rows.len, line.begin());
        for (int64_t p = 0; p < rows.len; ++p) {
          float best = line[p];
          for (int64_t t = 1; t <= reach; ++t) {
            if (p - t >= 0) best = std::min(best, line[p - t] + add[t]);
            if (p + t < rows.len) best = std::min(best, line[p + t] + add[t]);
          }
          row[p] = best;
        }
      }
    }
    return;
  }
  ForColumnChunks(rows, threads, [&](int64_t slab, int64_t c0, int64_t c1) {
    const int64_t width = c1 - c0, base = slab * rows.len * rows.inner + c0;
    // Ring of the original values of the last `reach` rows (they are overwritten in place).
    std::vector<float> ring(reach * width), out(width);
    for (int64_t p = 0; p < rows.len; ++p) {
      float* row = g + base + p * rows.inner;
      for (int64_t c = 0; c < width; ++c) out[c] = row[c];
      for (int64_t t = 1; t <= reach; ++t) {
        if (p - t >= 0) {
          const float* before = &ring[((p - t) % reach) * width];
          for (int64_t c = 0; c < width; ++c) out[c] = std::min(out[c], before[c] + add[t]);
        }
        if (p + t < rows.len) {
          const float* after = g + base + (p + t) * rows.inner;
          for (int64_t c = 0; c < width; ++c) out[c] = std::min(out[c], after[c] + add[t]);
        }
      }
      std::copy(row, row + width, &ring[(p % reach) * width]);
      std::copy(out.begin(), out.end(), row);
    }
  });
}

}  // namespace

void RegionSignedDistance(const uint8_t* labels, const std::array<int64_t, 3>& dims,
                          const double h[3], int region, float clamp, float* phi, int threads) {
  const int64_t n = dims[0] * dims[1] * dims[2];
  std::fill(phi, phi + n, kInf);
  std::vector<float> g(n);
  // Per face lattice (faces normal to axis a): the 1D distance along a, then the windowed
  // minimum along the two other axes (the separable squared distance, bounded by the clamp).
  for (int a = 0; a < 3; ++a) {
    if (dims[a] < 2) continue;
    LineFaceDistance(labels, dims, a, h[a], region, clamp, g.data(), threads);
    for (int b = 0; b < 3; ++b)
      if (b != a && dims[b] > 1) WindowMin(dims, b, h[b], clamp, g.data(), threads);
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t x = 0; x < n; ++x) phi[x] = std::min(phi[x], g[x]);
  }
  const float c2 = clamp * clamp;
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t x = 0; x < n; ++x) {
    const float d = phi[x] < c2 ? std::sqrt(phi[x]) : clamp;
    phi[x] = labels[x] == region ? d : -d;
  }
}

}  // namespace segment_internal

absl::Status ComputeInterfaceDistance(const Volume& labels, std::vector<float>* voxels,
                                      std::vector<float>* mm, int threads,
                                      const CancelToken* cancel) {
  DECIMA_RETURN_IF_ERROR(Validate(labels, "interface distance: labels"));
  if (labels.type != VoxelType::kUInt8) {
    return absl::InvalidArgumentError(
        absl::StrCat("interface distance: labels must be uint8, got ", VoxelTypeName(labels.type)));
  }
  const int nt = segment_internal::ResolveThreads(threads);
  const int64_t n = labels.voxel_count();
  const uint8_t* lab = labels.data<uint8_t>();
  std::vector<float> g;
  // Isotropic spacing: the mm distance is the voxel distance times the spacing, one transform.
  const Eigen::Vector3d& sp = labels.spacing;
  const bool isotropic = voxels != nullptr && mm != nullptr && sp[0] == sp[1] && sp[1] == sp[2];
  for (int metric = 0; metric < 2; ++metric) {
    std::vector<float>* out = metric == 0 ? voxels : mm;
    if (out == nullptr) continue;
    if (metric == 1 && isotropic) {
      const float h = static_cast<float>(sp[0]);
      out->resize(n);
      const float* vin = voxels->data();
      float* o = out->data();
#pragma omp parallel for schedule(static) num_threads(nt)
      for (int64_t x = 0; x < n; ++x) o[x] = vin[x] * h;
      continue;
    }
    out->assign(n, kInf);
    double w[3];
    for (int c = 0; c < 3; ++c) w[c] = metric == 0 ? 1.0 : labels.spacing[c] * labels.spacing[c];
    for (int a = 0; a < 3; ++a) {
      if (labels.dims[a] < 2) continue;
      DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "segment"));
      g.resize(n / labels.dims[a] * (labels.dims[a] - 1));
      segment_internal::ShiftedLatticeEdt(lab, labels.dims, a, w, -1, g, out->data(), nt);
    }
    float* o = out->data();
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t x = 0; x < n; ++x) o[x] = std::sqrt(o[x]);
  }
  return absl::OkStatus();
}

namespace segment_internal {

void CountRegions(int k, SegmentResult* result) {
  result->region_voxels.assign(k, 0);
  const uint8_t* lab = result->labels.data<uint8_t>();
  const int64_t n = result->labels.voxel_count();
  for (int64_t x = 0; x < n; ++x) ++result->region_voxels[lab[x]];
  const Eigen::Vector3d& s = result->labels.spacing;
  const double voxel_mm3 = s[0] * s[1] * s[2];
  result->region_volumes_mm3.resize(k);
  for (int i = 0; i < k; ++i) result->region_volumes_mm3[i] = result->region_voxels[i] * voxel_mm3;
}

}  // namespace segment_internal
}  // namespace decima
