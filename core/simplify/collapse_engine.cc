// Cell collapse with the feature-preserving rules of:
//   Feature Preserving Volumetric Data Simplification for Application in Medical Imaging,
//   §2.2 (rules 1-6, Eq. 5-8, the greedy loop), and the baseline
//   Chopra, Meyer: TetFusion, an algorithm for rapid tetrahedral mesh simplification (2002).
// Interpretations of the paper and the departures from it are listed in README.md beside this
// file.
#include "core/simplify/collapse_engine.h"
#include "core/common/parallel.h"

#include <algorithm>
#include <bit>
#include <cfloat>
#include <cmath>
#include <cstring>
#include <numeric>
#include <thread>

#include "core/mesh/tetrahedralize.h"

namespace decima::simplify_internal {
namespace {

// Cell loops run in ranges of at least this many cells (thread start-up is not free).
constexpr int64_t kCellChunk = 4096;

// 6 * signed volume of (a, b, c, d) from float coordinates, in double.
inline double Orient6(const float* a, const float* b, const float* c, const float* d) {
  const double bx = double(b[0]) - a[0], by = double(b[1]) - a[1], bz = double(b[2]) - a[2];
  const double cx = double(c[0]) - a[0], cy = double(c[1]) - a[1], cz = double(c[2]) - a[2];
  const double dx = double(d[0]) - a[0], dy = double(d[1]) - a[1], dz = double(d[2]) - a[2];
  return bx * (cy * dz - cz * dy) - by * (cx * dz - cz * dx) + bz * (cx * dy - cy * dx);
}

// Queue key of an error: non-negative floats order like their bit patterns.
inline uint32_t FloatKey(float e) {
  if (!(e < FLT_MAX)) e = FLT_MAX;  // also NaN
  if (e < 0) e = 0;
  uint32_t bits;
  std::memcpy(&bits, &e, 4);
  return bits;
}
inline float KeyFloat(uint32_t key) {
  float e;
  std::memcpy(&e, &key, 4);
  return e;
}

constexpr uint32_t kNotCandidate = 0xFFFFFFFFu;

// Prefetch distances of the greedy loop, in queue entries.
constexpr size_t kFarAhead = 16, kNearAhead = 8;

// A way to delete τ: merge the vertices of τ in `mask` (two or more) into one point with
// barycentric weights `w` (zero outside the mask). Row 0 of the free merges is the paper's
// rule 1: all four at the centroid. The others widen it (README): all four at a face centroid,
// edge midpoint or vertex; three at their centroid, an edge midpoint or a vertex; two (an edge)
// at its midpoint or an end.
struct Merge {
  uint8_t mask;
  double w[4];
};

std::vector<Merge> BuildFreeMerges() {
  std::vector<Merge> out;
  auto add = [&](unsigned mask, std::initializer_list<int> at) {
    Merge m{uint8_t(mask), {0, 0, 0, 0}};
    for (int k : at) m.w[k] += 1.0 / double(at.size());
    out.push_back(m);
  };
  for (unsigned mask : {0xFu, 0xEu, 0xDu, 0xBu, 0x7u, 0x3u, 0x5u, 0x9u, 0x6u, 0xAu, 0xCu}) {
    int s[4], n = 0;
    for (int k = 0; k < 4; ++k)
      if (mask & (1u << k)) s[n++] = k;
    if (n == 4) {
      add(mask, {0, 1, 2, 3});
      for (int k = 3; k >= 0; --k) add(mask, {(k + 1) % 4, (k + 2) % 4, (k + 3) % 4});
    } else if (n == 3) {
      add(mask, {s[0], s[1], s[2]});
    }
    if (n >= 3) {
      for (int i = 0; i < n; ++i)
        for (int j = i + 1; j < n; ++j) add(mask, {s[i], s[j]});
    } else {
      add(mask, {s[0], s[1]});
    }
    for (int i = 0; i < n; ++i) add(mask, {s[i]});
  }
  return out;
}

const std::vector<Merge>& FreeMerges() {
  static const std::vector<Merge> merges = BuildFreeMerges();
  return merges;
}

constexpr double kCentroid[4] = {0.25, 0.25, 0.25, 0.25};
constexpr double kVertexWeights[4][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}, {0, 0, 0, 1}};

}  // namespace

const char* OutcomeName(Outcome o) {
  switch (o) {
    case Outcome::kCollapsed:
      return "collapsed";
    case Outcome::kDead:
      return "deleted earlier";
    case Outcome::kLocked:
      return "locked";
    case Outcome::kUnchanged:
      return "rejected before, neighbourhood unchanged";
    case Outcome::kTwoFeatureVertices:
      return "two or more feature vertices (rule 2)";
    case Outcome::kCrossRegion:
      return "cross-region cell (rule 3)";
    case Outcome::kTwoBoundaryVertices:
      return "two or more exterior-boundary vertices (rule 5)";
    case Outcome::kBoundaryCell:
      return "touches the hull (TetFusion)";
    case Outcome::kPinnedConflict:
      return "two different vertices must stay";
    case Outcome::kCrossRegionNeighbours:
      return "no common vertex with the cross-region cells (rule 4)";
    case Outcome::kFeatureNeighbourhood:
      return "A(cell) holds several feature cells (rule 4)";
    case Outcome::kFlip:
      return "a neighbour would flip or become a sliver (rule 6)";
    case Outcome::kRequeued:
      return "valid point costs more than the next queued cell";
  }
  return "?";
}

bool IsPermanent(Outcome o) {
  return o == Outcome::kTwoFeatureVertices || o == Outcome::kCrossRegion ||
         o == Outcome::kTwoBoundaryVertices || o == Outcome::kBoundaryCell ||
         o == Outcome::kPinnedConflict;
}

void ApplyFeatureThreshold(const SimplifyOptions& options,
                           const std::vector<float>& interface_distance,
                           std::vector<uint8_t>* flags) {
  if (!options.feature_threshold_voxels) return;
  const float threshold = *options.feature_threshold_voxels;
  for (size_t v = 0; v < flags->size(); ++v) {
    const bool feature = std::abs(interface_distance[v]) <= threshold;
    (*flags)[v] = uint8_t((*flags)[v] & ~kFeatureVertex) | (feature ? kFeatureVertex : 0);
  }
}

CollapseEngine::CollapseEngine(TetMesh mesh, const SimplifyOptions& options, int threads)
    : mesh_(std::move(mesh)), options_(options) {
  const int64_t nv = mesh_.vertex_count(), nt = mesh_.tet_count();
  if (options_.policy == SimplifyPolicy::kPaper) {
    ApplyFeatureThreshold(options_, mesh_.interface_distance, &mesh_.vertex_flags);
  }
  mesh_.cell_regions.clear();  // recomputed by Finish()

  cell_volume_.resize(nt);
  ParallelFor(nt, threads, kCellChunk, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) cell_volume_[t] = float(CellVolume(&mesh_.tets[4 * t]));
  });
  double total = 0;
  for (int64_t t = 0; t < nt; ++t) total += cell_volume_[t];
  voxel_ = options_.voxel_size_mm > 0 ? options_.voxel_size_mm
                                      : (nt > 0 ? std::cbrt(5.0 * total / double(nt)) : 1.0);
  if (!(voxel_ > 0)) voxel_ = 1;
  voxel_volume_ = voxel_ * voxel_ * voxel_;
  min_volume_ = options_.min_volume_fraction * voxel_volume_;

  // Eq. (5): the distribution of every region, taken once from the input (the paper assumes
  // the region means do not change).
  double sum[256] = {}, count[256] = {}, global_sum = 0;
  for (int64_t v = 0; v < nv; ++v) {
    sum[mesh_.labels[v]] += mesh_.scalars[v];
    count[mesh_.labels[v]] += 1;
    global_sum += mesh_.scalars[v];
  }
  const double global_mean = nv > 0 ? global_sum / double(nv) : 0;
  double sq[256] = {}, global_sq = 0;
  for (int r = 0; r < 256; ++r) region_mean_[r] = count[r] > 0 ? sum[r] / count[r] : 0;
  for (int64_t v = 0; v < nv; ++v) {
    const double d = mesh_.scalars[v] - region_mean_[mesh_.labels[v]];
    sq[mesh_.labels[v]] += d * d;
    global_sq += (mesh_.scalars[v] - global_mean) * (mesh_.scalars[v] - global_mean);
  }
  const double global_std = nv > 0 ? std::sqrt(global_sq / double(nv)) : 0;
  // Floors keep noise-free regions finite: a collapse that changes their values then costs a
  // lot instead of infinity.
  const double floor_std = global_std > 0 ? 1e-3 * global_std : 1.0;
  global_std_ = global_std > 0 ? global_std : 1.0;
  for (int r = 0; r < 256; ++r) {
    const double var = count[r] > 0 ? sq[r] / count[r] : 0;
    region_std_[r] = std::max(std::sqrt(var), floor_std);
    region_var_[r] = region_std_[r] * region_std_[r];
  }

  // Adjacency rows (input CSR), star volumes and the cross-region marks.
  VertexTetAdjacency adjacency = BuildVertexTetAdjacency(mesh_, threads);
  adj_ids_ = std::move(adjacency.tet_ids);
  rows_.resize(nv);
  star_.resize(nv);
  for (int64_t v = 0; v < nv; ++v) {
    const int64_t begin = adjacency.offsets[v], count = adjacency.offsets[v + 1] - begin;
    rows_[v] = {int32_t(begin), int32_t(count), -1, int32_t(v)};
    star_[v] = {0.0, int32_t(count), 0};
  }
  cross_touch_.assign(nv, 0);
  const bool paper = options_.policy == SimplifyPolicy::kPaper;
  for (int64_t t = 0; t < nt; ++t) {
    const int32_t* tet = &mesh_.tets[4 * t];
    for (int k = 0; k < 4; ++k) star_[tet[k]].star_volume += cell_volume_[t];
    if (paper && IsCrossRegionCell(tet)) {
      for (int k = 0; k < 4; ++k) cross_touch_[tet[k]] = 1;
    }
  }

  parent_.resize(nv);
  std::iota(parent_.begin(), parent_.end(), 0);
  dead_ = BitSet(nt);
  permanent_.assign(nt, 0);
  scored_at_.assign(nt, 0);
  rejected_at_.assign(nt, 0);
  locked_ = BitSet(nt);
  live_cells_ = nt;
}

double CollapseEngine::CellVolume(const int32_t* tet) const {
  const float* p = mesh_.positions.data();
  return Orient6(p + 3 * tet[0], p + 3 * tet[1], p + 3 * tet[2], p + 3 * tet[3]) / 6.0;
}

bool CollapseEngine::IsCrossRegionCell(const int32_t* tet) const {
  const uint8_t l = mesh_.labels[tet[0]];
  bool mixed = false;
  for (int k = 0; k < 4; ++k) {
    if (IsFeature(tet[k])) return false;
    mixed |= mesh_.labels[tet[k]] != l;
  }
  return mixed;
}

uint32_t CollapseEngine::LastTouch(int32_t cell) const {
  const int32_t* t = &mesh_.tets[4 * int64_t(cell)];
  return std::max(std::max(star_[t[0]].touched, star_[t[1]].touched),
                  std::max(star_[t[2]].touched, star_[t[3]].touched));
}

CollapseEngine::PointFreeError CollapseEngine::PointFreeTerms(const int32_t* tet,
                                                              double volume) const {
  PointFreeError out;
  out.region = CellRegion(mesh_.labels[tet[0]], mesh_.labels[tet[1]], mesh_.labels[tet[2]],
                          mesh_.labels[tet[3]]);
  out.e_r = 0;
  if (options_.policy == SimplifyPolicy::kPaper) {
    for (int k = 0; k < 4; ++k) {
      const double d = mesh_.scalars[tet[k]] - region_mean_[out.region];
      out.e_r += d * d;
    }
    out.e_r = 0.25 * out.e_r / region_var_[out.region];  // Eq. (5): δ_c / δ_N
  }
  out.e_v = std::abs(volume) / voxel_volume_;  // Eq. (7), voxels^3
  // Eq. (7) ε_n: neighbourhood volume from the vertex stars (a cell sharing k vertices with τ
  // counts k times; τ itself is excluded).
  double neighbourhood = -4.0 * volume;
  for (int k = 0; k < 4; ++k) neighbourhood += star_[tet[k]].star_volume;
  out.e_n = neighbourhood > 1e-12 * voxel_volume_ ? std::abs(volume) / neighbourhood : 1;
  return out;
}

float CollapseEngine::MergeError(const int32_t* tet, const PointFreeError& base, unsigned mask,
                                 const double* w) const {
  const ErrorWeights& ew = options_.weights;
  const float* P = mesh_.positions.data();
  double s[4], px = 0, py = 0, pz = 0, s_new = 0;
  for (int k = 0; k < 4; ++k) {
    s[k] = mesh_.scalars[tet[k]];
    px += w[k] * P[3 * tet[k]], py += w[k] * P[3 * tet[k] + 1], pz += w[k] * P[3 * tet[k] + 2];
    s_new += w[k] * s[k];  // the linear field of τ at the point (§2.2.3.2's s'_n)
  }
  const bool paper = options_.policy == SimplifyPolicy::kPaper;
  double e_g = 0, e_s = 0;
  for (int k = 0; k < 4; ++k) {
    if (!(mask & (1u << k))) continue;  // a vertex that is not merged keeps its value and place
    e_g += std::abs(s[k] - s_new);
    const double dx = P[3 * tet[k]] - px, dy = P[3 * tet[k] + 1] - py, dz = P[3 * tet[k] + 2] - pz;
    e_s += std::sqrt(dx * dx + dy * dy + dz * dz);
  }
  e_g = 0.25 * e_g / (paper ? region_std_[base.region] : global_std_);  // Eq. (6)
  e_s = 0.25 * e_s / voxel_;                                            // Eq. (7), voxels
  return float(ew.regional * base.e_r + ew.gradient * e_g + ew.shape * e_s + ew.volume * base.e_v +
               ew.neighbour * base.e_n);
}

int CollapseEngine::BestSlot(const int32_t* tet, unsigned mask) const {
  // Only ε_g and ε_s depend on the collapse point; the other terms are the same for all slots.
  const float* P = mesh_.positions.data();
  int best = -1;
  double best_cost = 0;
  for (int slot = 0; slot < 4; ++slot) {
    if (!(mask & (1u << slot))) continue;
    const uint8_t region = mesh_.labels[tet[slot]];
    double e_g = 0, e_s = 0;
    for (int k = 0; k < 4; ++k) {
      e_g += std::abs(double(mesh_.scalars[tet[k]]) - mesh_.scalars[tet[slot]]);
      const double dx = double(P[3 * tet[k]]) - P[3 * tet[slot]];
      const double dy = double(P[3 * tet[k] + 1]) - P[3 * tet[slot] + 1];
      const double dz = double(P[3 * tet[k] + 2]) - P[3 * tet[slot] + 2];
      e_s += std::sqrt(dx * dx + dy * dy + dz * dz);
    }
    const double cost = options_.weights.gradient * 0.25 * e_g / region_std_[region] +
                        options_.weights.shape * 0.25 * e_s / voxel_;
    if (best < 0 || cost < best_cost || (cost == best_cost && tet[slot] < tet[best])) {
      best = slot;
      best_cost = cost;
    }
  }
  return best;
}

CellPlan CollapseEngine::PlanCell(int32_t cell) const {
  const int32_t* tet = &mesh_.tets[4 * int64_t(cell)];
  CellPlan plan;
  if (IsDead(cell)) {
    plan.outcome = Outcome::kDead;
    return plan;
  }
  const double volume = cell_volume_[cell];
  int nf = 0, nb = 0, fslot = -1, bslot = -1;
  bool same_label = true;
  for (int k = 0; k < 4; ++k) {
    if (IsFeature(tet[k])) ++nf, fslot = k;
    if (IsBoundary(tet[k])) ++nb, bslot = k;
    same_label &= mesh_.labels[tet[k]] == mesh_.labels[tet[0]];
  }
  if (options_.policy == SimplifyPolicy::kTetFusion) {
    // TetFusion keeps every cell that touches the hull and ignores features.
    if (nb > 0) {
      plan.outcome = Outcome::kBoundaryCell;
      return plan;
    }
    plan.error = MergeError(tet, volume, 0xF, kCentroid);
    return plan;
  }
  if (nf >= 2) {
    plan.outcome = Outcome::kTwoFeatureVertices;  // rule 2
    return plan;
  }
  if (nb >= 2) {
    plan.outcome = Outcome::kTwoBoundaryVertices;  // rule 5
    return plan;
  }
  if (nf == 0 && !same_label) {
    plan.outcome = Outcome::kCrossRegion;  // rule 3
    return plan;
  }
  int pinned = fslot;  // rule 2: τ -> v_f
  if (bslot >= 0) {    // rule 5: τ -> v_b
    if (pinned >= 0 && pinned != bslot) {
      plan.outcome = Outcome::kPinnedConflict;
      return plan;
    }
    pinned = bslot;
  }
  int slot = pinned;
  if (nf == 0) {
    // Rule 4, estimated from the set-up marks: TryCollapse decides exactly.
    unsigned touch = 0;
    for (int k = 0; k < 4; ++k) touch |= cross_touch_[tet[k]] ? 1u << k : 0u;
    if (touch != 0) {
      if (pinned >= 0) touch &= 1u << pinned;
      if (touch == 0) {
        plan.outcome = Outcome::kCrossRegionNeighbours;
        return plan;
      }
      slot = BestSlot(tet, touch);
    }
  }
  plan.target_slot = int8_t(slot);
  plan.error = MergeError(tet, volume, 0xF, slot < 0 ? kCentroid : kVertexWeights[slot]);
  return plan;
}

void CollapseEngine::GatherNeighbours(int32_t cell) {
  static constexpr uint8_t kBits[16] = {0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4};
  a_set_.clear();
  d_set_.clear();
  const int32_t* tet = &mesh_.tets[4 * int64_t(cell)];
  const float* P = mesh_.positions.data();
  // Three phases so that the cache misses of the cells (then of their vertices) overlap
  // instead of being waited for one by one: this loop is memory bound.
  // 1. The live cells around τ's vertices: walk the merge class of each vertex, dropping dead
  //    cells from the rows (and emptied rows from the class) as we go.
  gather_ids_.clear();
  for (int k = 0; k < 4; ++k) __builtin_prefetch(&rows_[tet[k]]);
  for (int k = 0; k < 4; ++k) __builtin_prefetch(&adj_ids_[rows_[tet[k]].begin]);
  int32_t begin[5] = {0, 0, 0, 0, 0};
  for (int k = 0; k < 4; ++k) {
    int32_t prev = -1;
    for (int32_t m = tet[k]; m >= 0;) {
      VertexRow& row = rows_[m];
      if (row.class_next >= 0) __builtin_prefetch(&rows_[row.class_next]);
      int32_t* ids = &adj_ids_[row.begin];
      int32_t n = row.count;
      for (int32_t i = 0; i < n;) {
        const int32_t c = ids[i];
        if (IsDead(c)) {
          ids[i] = ids[n - 1];
          --n;
          continue;
        }
        ++i;
        if (c == cell) continue;
        __builtin_prefetch(&mesh_.tets[4 * int64_t(c)]);
        gather_ids_.push_back(c);
      }
      row.count = n;
      const int32_t next = row.class_next;
      if (n == 0 && prev >= 0) {
        rows_[prev].class_next = next;  // unlink the emptied row (never the class root)
        if (next < 0) rows_[tet[k]].class_tail = prev;
      } else {
        prev = m;
      }
      m = next;
    }
    begin[k + 1] = int32_t(gather_ids_.size());
  }
  // 2. Shared vertices: A(τ) (one) and D(τ) (two or more).
  for (int k = 0; k < 4; ++k) {
    for (int32_t i = begin[k]; i < begin[k + 1]; ++i) {
      const int32_t c = gather_ids_[i];
      const int32_t* other = &mesh_.tets[4 * int64_t(c)];
      Neighbour nb{c, 0, {0, 0, 0, 0}, {0, 0, 0}, 0};
      for (int q = 0; q < 4; ++q) {
        for (int j = 0; j < 4; ++j) {
          if (other[q] == tet[j]) {
            nb.shared_mask |= uint8_t(1u << j);
            nb.pos[j] = uint8_t(q);
          }
        }
      }
      // A cell sharing several vertices is met once per shared vertex: keep the first.
      if (std::countr_zero(unsigned(nb.shared_mask)) != k) continue;
      if (kBits[nb.shared_mask] > 1) {
        d_set_.push_back(nb);
        continue;
      }
      for (int q = 0; q < 4; ++q) __builtin_prefetch(P + 3 * other[q]);
      a_set_.push_back(nb);
    }
  }
  // 3. The plane of every cell of A(τ): 6 * volume with the shared vertex (at position `moved`)
  //    at p is affine in p. Moving p from `moved` to the front is `moved` transpositions, and
  //    Orient6(p, o0, o1, o2) = (o0 - p) . nrm with nrm = (o1 - o0) x (o2 - o0).
  for (Neighbour& nb : a_set_) {
    const int32_t* other = &mesh_.tets[4 * int64_t(nb.cell)];
    const int moved = nb.pos[std::countr_zero(unsigned(nb.shared_mask))];
    const float* o[3];
    for (int q = 0, j = 0; q < 4; ++q)
      if (q != moved) o[j++] = P + 3 * other[q];
    const double ax = double(o[1][0]) - o[0][0], ay = double(o[1][1]) - o[0][1],
                 az = double(o[1][2]) - o[0][2];
    const double bx = double(o[2][0]) - o[0][0], by = double(o[2][1]) - o[0][1],
                 bz = double(o[2][2]) - o[0][2];
    const double nx = ay * bz - az * by, ny = az * bx - ax * bz, nz = ax * by - ay * bx;
    const double sign = (moved & 1) ? -1.0 : 1.0;
    nb.n[0] = -sign * nx, nb.n[1] = -sign * ny, nb.n[2] = -sign * nz;
    nb.d = sign * (nx * o[0][0] + ny * o[0][1] + nz * o[0][2]);
  }
}

double CollapseEngine::MovedVolume6(const Neighbour& n, int slot, const float* p) const {
  if ((n.shared_mask & (n.shared_mask - 1)) == 0) {
    return n.n[0] * p[0] + n.n[1] * p[1] + n.n[2] * p[2] + n.d;  // A(τ): the stored plane
  }
  const int32_t* other = &mesh_.tets[4 * int64_t(n.cell)];
  const float* q[4];
  for (int j = 0; j < 4; ++j) q[j] = mesh_.positions.data() + 3 * other[j];
  q[n.pos[slot]] = p;
  return Orient6(q[0], q[1], q[2], q[3]);
}

bool CollapseEngine::MergeValid(unsigned mask, int fixed_slot, const float* p) const {
  const double min6 = 6.0 * min_volume_;
  for (const auto* set : {&a_set_, &d_set_}) {
    for (const Neighbour& n : *set) {
      const unsigned m = n.shared_mask & mask;
      // Cells holding two merged vertices degenerate and are deleted; cells holding none, or
      // only the vertex that stays, keep their shape.
      if (m == 0 || (m & (m - 1)) != 0) continue;
      const int slot = std::countr_zero(m);
      if (slot == fixed_slot) continue;
      if (!(MovedVolume6(n, slot, p) >= min6)) return false;
    }
  }
  // A vertex that must stay (feature or exterior boundary) must keep a cell: deleting every
  // cell around it would remove it from the mesh (the degenerate cells can be its whole star).
  return !OrphansPinnedVertex(mask, fixed_slot);
}

bool CollapseEngine::OrphansPinnedVertex(unsigned mask, int fixed_slot) const {
  const int32_t* tet = &mesh_.tets[4 * int64_t(current_)];
  auto pinned = [&](int32_t v) {
    return (mesh_.vertex_flags[v] & (kFeatureVertex | kExteriorBoundaryVertex)) != 0;
  };
  // The survivor keeps the cells that hold exactly one merged vertex.
  if (fixed_slot >= 0) {
    bool kept = false;
    for (const auto* set : {&a_set_, &d_set_}) {
      for (const Neighbour& n : *set) {
        const unsigned m = n.shared_mask & mask;
        kept |= m != 0 && (m & (m - 1)) == 0;
      }
    }
    if (!kept) return true;
  }
  // Other pinned vertices: count the dying cells around them (τ too) against their valence.
  int32_t ids[64];
  int32_t counts[64];
  int used = 0;
  auto die = [&](const int32_t* cell_tet) {
    for (int j = 0; j < 4; ++j) {
      const int32_t v = cell_tet[j];
      bool merged = false;
      for (int k = 0; k < 4; ++k) merged |= tet[k] == v && (mask & (1u << k));
      if (merged || !pinned(v)) continue;
      int i = 0;
      while (i < used && ids[i] != v) ++i;
      if (i == used) {
        if (used == 64) return true;  // too many to track: be conservative
        ids[used] = v, counts[used++] = 0;
      }
      if (++counts[i] >= star_[v].valence) return true;
    }
    return false;
  };
  if (die(tet)) return true;
  for (const Neighbour& n : d_set_) {
    const unsigned m = n.shared_mask & mask;
    if ((m & (m - 1)) != 0 && die(&mesh_.tets[4 * int64_t(n.cell)])) return true;
  }
  return false;
}

CollapseResult CollapseEngine::TryCollapse(int32_t cell, float next_key) {
  CollapseResult result;
  if (IsDead(cell)) {
    result.outcome = Outcome::kDead;
    return result;
  }
  if (options_.lock_neighbours && IsLocked(cell)) {
    result.outcome = Outcome::kLocked;
    return result;
  }
  // A cell rejected for its neighbourhood stays rejected until a collapse changes a cell
  // around one of its vertices (the decision depends on nothing else).
  if (rejected_at_[cell] != 0 && LastTouch(cell) <= rejected_at_[cell]) {
    result.outcome = Outcome::kUnchanged;
    return result;
  }
  const CellPlan plan = PlanCell(cell);
  result.error = plan.error;
  if (plan.outcome != Outcome::kCollapsed) {
    if (IsPermanent(plan.outcome)) permanent_[cell] = 1;
    result.outcome = plan.outcome;
    return result;
  }
  int32_t tet[4];
  std::copy_n(&mesh_.tets[4 * int64_t(cell)], 4, tet);
  const double volume = cell_volume_[cell];
  int slot = plan.target_slot;
  const bool paper = options_.policy == SimplifyPolicy::kPaper;
  bool any_feature = false, near_crossing = false;
  int bslot = -1;
  for (int k = 0; k < 4; ++k) {
    any_feature |= IsFeature(tet[k]);
    near_crossing |= cross_touch_[tet[k]] != 0;
    if (IsBoundary(tet[k])) bslot = k;
  }
  GatherNeighbours(cell);
  current_ = cell;
  auto reject = [&](Outcome o) {
    result.outcome = o;
    rejected_at_[cell] = clock_;
    return result;
  };
  // Rule 4 on the current neighbourhood; cross-region cells are never created, so only cells
  // with a vertex marked at set-up can have one around them.
  if (paper && !any_feature && near_crossing) {
    // (a) Cross-region cells in A(τ) ∪ D(τ): collapse to the vertex τ shares with them (with
    // several, one common to all of them).
    int crossing = 0;
    unsigned common = 0xF;
    for (const auto* set : {&a_set_, &d_set_}) {
      for (const Neighbour& n : *set) {
        if (IsCrossRegionCell(&mesh_.tets[4 * int64_t(n.cell)])) {
          ++crossing;
          common &= n.shared_mask;
        }
      }
    }
    if (crossing > 0) {
      if (bslot >= 0) common &= 1u << bslot;
      if (common == 0) return reject(Outcome::kCrossRegionNeighbours);
      slot = BestSlot(tet, common);
      // (b) More than one feature cell and more than one feature vertex in A(τ): keep τ.
      // Cells of D(τ) may hold any number of feature vertices.
      int feature_cells = 0;
      int32_t first_feature = -1;
      bool two_features = false;
      for (const Neighbour& n : a_set_) {
        const int32_t* other = &mesh_.tets[4 * int64_t(n.cell)];
        bool is_feature_cell = false;
        for (int q = 0; q < 4; ++q) {
          if (!IsFeature(other[q])) continue;
          is_feature_cell = true;
          if (first_feature < 0) first_feature = other[q];
          two_features |= other[q] != first_feature;
        }
        feature_cells += is_feature_cell;
      }
      if (feature_cells > 1 && two_features) return reject(Outcome::kFeatureNeighbourhood);
    } else {
      slot = bslot;
    }
    if (slot != plan.target_slot) {
      result.error = MergeError(tet, volume, 0xF, slot < 0 ? kCentroid : kVertexWeights[slot]);
    }
  }

  // The collapse point, rounded to the stored float precision before the flip check so the
  // check sees exactly the coordinates the mesh will hold.
  const float* P = mesh_.positions.data();
  auto point = [&](const double* w, float* p) {
    for (int c = 0; c < 3; ++c) {
      p[c] = float(w[0] * P[3 * tet[0] + c] + w[1] * P[3 * tet[1] + c] + w[2] * P[3 * tet[2] + c] +
                   w[3] * P[3 * tet[3] + c]);
    }
  };
  // The paper's collapse first: all four vertices to the centroid (rule 1) or onto the vertex
  // that must stay (rules 2, 4, 5).
  unsigned mask = 0xF;
  const double* w = slot < 0 ? kCentroid : kVertexWeights[slot];
  int row = slot < 0 ? 0 : -1;
  float p[3];
  point(w, p);
  // Rule 6: every cell whose vertex moves must stay positive (and not a sliver).
  if (!MergeValid(mask, slot, p)) {
    // Departure (README): when the paper's collapse would flip a neighbour, delete τ by the
    // cheapest valid merge of the widened set (Δε of Eq. 8 over the merged vertices). A vertex
    // that must stay (feature, boundary, rule 4) stays: its merges all end on it.
    if (!paper || !options_.widen_collapse_point) return reject(Outcome::kFlip);
    const std::vector<Merge>& free = FreeMerges();
    std::pair<float, int> alternatives[64];
    int count = 0;
    const PointFreeError base = PointFreeTerms(tet, volume);
    if (slot < 0) {
      for (int i = 1; i < int(free.size()); ++i)
        alternatives[count++] = {MergeError(tet, base, free[i].mask, free[i].w), i};
    } else {
      for (unsigned m = 1; m < 0xF; ++m) {  // merges of 2 or 3 vertices holding `slot`
        if (!(m & (1u << slot)) || std::popcount(m) < 2) continue;
        alternatives[count++] = {MergeError(tet, base, m, kVertexWeights[slot]), -int(m)};
      }
    }
    std::sort(alternatives, alternatives + count);
    bool found = false;
    for (int a = 0; a < count && !found; ++a) {
      const int i = alternatives[a].second;
      mask = i > 0 ? free[i].mask : unsigned(-i);
      if (i > 0) w = free[i].w;
      point(w, p);
      if (MergeValid(mask, slot, p)) {
        found = true;
        row = i;
        result.error = alternatives[a].first;
      }
    }
    if (!found) return reject(Outcome::kFlip);
    if (FloatKey(result.error) > FloatKey(next_key)) {
      result.outcome = Outcome::kRequeued;
      return result;
    }
  }

  // Apply: the survivor takes the collapse point; the other merged vertices merge into it.
  int32_t survivor = slot >= 0 ? tet[slot] : -1;
  for (int k = 0; k < 4 && slot < 0; ++k) {
    if ((mask & (1u << k)) && (survivor < 0 || tet[k] < survivor)) survivor = tet[k];
  }
  if (slot < 0) {
    double s = 0, d = 0;
    for (int k = 0; k < 4; ++k) {
      s += w[k] * mesh_.scalars[tet[k]];
      d += w[k] * mesh_.interface_distance[tet[k]];
    }
    // The value at the point: the linear interpolation of τ's field (for the centroid, the
    // mean of the four: §2.2.3.2's s'_n).
    mesh_.scalars[survivor] = float(s);
    mesh_.interface_distance[survivor] = float(d);
    mesh_.labels[survivor] = CellRegion(mesh_.labels[tet[0]], mesh_.labels[tet[1]],
                                        mesh_.labels[tet[2]], mesh_.labels[tet[3]]);
    mesh_.vertex_flags[survivor] = 0;  // no feature or boundary vertex goes to a free point
  }
  ++clock_;
  double survivor_star = 0;
  int32_t removed = 1, survivor_valence = 0;
  auto is_merged = [&](int32_t v) {
    for (int k = 0; k < 4; ++k)
      if (tet[k] == v) return (mask & (1u << k)) != 0;
    return false;
  };
  for (const auto* set : {&a_set_, &d_set_}) {
    for (const Neighbour& n : *set) {
      const unsigned m = n.shared_mask & mask;
      if (m == 0) continue;
      int32_t* other = &mesh_.tets[4 * int64_t(n.cell)];
      if ((m & (m - 1)) != 0) {  // step 2f: degenerate
        Kill(n.cell);
        ++removed;
        for (int j = 0; j < 4; ++j) {
          if (is_merged(other[j])) continue;
          --star_[other[j]].valence;
          star_[other[j]].star_volume -= cell_volume_[n.cell];
          star_[other[j]].touched = clock_;
        }
        continue;
      }
      const int k = std::countr_zero(m);
      if (k != slot) {
        const double before = cell_volume_[n.cell];
        const double after = MovedVolume6(n, k, p) / 6.0;
        other[n.pos[k]] = survivor;
        cell_volume_[n.cell] = float(after);
        for (int j = 0; j < 4; ++j) {
          if (j != n.pos[k]) star_[other[j]].star_volume += after - before;
        }
        if (options_.lock_neighbours) Lock(n.cell);  // §2.2.4 step 2g
      }
      survivor_star += cell_volume_[n.cell];
      ++survivor_valence;
      for (int j = 0; j < 4; ++j) star_[other[j]].touched = clock_;
    }
  }
  if (slot < 0) std::copy_n(p, 3, &mesh_.positions[3 * int64_t(survivor)]);
  star_[survivor].star_volume = survivor_star;
  star_[survivor].valence = survivor_valence;
  for (int k = 0; k < 4; ++k) {
    const int32_t v = tet[k];
    star_[v].touched = clock_;
    if (v == survivor || !(mask & (1u << k))) continue;
    parent_[v] = survivor;
    rows_[rows_[survivor].class_tail].class_next = v;
    rows_[survivor].class_tail = rows_[v].class_tail;
  }
  // Vertices of τ that were not merged lose τ from their stars.
  for (int k = 0; k < 4; ++k) {
    if (mask & (1u << k)) continue;
    star_[tet[k]].star_volume -= volume;
    --star_[tet[k]].valence;
  }
  Kill(cell);
  result.cells_removed = removed;
  live_cells_ -= removed;
  result.survivor = survivor;
  result.point = int8_t(row);
  result.merged = int8_t(std::popcount(mask));
  result.outcome = Outcome::kCollapsed;
  return result;
}

int64_t CollapseEngine::BeginPass(int threads) {
  heap_.clear();
  locked_.ClearAll();
  const int64_t nt = mesh_.tet_count();
  keys_.resize(nt);
  ParallelFor(nt, threads, kCellChunk, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) {
      keys_[t] = kNotCandidate;
      if (IsDead(int32_t(t)) || permanent_[t]) continue;
      if (rejected_at_[t] != 0 && LastTouch(int32_t(t)) <= rejected_at_[t]) continue;
      const CellPlan plan = PlanCell(int32_t(t));
      scored_at_[t] = clock_;
      if (plan.outcome == Outcome::kCollapsed) {
        keys_[t] = FloatKey(plan.error);
      } else if (IsPermanent(plan.outcome)) {
        permanent_[t] = 1;
      }
    }
  });
  order_.clear();
  for (int64_t t = 0; t < nt; ++t) {
    if (keys_[t] != kNotCandidate) order_.push_back(int32_t(t));
  }
  // Stable LSD radix sort on the 32-bit error key, two 16-bit digits: ids enter in increasing
  // order, so ties stay ordered by cell id.
  const size_t n = order_.size();
  keys_tmp_.resize(n);
  ids_tmp_.resize(n);
  order_keys_.resize(n);
  for (size_t i = 0; i < n; ++i) order_keys_[i] = keys_[order_[i]];
  sort_count_.resize(65537);
  for (int shift = 0; shift < 32; shift += 16) {
    std::fill(sort_count_.begin(), sort_count_.end(), 0);
    for (size_t i = 0; i < n; ++i) ++sort_count_[((order_keys_[i] >> shift) & 0xFFFF) + 1];
    for (int d = 0; d < 65536; ++d) sort_count_[d + 1] += sort_count_[d];
    for (size_t i = 0; i < n; ++i) {
      const uint32_t pos = sort_count_[(order_keys_[i] >> shift) & 0xFFFF]++;
      keys_tmp_[pos] = order_keys_[i];
      ids_tmp_[pos] = order_[i];
    }
    order_keys_.swap(keys_tmp_);
    order_.swap(ids_tmp_);
  }
  return int64_t(n);
}

void CollapseEngine::PushKey(uint32_t key, int32_t cell) {
  heap_.emplace_back(key, cell);
  std::push_heap(heap_.begin(), heap_.end(), std::greater<>());
}

absl::Status CollapseEngine::RunPass(int64_t max_removed, double tolerance,
                                     const CancelToken* cancel, EnginePassStats* stats) {
  stats->candidates = int64_t(order_.size());
  size_t i = 0;
  const size_t n = order_.size();
  for (int64_t pops = 1;; ++pops) {
    if (removed_cells() >= max_removed) break;
    if ((pops & 0xFFFF) == 0) {
      if (absl::Status s = CheckCancelled(cancel, "simplify"); !s.ok()) return s;
    }
    // The smallest (key, id) of the sorted list and the heap of re-pushed cells.
    uint32_t key;
    int32_t cell;
    if (i < n && (heap_.empty() || std::make_pair(order_keys_[i], order_[i]) < heap_.front())) {
      key = order_keys_[i];
      cell = order_[i++];
      // The queue is in error order, so its cells are scattered in memory: fetch the cells a
      // few places ahead, then their vertices, while this one is worked on.
      if (i + kFarAhead < n) {
        const int32_t far = order_[i + kFarAhead];
        if (!IsDead(far)) __builtin_prefetch(&mesh_.tets[4 * int64_t(far)]);
      }
      if (i + kNearAhead < n) {
        const int32_t near = order_[i + kNearAhead];
        if (!IsDead(near) && !IsLocked(near)) {
          const int32_t* t = &mesh_.tets[4 * int64_t(near)];
          for (int k = 0; k < 4; ++k) {
            __builtin_prefetch(&star_[t[k]]);
            __builtin_prefetch(&rows_[t[k]]);
          }
          __builtin_prefetch(&scored_at_[near]);
        }
      }
    } else if (!heap_.empty()) {
      std::pop_heap(heap_.begin(), heap_.end(), std::greater<>());
      std::tie(key, cell) = heap_.back();
      heap_.pop_back();
    } else {
      break;
    }
    if (IsDead(cell) || (options_.lock_neighbours && IsLocked(cell))) continue;
    if (tolerance > 0 && KeyFloat(key) > tolerance) {
      stats->tolerance_hit = true;
      break;
    }
    uint32_t next = kNotCandidate;
    if (i < n) next = order_keys_[i];
    if (!heap_.empty()) next = std::min(next, heap_.front().first);
    // Lazy update: a cell whose neighbourhood changed since it was scored is re-scored when it
    // reaches the front, and pushed back if it no longer is the cheapest.
    if (LastTouch(cell) > scored_at_[cell]) {
      const CellPlan plan = PlanCell(cell);
      scored_at_[cell] = clock_;
      if (plan.outcome != Outcome::kCollapsed) {
        if (IsPermanent(plan.outcome)) permanent_[cell] = 1;
        continue;
      }
      const uint32_t fresh = FloatKey(plan.error);
      if (fresh > next) {
        PushKey(fresh, cell);
        ++stats->requeued;
        continue;
      }
    }
    const CollapseResult r = TryCollapse(cell, KeyFloat(next));
    switch (r.outcome) {
      case Outcome::kCollapsed:
        ++stats->collapses;
        stats->cells_removed += r.cells_removed;
        stats->last_error = r.error;
        stats->max_error = std::max(stats->max_error, double(r.error));
        stats->other_point += r.point > 0 || r.merged < 4;
        break;
      case Outcome::kRequeued:
        PushKey(FloatKey(r.error), cell);
        ++stats->requeued;
        break;
      case Outcome::kFlip:
        ++stats->rejected_flip;
        break;
      case Outcome::kCrossRegionNeighbours:
      case Outcome::kFeatureNeighbourhood:
        ++stats->rejected_rule4;
        break;
      default:
        break;
    }
  }
  return absl::OkStatus();
}

void CollapseEngine::Finish(TetMesh* out, std::vector<int32_t>* vertex_map) {
  const int64_t nv = mesh_.vertex_count(), nt = mesh_.tet_count();
  std::vector<int32_t> new_id(nv, -1);
  int64_t live = 0;
  for (int64_t t = 0; t < nt; ++t) {
    if (IsDead(int32_t(t))) continue;
    ++live;
    for (int k = 0; k < 4; ++k) new_id[mesh_.tets[4 * t + k]] = 0;
  }
  int32_t next = 0;
  for (int64_t v = 0; v < nv; ++v) {
    if (new_id[v] == 0) new_id[v] = next++;
  }
  out->positions.resize(3 * int64_t(next));
  out->scalars.resize(next);
  out->labels.resize(next);
  out->interface_distance.resize(next);
  out->vertex_flags.resize(next);
  for (int64_t v = 0; v < nv; ++v) {
    const int32_t n = new_id[v];
    if (n < 0) continue;
    std::copy_n(&mesh_.positions[3 * v], 3, &out->positions[3 * int64_t(n)]);
    out->scalars[n] = mesh_.scalars[v];
    out->labels[n] = mesh_.labels[v];
    out->interface_distance[n] = mesh_.interface_distance[v];
    out->vertex_flags[n] = mesh_.vertex_flags[v];
  }
  out->tets.resize(4 * live);
  out->cell_regions.resize(live);
  int64_t c = 0;
  for (int64_t t = 0; t < nt; ++t) {
    if (IsDead(int32_t(t))) continue;
    int32_t* o = &out->tets[4 * c];
    for (int k = 0; k < 4; ++k) o[k] = new_id[mesh_.tets[4 * t + k]];
    out->cell_regions[c] =
        CellRegion(out->labels[o[0]], out->labels[o[1]], out->labels[o[2]], out->labels[o[3]]);
    ++c;
  }
  // Input vertex -> its survivor (path-halving find) -> output index.
  vertex_map->resize(nv);
  for (int64_t v = 0; v < nv; ++v) {
    int32_t r = int32_t(v);
    while (parent_[r] != r) {
      parent_[r] = parent_[parent_[r]];
      r = parent_[r];
    }
    (*vertex_map)[v] = new_id[r];
  }
}

}  // namespace decima::simplify_internal
