// Ray casting through tetrahedral meshes by walking face-adjacent cells, with the exit face
// chosen by 2D orientation tests in screen space (the screen-space form of the Plücker tests of
// Platis & Theoharis 2003: for a ray through pixel point P, the ray passes through a projected
// face iff P is inside the projected triangle). See renderer.h for the model.
#include "core/render/renderer.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <mutex>

#include "absl/strings/str_cat.h"
#include "core/common/parallel.h"
#include "core/common/status.h"
#include "core/mesh/tetrahedralize.h"

namespace decima {
namespace {

using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// Runs fn(range_index, begin, end) over [0, n) split into `ranges` contiguous ranges, one
// thread each (core/common/parallel.h), so per-range outputs can be concatenated in order.
template <typename Fn>
void ParallelRanges(int64_t n, int ranges, Fn&& fn) {
  ranges = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(ranges, n)));
  ParallelFor(ranges, ranges, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) fn(static_cast<int>(r), n * r / ranges, n * (r + 1) / ranges);
  });
}

// Vertices of face q (opposite vertex q) of a positively oriented tet, wound outwards.
constexpr int kFaceVerts[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};

}  // namespace

namespace {

// MeshBounds and MeshScalarRange over bare arrays, shared with the grid so both get the same.
Bounds BoundsOf(const std::vector<float>& positions) {
  Bounds b;
  const int64_t nv = static_cast<int64_t>(positions.size() / 3);
  if (nv == 0) return b;
  const auto position = [&](int64_t v) {
    return Eigen::Vector3d(positions[3 * v], positions[3 * v + 1], positions[3 * v + 2]);
  };
  b.min = b.max = position(0);
  for (int64_t v = 1; v < nv; ++v) {
    const Eigen::Vector3d p = position(v);
    b.min = b.min.cwiseMin(p);
    b.max = b.max.cwiseMax(p);
  }
  return b;
}

ScalarRange ScalarRangeOf(const std::vector<float>& scalars) {
  if (scalars.empty()) return {};
  const auto [lo, hi] = std::minmax_element(scalars.begin(), scalars.end());
  return {*lo, *hi};
}

}  // namespace

Bounds MeshBounds(const TetMesh& mesh) { return BoundsOf(mesh.positions); }

ScalarRange MeshScalarRange(const TetMesh& mesh) { return ScalarRangeOf(mesh.scalars); }

namespace {

// BuildRenderableMesh; with `consume` (== &mesh) the mesh's arrays are freed or moved into the
// result as soon as they are copied, so the mesh and its renderable form never coexist in full.
absl::StatusOr<RenderableMesh> BuildRenderable(const TetMesh& mesh, TetMesh* consume,
                                               const RenderableMeshOptions& options,
                                               const CancelToken* cancel) {
  const int64_t nv = mesh.vertex_count(), nt = mesh.tet_count();
  if (nv < 4 || mesh.positions.size() != size_t(3 * nv) || mesh.tets.size() % 4 != 0 || nt < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("render mesh: ", nv, " scalars, ", mesh.positions.size(),
                     " position floats and ", mesh.tets.size(),
                     " tet indices are not a mesh (need >= 4 vertices, 3 floats each, and "
                     "4 indices per tet)"));
  }
  if (nv > std::numeric_limits<int32_t>::max() || nt >= (int64_t{1} << 29)) {
    return absl::InvalidArgumentError(
        absl::StrCat("render mesh: ", nv, " vertices / ", nt, " tets exceed the 32-bit limits"));
  }
  for (int64_t i = 0; i < 3 * nv; ++i) {
    if (!std::isfinite(mesh.positions[i])) {
      return absl::InvalidArgumentError(
          absl::StrCat("render mesh: vertex ", i / 3, " has a non-finite position"));
    }
  }
  for (int64_t v = 0; v < nv; ++v) {
    if (!std::isfinite(mesh.scalars[v])) {
      return absl::InvalidArgumentError(
          absl::StrCat("render mesh: vertex ", v, " has a non-finite scalar"));
    }
  }
  for (int64_t t = 0; t < nt; ++t) {
    const int32_t* q = &mesh.tets[4 * t];
    for (int i = 0; i < 4; ++i) {
      if (q[i] < 0 || q[i] >= nv) {
        return absl::InvalidArgumentError(
            absl::StrCat("render mesh: tet ", t, " refers to vertex ", q[i], " of ", nv));
      }
      for (int j = 0; j < i; ++j) {
        if (q[i] == q[j]) {
          return absl::InvalidArgumentError(
              absl::StrCat("render mesh: tet ", t, " repeats vertex ", q[i]));
        }
      }
    }
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "render"));

  RenderableMesh out;
  out.bounds = MeshBounds(mesh);
  out.scalar_range = MeshScalarRange(mesh);
  out.cells.resize(8 * nt);
  for (int64_t t = 0; t < nt; ++t) {
    std::copy_n(&mesh.tets[4 * t], 4, &out.cells[8 * t]);
    std::fill_n(&out.cells[8 * t + 4], 4, -1);
  }
  if (consume != nullptr) {
    // The job's original mesh is its largest structure (issue 30): from here on only the
    // positions and scalars are read, and those move instead of being copied.
    out.positions = std::move(consume->positions);
    out.scalars = std::move(consume->scalars);
    *consume = TetMesh();
  } else {
    out.positions = mesh.positions;
    out.scalars = mesh.scalars;
  }
  // Everything below reads the vertices of tet t from cells[8t .. 8t+4) (the same values as
  // mesh.tets) and positions from `out`, so it works on a consumed mesh.
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(out.cells.data(), 8, nv, nt);

  // Every face is matched around its smallest vertex v: both tets sharing it are incident to v,
  // and each (tet, face) record is written by exactly one v, so threads never collide.
  struct Record {
    int32_t b, c, tet;
    int8_t q;
  };
  const int threads = ResolveThreads(options.threads);
  std::vector<std::vector<int32_t>> boundary(threads);
  std::vector<std::string> errors(threads);
  ParallelRanges(nv, threads, [&](int th, int64_t v0, int64_t v1) {
    std::vector<Record> recs;
    for (int64_t v = v0; v < v1 && errors[th].empty(); ++v) {
      recs.clear();
      for (int64_t e = adj.offsets[v]; e < adj.offsets[v + 1]; ++e) {
        const int32_t t = adj.tet_ids[e];
        const int32_t* tv = &out.cells[8 * int64_t{t}];
        for (int q = 0; q < 4; ++q) {
          if (tv[q] == v) continue;  // face q does not contain v
          int32_t o[3], n = 0;
          for (int k = 0; k < 4; ++k)
            if (k != q) o[n++] = tv[k];
          if (std::min({o[0], o[1], o[2]}) != v) continue;
          int32_t b = -1, c = -1;
          for (int k = 0; k < 3; ++k) {
            if (o[k] == v) continue;
            if (b < 0)
              b = o[k];
            else
              c = o[k];
          }
          if (b > c) std::swap(b, c);
          recs.push_back({b, c, t, static_cast<int8_t>(q)});
        }
      }
      std::sort(recs.begin(), recs.end(), [](const Record& x, const Record& y) {
        return x.b != y.b ? x.b < y.b : x.c != y.c ? x.c < y.c : x.tet < y.tet;
      });
      for (size_t i = 0; i < recs.size();) {
        size_t j = i + 1;
        while (j < recs.size() && recs[j].b == recs[i].b && recs[j].c == recs[i].c) ++j;
        if (j - i == 1) {
          boundary[th].push_back(4 * recs[i].tet + recs[i].q);
        } else if (j - i == 2) {
          out.cells[8 * int64_t{recs[i].tet} + 4 + recs[i].q] = recs[i + 1].tet;
          out.cells[8 * int64_t{recs[i + 1].tet} + 4 + recs[i + 1].q] = recs[i].tet;
        } else {
          errors[th] = absl::StrCat("render mesh: face (", v, ", ", recs[i].b, ", ", recs[i].c,
                                    ") is shared by ", j - i, " tets (non-manifold)");
          break;
        }
        i = j;
      }
    }
  });
  for (const std::string& e : errors) {
    if (!e.empty()) return absl::InvalidArgumentError(e);
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "render"));

  for (const auto& part : boundary) {
    for (int32_t code : part) {
      const int64_t t = code >> 2;
      const int q = code & 3;
      const int32_t* tv = &out.cells[8 * t];
      int32_t a = tv[kFaceVerts[q][0]], b = tv[kFaceVerts[q][1]], c = tv[kFaceVerts[q][2]];
      // Wind outwards from the actual geometry, so inverted tets do not flip their faces.
      const auto position = [&](int32_t v) {
        return Eigen::Vector3d(out.positions[3 * int64_t{v}], out.positions[3 * int64_t{v} + 1],
                               out.positions[3 * int64_t{v} + 2]);
      };
      const Eigen::Vector3d pa = position(a);
      const Eigen::Vector3d n = (position(b) - pa).cross(position(c) - pa);
      if (n.dot(position(tv[q]) - pa) > 0) std::swap(b, c);
      out.boundary_faces.push_back(code);
      out.boundary_vertices.insert(out.boundary_vertices.end(), {a, b, c});
    }
  }
  return out;
}

}  // namespace

absl::StatusOr<RenderableMesh> BuildRenderableMesh(const TetMesh& mesh,
                                                   const RenderableMeshOptions& options,
                                                   const CancelToken* cancel) {
  return BuildRenderable(mesh, nullptr, options, cancel);
}

absl::StatusOr<RenderableMesh> BuildRenderableMesh(TetMesh&& mesh,
                                                   const RenderableMeshOptions& options,
                                                   const CancelToken* cancel) {
  return BuildRenderable(mesh, &mesh, options, cancel);
}

absl::StatusOr<RenderableGrid> BuildRenderableGrid(const Volume& image,
                                                   const RenderableMeshOptions& options,
                                                   const CancelToken* cancel) {
  const int64_t nx = image.dims[0], ny = image.dims[1], nz = image.dims[2];
  if (nx < 2 || ny < 2 || nz < 2) {
    return absl::InvalidArgumentError(absl::StrCat("render grid: volume ", Describe(image),
                                                   " needs at least 2 voxels along every axis"));
  }
  const int64_t nv = image.voxel_count(), nt = 5 * (nx - 1) * (ny - 1) * (nz - 1);
  // The same limits as BuildRenderableMesh: entry codes are 4 * tet + face in an int32.
  if (nv > std::numeric_limits<int32_t>::max() || nt >= (int64_t{1} << 29)) {
    return absl::InvalidArgumentError(absl::StrCat("render grid: ", Describe(image), " gives ", nt,
                                                   " tets, beyond the 32-bit limits"));
  }
  RenderableGrid out;
  const Eigen::Matrix3d linear = image.direction * image.spacing.asDiagonal();
  out.grid = GridTets(nx, ny, nz, linear.determinant() < 0);
  out.scalars = image.ToFloat();
  for (int64_t v = 0; v < nv; ++v) {
    if (!std::isfinite(out.scalars[v])) {
      return absl::InvalidArgumentError(
          absl::StrCat("render grid: voxel ", v, " of ", Describe(image), " is not finite"));
    }
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "render"));
  out.positions.resize(3 * nv);
  GridVertexPositions(image, out.positions.data(), options.threads);
  for (int64_t i = 0; i < 3 * nv; ++i) {
    if (!std::isfinite(out.positions[i])) {
      return absl::InvalidArgumentError(
          absl::StrCat("render grid: voxel ", i / 3, " of ", Describe(image),
                       " has a non-finite position (check the origin, spacing and direction)"));
    }
  }
  out.bounds = BoundsOf(out.positions);
  out.scalar_range = ScalarRangeOf(out.scalars);
  return out;
}

namespace {

// A vertex in screen space. Orthographic: a = depth, b = scalar. Perspective: a = 1 / depth,
// b = scalar / depth (perspective-correct interpolation is linear in these).
struct ScreenVertex {
  float x, y, a, b;
};

constexpr double kTiny = 1e-300;

// Orientation of pixel point (px, py) against the projected edge x -> y: twice the signed
// area of (x, y, P). Evaluated in the canonical order (smaller vertex id first) so every tet
// sharing the edge gets the identical number; an exact zero is replaced by the sign the value
// takes when P moves to (px + eps, py + eps^2) (simulation of simplicity), so P is never
// exactly on an edge unless the edge projects to a point.
inline double Orient(const ScreenVertex* sv, int32_t ix, int32_t iy, double px, double py) {
  double sign = 1;
  if (ix > iy) {
    std::swap(ix, iy);
    sign = -1;
  }
  const ScreenVertex& x = sv[ix];
  const ScreenVertex& y = sv[iy];
  const double det =
      (double(x.x) - px) * (double(y.y) - py) - (double(x.y) - py) * (double(y.x) - px);
  if (det != 0) return sign * det;
  if (x.y != y.y) return sign * (x.y > y.y ? kTiny : -kTiny);
  if (x.x != y.x) return sign * (y.x > x.x ? kTiny : -kTiny);
  return 0;
}

// Transfer function prepared for fast lookups. [lo, hi] (first to last control point) is cut
// into kBins uniform bins with the exact colour and opacity at their edges. In a bin without a
// control point inside, the transfer function is linear, so interpolating the edge values is
// exact (up to float rounding); the few bins holding a control point fall back to the exact
// piecewise evaluation. A prefix count of bins with non-zero opacity answers "is the opacity
// zero for every value between s0 and s1" in O(1) (conservatively), so tet segments in
// transparent ranges are skipped without sampling.
class TfTable {
 public:
  explicit TfTable(const TransferFunction& tf) : tf_(&tf) {
    const auto& p = tf.points;
    n_ = static_cast<int>(p.size());
    lo_ = p.front().value;
    hi_ = p.back().value;
    first_ = {p.front().rgb[0], p.front().rgb[1], p.front().rgb[2], p.front().opacity};
    last_ = {p.back().rgb[0], p.back().rgb[1], p.back().rgb[2], p.back().opacity};
    inv_bin_ = n_ > 1 ? kBins / (hi_ - lo_) : 0;
    // Bin ids for the prefix: 0 = below lo, 1..kBins = the bins, kBins + 1 = above hi.
    std::vector<uint8_t> nonzero(kBins + 2, 0);
    nonzero[0] = first_[3] > 0;
    nonzero[kBins + 1] = last_[3] > 0;
    if (n_ > 1) {
      edges_.resize(kBins + 1);
      kink_.assign(kBins, 0);
      for (int k = 0; k <= kBins; ++k) {
        float rgb[3], o;
        tf.Evaluate(k == kBins ? hi_ : lo_ + (hi_ - lo_) * k / kBins, rgb, &o);
        edges_[k] = {rgb[0], rgb[1], rgb[2], o};
      }
      for (int k = 0; k < kBins; ++k) nonzero[k + 1] = edges_[k][3] > 0 || edges_[k + 1][3] > 0;
      for (int i = 1; i + 1 < n_; ++i) {
        const int k = std::clamp(static_cast<int>((p[i].value - lo_) * inv_bin_), 0, kBins - 1);
        kink_[k] = 1;
        if (p[i].opacity > 0) nonzero[k + 1] = 1;
        // A control point exactly on a bin edge leaves both bins linear; marking is harmless.
      }
    }
    nonzero_prefix_.assign(kBins + 3, 0);
    for (int id = 0; id < kBins + 2; ++id)
      nonzero_prefix_[id + 1] = nonzero_prefix_[id] + nonzero[id];
  }

  // True if the opacity is zero for every value between s0 and s1 (false when unsure).
  bool Transparent(double s0, double s1) const {
    if (s0 > s1) std::swap(s0, s1);
    return nonzero_prefix_[BinId(s1) + 1] == nonzero_prefix_[BinId(s0)];
  }

  void Eval(double s, float* r, float* g, float* b, float* o) const {
    const std::array<float, 4>* v;
    std::array<float, 4> tmp;
    if (s <= lo_ || n_ == 1) {
      v = s <= lo_ ? &first_ : &last_;
    } else if (s >= hi_) {
      v = &last_;
    } else {
      const double u = (s - lo_) * inv_bin_;
      const int k = std::min(static_cast<int>(u), kBins - 1);
      if (kink_[k]) {
        float rgb[3];
        tf_->Evaluate(s, rgb, &tmp[3]);
        std::copy_n(rgb, 3, tmp.begin());
      } else {
        const float f = static_cast<float>(u - k);
        const auto& e0 = edges_[k];
        const auto& e1 = edges_[k + 1];
        for (int c = 0; c < 4; ++c) tmp[c] = e0[c] + f * (e1[c] - e0[c]);
      }
      v = &tmp;
    }
    *r = (*v)[0];
    *g = (*v)[1];
    *b = (*v)[2];
    *o = (*v)[3];
  }

 private:
  static constexpr int kBins = 2048;
  int BinId(double s) const {
    if (s < lo_) return 0;
    if (s > hi_ || n_ == 1) return kBins + 1;
    return 1 + std::min(static_cast<int>((s - lo_) * inv_bin_), kBins - 1);
  }

  const TransferFunction* tf_;
  int n_ = 0;
  double lo_ = 0, hi_ = 0, inv_bin_ = 0;
  std::array<float, 4> first_{}, last_{};
  std::vector<std::array<float, 4>> edges_;
  std::vector<uint8_t> kink_;
  std::vector<int> nonzero_prefix_;
};

// Colour and transmittance of one ray, front to back.
struct Accum {
  float r = 0, g = 0, b = 0, t = 1;
};

// Integrates the segment where the scalar goes linearly from s0 to s1 over `len` mm, with
// n = floor(len / step) + 1 midpoint samples (so at most `step` apart; inv_step = 1 / step).
inline void IntegrateSegment(const TfTable& tf, double s0, double s1, double len, double inv_step,
                             Accum& acc) {
  if (!(len > 0) || tf.Transparent(s0, s1)) return;
  const int n = static_cast<int>(std::min(65535.0, len * inv_step)) + 1;
  const double inv_n = 1.0 / n;
  const float dl = static_cast<float>(len * inv_n);
  const double ds = (s1 - s0) * inv_n;
  double s = s0 + 0.5 * ds;
  for (int i = 0; i < n; ++i, s += ds) {
    float r, g, b, o;
    tf.Eval(s, &r, &g, &b, &o);
    if (o <= 0) continue;
    const float a = 1.0f - std::exp(-o * dl);
    const float w = acc.t * a;
    acc.r += w * r;
    acc.g += w * g;
    acc.b += w * b;
    acc.t -= w;
  }
}

struct Entry {
  float depth;
  int32_t code;  // 4 * tet + local face
};

// Cell sources of the one ray-casting loop. A Place is where a walk is: At(t) makes it from a tet
// id, Id gives the id back, Vertices the 4 vertex ids (a pointer into the source's own array or
// into `buf`), and Step moves it across face q (false, unmoved, on the hull); ForEachCell(t0, t1,
// f) calls f(t, vertices) for a run of ids in order (the grid steps instead of decoding each).
// A materialized mesh: RenderableMesh::cells, 8 ints per tet, the Place is the tet id.
struct MeshCells {
  using Place = int32_t;
  const int32_t* cells;
  Place At(int64_t t) const { return static_cast<int32_t>(t); }
  int64_t Id(Place p) const { return p; }
  const int32_t* Vertices(Place p, int32_t* /*buf*/) const { return &cells[8 * int64_t{p}]; }
  template <typename F>
  void ForEachCell(int64_t t0, int64_t t1, F&& f) const {
    for (int64_t t = t0; t < t1; ++t) f(t, &cells[8 * t]);
  }
  bool Step(Place& p, int q) const {
    const int32_t n = cells[8 * int64_t{p} + 4 + q];
    if (n < 0) return false;
    p = n;
    return true;
  }
};

// The original grid: vertices and neighbours computed from the tet's cube (GridTets::Place, so a
// step costs no division), nothing read per tet.
struct GridCells {
  using Place = GridTets::Place;
  const GridTets* grid;
  Place At(int64_t t) const { return grid->At(t); }
  int64_t Id(const Place& p) const { return grid->Id(p); }
  const int32_t* Vertices(const Place& p, int32_t* buf) const {
    grid->Cell(p, buf);
    return buf;
  }
  bool Step(Place& p, int q) const { return grid->Step(p, q); }
  template <typename F>
  void ForEachCell(int64_t t0, int64_t t1, F&& f) const {
    grid->ForEachCell(t0, t1, f);
  }
};

// What Render reads of its input besides the cells.
struct RenderInput {
  const float* positions;
  const float* scalars;
  int64_t nv = 0, nt = 0;
  // The hull's faces and their outward vertices (RenderableMesh's), or nullptr: then the entry
  // faces of a fully visible mesh are found from the neighbours, the same set.
  const std::vector<int32_t>* boundary_faces = nullptr;
  const std::vector<int32_t>* boundary_vertices = nullptr;
};

// Visibility of tet t in a bit per tet (see Render).
inline bool VisibleBit(const uint64_t* bits, int64_t t) { return (bits[t >> 6] >> (t & 63)) & 1; }

template <typename Cells>
struct Frame {
  Cells cells;
  const ScreenVertex* sv;
  const TfTable* tf;
  const RenderOptions* options;
  const Camera* camera;
  // Per tet a bit: 1 if the transfer function is non-zero somewhere on its scalar range; nullptr
  // when every tet is.
  const uint64_t* visible = nullptr;
  std::vector<int64_t> entry_offsets;  // per pixel, CSR into entries
  std::vector<Entry> entries;
};

// Depth and scalar at the point with screen barycentrics (la, lb, lc) of vertices a, b, c.
template <bool kPersp>
inline void Interpolate(const ScreenVertex* sv, int32_t a, int32_t b, int32_t c, double la,
                        double lb, double lc, double* depth, double* scalar) {
  const double sum = la + lb + lc;
  if (!(sum > 0)) {
    la = lb = lc = 1.0 / 3;
  } else {
    la /= sum;
    lb /= sum;
    lc /= sum;
  }
  const double A = la * sv[a].a + lb * sv[b].a + lc * sv[c].a;
  const double B = la * sv[a].b + lb * sv[b].b + lc * sv[c].b;
  if constexpr (kPersp) {
    *depth = 1.0 / A;
    *scalar = B / A;
  } else {
    *depth = A;
    *scalar = B;
  }
}

// Walks one ray from boundary entry `e` until it leaves the mesh or becomes opaque.
// Returns the depth where it left.
template <bool kPersp, typename Cells>
double Walk(const Frame<Cells>& f, Entry e, double px, double py, double len_per_depth, Accum& acc,
            RenderStats& stats, bool* lost) {
  const Cells& cells = f.cells;
  int32_t buf[4];
  const ScreenVertex* sv = f.sv;
  const double inv_step = 1.0 / f.options->step_mm;
  const float tmin = f.options->min_transmittance;

  typename Cells::Place place = cells.At(e.code >> 2);
  const int eq = e.code & 3;
  const int32_t* cell = cells.Vertices(place, buf);
  int32_t a = cell[kFaceVerts[eq][0]], b = cell[kFaceVerts[eq][1]], c = cell[kFaceVerts[eq][2]];
  double eab = Orient(sv, a, b, px, py), ebc = Orient(sv, b, c, px, py),
         eca = Orient(sv, c, a, px, py);
  // Orient all edge values so the current entry face's are positive; the walk keeps this.
  const double sigma = (eab + ebc + eca) < 0 ? -1.0 : 1.0;
  eab *= sigma;
  ebc *= sigma;
  eca *= sigma;
  double depth, scalar;
  Interpolate<kPersp>(sv, a, b, c, std::max(ebc, 0.0), std::max(eca, 0.0), std::max(eab, 0.0),
                      &depth, &scalar);

  int stuck = 0;
  for (;;) {
    cell = cells.Vertices(place, buf);
    int qa = 0, qb = 0, qc = 0, qd = 0;
    for (int q = 0; q < 4; ++q) {
      const int32_t v = cell[q];
      if (v == a)
        qa = q;
      else if (v == b)
        qb = q;
      else if (v == c)
        qc = q;
      else
        qd = q;
    }
    const int32_t d = cell[qd];
    const double ead = sigma * Orient(sv, a, d, px, py);
    const double ebd = sigma * Orient(sv, b, d, px, py);
    const double ecd = sigma * Orient(sv, c, d, px, py);
    // The ray leaves through the face (among abd, bcd, cad) whose three edge values are all
    // positive; the smallest of the three measures how far P is inside it. Exactly one face
    // qualifies unless rounding made the signs inconsistent, then the best one is taken.
    const double m_abd = std::min({eab, ebd, -ead});
    const double m_bcd = std::min({ebc, ecd, -ebd});
    const double m_cad = std::min({eca, ead, -ecd});
    double next_depth, next_scalar;
    int exit_q;
    if (m_abd >= m_bcd && m_abd >= m_cad) {
      if (!(m_abd > 0)) ++stats.fallback_steps;
      Interpolate<kPersp>(sv, a, b, d, std::max(ebd, 0.0), std::max(-ead, 0.0), std::max(eab, 0.0),
                          &next_depth, &next_scalar);
      exit_q = qc;
      c = d;
      ebc = ebd;
      eca = -ead;
    } else if (m_bcd >= m_cad) {
      if (!(m_bcd > 0)) ++stats.fallback_steps;
      Interpolate<kPersp>(sv, b, c, d, std::max(ecd, 0.0), std::max(-ebd, 0.0), std::max(ebc, 0.0),
                          &next_depth, &next_scalar);
      exit_q = qa;
      // New entry face (b, c, d) renamed to (a, b, c).
      a = b;
      b = c;
      c = d;
      eab = ebc;
      ebc = ecd;
      eca = -ebd;
    } else {
      if (!(m_cad > 0)) ++stats.fallback_steps;
      Interpolate<kPersp>(sv, c, a, d, std::max(ead, 0.0), std::max(-ecd, 0.0), std::max(eca, 0.0),
                          &next_depth, &next_scalar);
      exit_q = qb;
      // New entry face (c, a, d) renamed to (a, b, c).
      const int32_t old_a = a;
      a = c;
      b = old_a;
      c = d;
      eab = eca;
      ebc = ead;
      eca = -ecd;
    }
    ++stats.steps;
    if (next_depth > depth) {
      IntegrateSegment(*f.tf, scalar, next_scalar, (next_depth - depth) * len_per_depth, inv_step,
                       acc);
      depth = next_depth;
      stuck = 0;
    } else if (++stuck > 4096) {
      *lost = true;
      return depth;
    }
    scalar = next_scalar;
    if (acc.t < tmin) return depth;
    if (!cells.Step(place, exit_q)) return depth;
    if (f.visible != nullptr && !VisibleBit(f.visible, cells.Id(place))) return depth;
  }
}

template <bool kPersp, typename Cells>
void RenderTile(const Frame<Cells>& f, int x0, int y0, int x1, int y1, RenderedImage& img,
                RenderStats& stats) {
  const Camera& cam = *f.camera;
  const double s = cam.Scale();
  const auto& bg = f.options->background;
  for (int y = y0; y < y1; ++y) {
    for (int x = x0; x < x1; ++x) {
      const int64_t pix = int64_t{y} * img.width + x;
      Accum acc;
      const int64_t e0 = f.entry_offsets[pix], e1 = f.entry_offsets[pix + 1];
      if (e1 > e0) {
        ++stats.rays_hit;
        double len_per_depth = 1;
        if constexpr (kPersp) {
          const double u = (x - 0.5 * (cam.width - 1)) / s, v = (0.5 * (cam.height - 1) - y) / s;
          len_per_depth = std::sqrt(1 + u * u + v * v);
        }
        double depth = -std::numeric_limits<double>::infinity();
        bool lost = false;
        for (int64_t k = e0; k < e1 && acc.t >= f.options->min_transmittance && !lost; ++k) {
          if (f.entries[k].depth < depth) continue;  // already inside when passing it
          depth = Walk<kPersp>(f, f.entries[k], x, y, len_per_depth, acc, stats, &lost);
        }
        if (lost) ++stats.lost_rays;
      }
      img.rgb[3 * pix + 0] = acc.r + acc.t * bg[0];
      img.rgb[3 * pix + 1] = acc.g + acc.t * bg[1];
      img.rgb[3 * pix + 2] = acc.b + acc.t * bg[2];
      img.alpha[pix] = 1 - acc.t;
    }
  }
}

absl::Status ValidateCamera(const Camera& c) {
  if (c.width < 1 || c.width > 8192 || c.height < 1 || c.height > 8192) {
    return absl::InvalidArgumentError(
        absl::StrCat("camera: image size ", c.width, "x", c.height, " is not in 1..8192"));
  }
  const double tol = 1e-6;
  if (!c.eye.allFinite() || !c.forward.allFinite() || !c.up.allFinite() || !c.right.allFinite() ||
      std::abs(c.forward.norm() - 1) > tol || std::abs(c.up.norm() - 1) > tol ||
      std::abs(c.forward.dot(c.up)) > tol || (c.forward.cross(c.up) - c.right).norm() > 1e-5) {
    return absl::InvalidArgumentError(
        "camera: forward and up must be finite orthonormal vectors and right = forward x up");
  }
  if (c.perspective && !(c.fov_y_deg > 0 && c.fov_y_deg < 180)) {
    return absl::InvalidArgumentError(
        absl::StrCat("camera: fov_y_deg ", c.fov_y_deg, " is not in (0, 180)"));
  }
  if (!c.perspective && !(c.ortho_width_mm > 0 && std::isfinite(c.ortho_width_mm))) {
    return absl::InvalidArgumentError(
        absl::StrCat("camera: ortho_width_mm ", c.ortho_width_mm, " must be finite and > 0"));
  }
  return absl::OkStatus();
}

}  // namespace

Image RenderedImage::ToImage() const {
  Image out;
  out.width = width;
  out.height = height;
  out.channels = 3;
  out.pixels.resize(rgb.size());
  for (size_t i = 0; i < rgb.size(); ++i) {
    out.pixels[i] = static_cast<uint8_t>(std::lround(std::clamp(rgb[i], 0.0f, 1.0f) * 255.0f));
  }
  return out;
}

absl::Status WriteRenderedPng(const RenderedImage& image, const std::filesystem::path& path) {
  return WritePng(path, image.ToImage());
}

namespace {

// The one Render, over either cell source.
template <typename Cells>
absl::StatusOr<RenderedImage> RenderCells(const RenderInput& mesh, const Cells& cells,
                                          const Camera& camera, const TransferFunction& tf,
                                          const RenderOptions& options, const CancelToken* cancel) {
  const auto start = Clock::now();
  DECIMA_RETURN_IF_ERROR(ValidateCamera(camera));
  DECIMA_RETURN_IF_ERROR(tf.Validate());
  if (!(options.step_mm >= 1e-3 && std::isfinite(options.step_mm))) {
    return absl::InvalidArgumentError(
        absl::StrCat("render: step_mm ", options.step_mm, " must be finite and >= 0.001"));
  }
  for (float c : options.background) {
    if (!(c >= 0 && c <= 1)) {
      return absl::InvalidArgumentError("render: background components must be in 0..1");
    }
  }
  if (!(options.min_transmittance >= 0 && options.min_transmittance < 1)) {
    return absl::InvalidArgumentError("render: min_transmittance must be in [0, 1)");
  }
  if (mesh.nt == 0) return absl::InvalidArgumentError("render: the mesh has no tets");

  RenderedImage img;
  img.width = camera.width;
  img.height = camera.height;
  const int64_t npix = int64_t{img.width} * img.height;
  img.rgb.resize(3 * npix);
  img.alpha.assign(npix, 0);
  for (int64_t p = 0; p < npix; ++p) std::copy_n(options.background.begin(), 3, &img.rgb[3 * p]);
  const int threads = ResolveThreads(options.threads);

  // Project every vertex; count those on or behind the camera plane.
  const int64_t nv = mesh.nv;
  std::vector<ScreenVertex> sv(nv);
  std::vector<int64_t> behind(threads, 0);
  ParallelRanges(nv, threads, [&](int th, int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      const Eigen::Vector3d p(mesh.positions[3 * v], mesh.positions[3 * v + 1],
                              mesh.positions[3 * v + 2]);
      const Eigen::Vector3d q = camera.Project(p);
      if (!(q.z() > 0) || !q.allFinite()) {
        ++behind[th];
        sv[v] = {0, 0, 0, 0};
        continue;
      }
      const double s = mesh.scalars[v];
      if (camera.perspective) {
        sv[v] = {float(q.x()), float(q.y()), float(1.0 / q.z()), float(s / q.z())};
      } else {
        sv[v] = {float(q.x()), float(q.y()), float(q.z()), float(s)};
      }
    }
  });
  int64_t n_behind = 0;
  for (int64_t b : behind) n_behind += b;
  if (n_behind == nv) {
    img.stats.seconds = Since(start);
    return img;  // looking away: empty image
  }
  if (n_behind > 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "render: ", n_behind, " of ", nv,
        " vertices are on or behind the camera plane; move the camera out of the mesh"));
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "render"));

  Frame<Cells> f;
  f.cells = cells;
  f.sv = sv.data();
  TfTable table(tf);
  f.tf = &table;
  f.options = &options;
  f.camera = &camera;

  // Empty-space skipping: a tet whose scalar range the transfer function maps to zero opacity
  // adds nothing to any ray, so rays only walk the visible tets. They enter through visible
  // tets' faces on the hull or next to an invisible tet, and stop when the next tet is
  // invisible; a later entry on the same pixel continues the ray behind the gap. The image is
  // the same as walking every tet (the skipped segments integrate to zero).
  // One bit per tet (1/8 of a byte array: the grid's original holds nothing else per tet), written
  // a 64-bit word per tet block so threads never share a word.
  const int64_t nt = mesh.nt;
  const int64_t nwords = (nt + 63) / 64;
  std::vector<uint64_t> visible(nwords);
  std::vector<int64_t> visible_count(threads, 0);
  ParallelRanges(nwords, threads, [&](int th, int64_t w0, int64_t w1) {
    int64_t n = 0;
    for (int64_t w = w0; w < w1; ++w) {
      uint64_t word = 0;
      cells.ForEachCell(64 * w, std::min(nt, 64 * (w + 1)), [&](int64_t t, const int32_t* c) {
        const float s0 = mesh.scalars[c[0]], s1 = mesh.scalars[c[1]], s2 = mesh.scalars[c[2]],
                    s3 = mesh.scalars[c[3]];
        const bool vis = !table.Transparent(std::min({s0, s1, s2, s3}), std::max({s0, s1, s2, s3}));
        word |= uint64_t{vis} << (t - 64 * w);
        n += vis;
      });
      visible[w] = word;
    }
    visible_count[th] = n;
  });
  int64_t n_visible = 0;
  for (int64_t n : visible_count) n_visible += n;
  img.stats.visible_tets = n_visible;
  f.visible = n_visible == nt ? nullptr : visible.data();

  // Entry faces (4 * tet + q) with their vertices wound outwards from the visible tet: a fully
  // visible mesh with a stored hull enters through it, anything else through the faces of
  // visible tets whose neighbour is absent or invisible (for a fully visible mesh, its hull).
  const bool hull_list = n_visible == nt && mesh.boundary_faces != nullptr;
  std::vector<std::vector<int32_t>> entry_parts(threads);
  if (hull_list) {
    const int64_t nb = static_cast<int64_t>(mesh.boundary_faces->size());
    for (int th = 0; th < threads; ++th) {
      for (int64_t i = nb * th / threads; i < nb * (th + 1) / threads; ++i) {
        entry_parts[th].push_back(int32_t(i));
      }
    }
  } else if (n_visible > 0) {
    ParallelRanges(nt, threads, [&](int th, int64_t t0, int64_t t1) {
      for (int64_t t = t0; t < t1; ++t) {
        if (!VisibleBit(visible.data(), t)) continue;
        const typename Cells::Place here = cells.At(t);
        for (int q = 0; q < 4; ++q) {
          typename Cells::Place next = here;
          if (!cells.Step(next, q) || !VisibleBit(visible.data(), cells.Id(next))) {
            entry_parts[th].push_back(int32_t(4 * t + q));
          }
        }
      }
    });
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "render"));

  // Rasterize the front-facing entry faces: each pixel gets the faces where its ray enters.
  struct PixelEntry {
    int64_t pix;
    Entry e;
  };
  std::vector<std::vector<PixelEntry>> raw_parts(threads);
  ParallelRanges(threads, threads, [&](int th, int64_t, int64_t) {
    std::vector<PixelEntry>& raw = raw_parts[th];
    for (const int32_t item : entry_parts[th]) {
      int32_t code, fv[3], buf[4];
      if (hull_list) {
        code = (*mesh.boundary_faces)[item];
        std::copy_n(&(*mesh.boundary_vertices)[3 * int64_t{item}], 3, fv);
      } else {
        code = item;
        const int32_t* c = cells.Vertices(cells.At(code >> 2), buf);
        const int q = code & 3;
        for (int k = 0; k < 3; ++k) fv[k] = c[kFaceVerts[q][k]];
        // Wind outwards from the actual geometry, so inverted tets do not flip their faces.
        const float* P = mesh.positions;
        auto pos = [&](int32_t v) {
          return Eigen::Vector3d(P[3 * int64_t{v}], P[3 * int64_t{v} + 1], P[3 * int64_t{v} + 2]);
        };
        const Eigen::Vector3d pa = pos(fv[0]);
        const Eigen::Vector3d n = (pos(fv[1]) - pa).cross(pos(fv[2]) - pa);
        if (n.dot(pos(c[q]) - pa) > 0) std::swap(fv[1], fv[2]);
      }
      const ScreenVertex &A = sv[fv[0]], &B = sv[fv[1]], &C = sv[fv[2]];
      const double area =
          (double(B.x) - A.x) * (double(C.y) - A.y) - (double(B.y) - A.y) * (double(C.x) - A.x);
      // Outward-wound faces facing the viewer have negative area in (x right, y down) pixels.
      if (!(area < 0)) continue;
      const double minx = std::min({A.x, B.x, C.x}), maxx = std::max({A.x, B.x, C.x});
      const double miny = std::min({A.y, B.y, C.y}), maxy = std::max({A.y, B.y, C.y});
      const int x0 = std::max(0, int(std::ceil(std::max(minx, -1.0)))),
                x1 = std::min(img.width - 1, int(std::floor(std::min(maxx, 1e9))));
      const int y0 = std::max(0, int(std::ceil(std::max(miny, -1.0)))),
                y1 = std::min(img.height - 1, int(std::floor(std::min(maxy, 1e9))));
      for (int y = y0; y <= y1; ++y) {
        for (int x = x0; x <= x1; ++x) {
          const double e0 = Orient(f.sv, fv[1], fv[2], x, y), e1 = Orient(f.sv, fv[2], fv[0], x, y),
                       e2 = Orient(f.sv, fv[0], fv[1], x, y);
          if (!((e0 < 0 && e1 < 0 && e2 < 0) || (e0 > 0 && e1 > 0 && e2 > 0))) continue;
          double depth, scalar;
          if (camera.perspective) {
            Interpolate<true>(f.sv, fv[0], fv[1], fv[2], std::abs(e0), std::abs(e1), std::abs(e2),
                              &depth, &scalar);
          } else {
            Interpolate<false>(f.sv, fv[0], fv[1], fv[2], std::abs(e0), std::abs(e1), std::abs(e2),
                               &depth, &scalar);
          }
          raw.push_back({int64_t{y} * img.width + x, {float(depth), code}});
        }
      }
    }
  });
  entry_parts.clear();
  entry_parts.shrink_to_fit();
  f.entry_offsets.assign(npix + 1, 0);
  int64_t n_raw = 0;
  for (const auto& raw : raw_parts) {
    n_raw += static_cast<int64_t>(raw.size());
    for (const PixelEntry& r : raw) ++f.entry_offsets[r.pix + 1];
  }
  for (int64_t p = 0; p < npix; ++p) f.entry_offsets[p + 1] += f.entry_offsets[p];
  f.entries.resize(n_raw);
  {
    std::vector<int64_t> cursor(f.entry_offsets.begin(), f.entry_offsets.end() - 1);
    for (const auto& raw : raw_parts)
      for (const PixelEntry& r : raw) f.entries[cursor[r.pix]++] = r.e;
  }
  raw_parts.clear();
  raw_parts.shrink_to_fit();
  // Entries of a pixel front to back (ties by code, so the order never depends on threads).
  ParallelRanges(npix, threads, [&](int, int64_t p0, int64_t p1) {
    for (int64_t p = p0; p < p1; ++p) {
      if (f.entry_offsets[p + 1] - f.entry_offsets[p] > 1) {
        std::sort(f.entries.begin() + f.entry_offsets[p],
                  f.entries.begin() + f.entry_offsets[p + 1], [](const Entry& x, const Entry& y) {
                    return x.depth != y.depth ? x.depth < y.depth : x.code < y.code;
                  });
      }
    }
  });
  img.stats.entry_faces = n_raw;
  img.stats.raster_seconds = Since(start);
  img.empty = f.entries.empty();

  // Tiles handed out dynamically; each writes only its own pixels.
  constexpr int kTile = 16;
  const int tiles_x = (img.width + kTile - 1) / kTile, tiles_y = (img.height + kTile - 1) / kTile;
  const int ntiles = tiles_x * tiles_y;
  std::atomic<int> next{0};
  std::atomic<bool> cancelled{false};
  std::mutex stats_mu;
  RenderStats total = img.stats;
  auto worker = [&] {
    RenderStats local;
    for (int tile; (tile = next.fetch_add(1)) < ntiles;) {
      if (cancel != nullptr && cancel->cancelled()) {
        cancelled = true;
        break;
      }
      const int tx = tile % tiles_x, ty = tile / tiles_x;
      const int x0 = tx * kTile, y0 = ty * kTile;
      const int x1 = std::min(img.width, x0 + kTile), y1 = std::min(img.height, y0 + kTile);
      if (camera.perspective) {
        RenderTile<true>(f, x0, y0, x1, y1, img, local);
      } else {
        RenderTile<false>(f, x0, y0, x1, y1, img, local);
      }
    }
    std::lock_guard<std::mutex> lock(stats_mu);
    total.rays_hit += local.rays_hit;
    total.steps += local.steps;
    total.fallback_steps += local.fallback_steps;
    total.lost_rays += local.lost_rays;
  };
  const int workers = std::max(1, std::min(threads, ntiles));
  ParallelFor(workers, workers, [&](int64_t w0, int64_t w1) {
    for (int64_t w = w0; w < w1; ++w) worker();
  });
  if (cancelled) return absl::CancelledError("render: cancelled");
  img.stats = total;
  img.stats.seconds = Since(start);
  return img;
}

}  // namespace

absl::StatusOr<RenderedImage> Render(const RenderableMesh& mesh, const Camera& camera,
                                     const TransferFunction& tf, const RenderOptions& options,
                                     const CancelToken* cancel) {
  RenderInput in;
  in.positions = mesh.positions.data();
  in.scalars = mesh.scalars.data();
  in.nv = mesh.vertex_count();
  in.nt = mesh.tet_count();
  in.boundary_faces = &mesh.boundary_faces;
  in.boundary_vertices = &mesh.boundary_vertices;
  return RenderCells(in, MeshCells{mesh.cells.data()}, camera, tf, options, cancel);
}

absl::StatusOr<RenderedImage> Render(const RenderableGrid& grid, const Camera& camera,
                                     const TransferFunction& tf, const RenderOptions& options,
                                     const CancelToken* cancel) {
  if (grid.positions.size() != size_t(3 * grid.vertex_count()) ||
      grid.vertex_count() != grid.grid.vertex_count()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "render grid: ", grid.vertex_count(), " scalars and ", grid.positions.size(),
        " position floats do not fit a grid of ", grid.grid.vertex_count(), " vertices"));
  }
  RenderInput in;
  in.positions = grid.positions.data();
  in.scalars = grid.scalars.data();
  in.nv = grid.vertex_count();
  in.nt = grid.tet_count();
  return RenderCells(in, GridCells{&grid.grid}, camera, tf, options, cancel);
}

absl::StatusOr<RenderedImage> Render(const TetMesh& mesh, const Camera& camera,
                                     const TransferFunction& tf, const RenderOptions& options,
                                     const CancelToken* cancel) {
  RenderableMeshOptions build;
  build.threads = options.threads;
  DECIMA_ASSIGN_OR_RETURN(RenderableMesh rm, BuildRenderableMesh(mesh, build, cancel));
  return Render(rm, camera, tf, options, cancel);
}

}  // namespace decima
