// Cell collapse with the feature-preserving rules of:
//   Feature Preserving Volumetric Data Simplification for Application in Medical Imaging,
//   §2.2 (rules 1-6, Eq. 5-8, the greedy loop), and the baseline
//   Chopra, Meyer: TetFusion, an algorithm for rapid tetrahedral mesh simplification (2002).
// Interpretations of the paper are listed in README.md beside this file.
#include "core/simplify/collapse_engine.h"

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

template <typename Fn>
void ParallelFor(int64_t n, int threads, Fn&& fn) {
  threads =
      std::max(1, std::min<int>(threads, static_cast<int>(std::min<int64_t>(n / 4096 + 1, 64))));
  if (threads == 1) {
    fn(int64_t{0}, n);
    return;
  }
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t) {
    const int64_t begin = n * t / threads, end = n * (t + 1) / threads;
    pool.emplace_back([&fn, begin, end] { fn(begin, end); });
  }
  for (auto& th : pool) th.join();
}

// 6 * signed volume of (a, b, c, d) from float coordinates, in double.
inline double Orient6(const float* a, const float* b, const float* c, const float* d) {
  const double bx = double(b[0]) - a[0], by = double(b[1]) - a[1], bz = double(b[2]) - a[2];
  const double cx = double(c[0]) - a[0], cy = double(c[1]) - a[1], cz = double(c[2]) - a[2];
  const double dx = double(d[0]) - a[0], dy = double(d[1]) - a[1], dz = double(d[2]) - a[2];
  return bx * (cy * dz - cz * dy) - by * (cx * dz - cz * dx) + bz * (cx * dy - cy * dx);
}

inline uint32_t FloatKey(float e) {
  if (!(e < FLT_MAX)) e = FLT_MAX;  // also NaN
  if (e < 0) e = 0;
  uint32_t bits;
  std::memcpy(&bits, &e, 4);
  return bits;  // non-negative floats order like their bit patterns
}

constexpr uint32_t kNotCandidate = 0xFFFFFFFFu;

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
  }
  return "?";
}

CollapseEngine::CollapseEngine(TetMesh mesh, const SimplifyOptions& options)
    : mesh_(std::move(mesh)), options_(options) {
  const int64_t nv = mesh_.vertex_count(), nt = mesh_.tet_count();
  if (options_.policy == SimplifyPolicy::kPaper && options_.feature_threshold_voxels >= 0) {
    for (int64_t v = 0; v < nv; ++v) {
      const bool feature =
          std::abs(mesh_.interface_distance[v]) <= options_.feature_threshold_voxels;
      mesh_.vertex_flags[v] =
          (mesh_.vertex_flags[v] & ~kFeatureVertex) | (feature ? kFeatureVertex : 0);
    }
  }
  mesh_.cell_regions.clear();  // recomputed by Finish()

  double total = 0;
  for (int64_t t = 0; t < nt; ++t) total += CellVolume(&mesh_.tets[4 * t]);
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

  parent_.resize(nv);
  std::iota(parent_.begin(), parent_.end(), 0);
  touched_.assign(nv, 0);
  dead_.assign(nt, 0);
  rejected_at_.assign(nt, 0);
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

void CollapseEngine::BeginPass(int threads) {
  // Drop the cells deleted in the previous pass (stable, so ids keep their relative order).
  int64_t nt = mesh_.tet_count(), kept = 0;
  for (int64_t t = 0; t < nt; ++t) {
    if (dead_[t]) continue;
    if (kept != t) {
      std::copy_n(&mesh_.tets[4 * t], 4, &mesh_.tets[4 * kept]);
      rejected_at_[kept] = rejected_at_[t];
    }
    ++kept;
  }
  mesh_.tets.resize(4 * kept);
  rejected_at_.resize(kept);
  nt = kept;
  live_cells_ = nt;
  dead_.assign(nt, 0);
  locked_.assign(nt, 0);
  adjacency_ = BuildVertexTetAdjacency(mesh_);
  // Passes after the first start by relaxing the normal vertices (README: "un-jamming").
  if (pass_ > 0) {
    for (int it = 0; it < options_.smoothing_iterations; ++it) SmoothVertices();
  }
  ++pass_;

  const int64_t nv = mesh_.vertex_count();
  cell_volume_.resize(nt);
  ParallelFor(nt, threads, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) cell_volume_[t] = float(CellVolume(&mesh_.tets[4 * t]));
  });
  star_volume_.assign(nv, 0.0);
  cross_touch_.assign(nv, 0);
  const bool paper = options_.policy == SimplifyPolicy::kPaper;
  for (int64_t t = 0; t < nt; ++t) {
    const int32_t* tet = &mesh_.tets[4 * t];
    for (int k = 0; k < 4; ++k) star_volume_[tet[k]] += cell_volume_[t];
    if (paper && IsCrossRegionCell(tet)) {
      for (int k = 0; k < 4; ++k) cross_touch_[tet[k]] = 1;
    }
  }
}

namespace {
// Mean-ratio quality 12 (3V)^(2/3) / sum of squared edge lengths: 1 for the regular tet, 0 flat.
double Quality(const float* q0, const float* q1, const float* q2, const float* q3, double o6) {
  if (o6 <= 0) return 0;
  const float* q[4] = {q0, q1, q2, q3};
  double l2 = 0;
  for (int i = 0; i < 4; ++i)
    for (int j = i + 1; j < 4; ++j)
      for (int c = 0; c < 3; ++c) l2 += (double(q[i][c]) - q[j][c]) * (double(q[i][c]) - q[j][c]);
  return 12.0 * std::cbrt(0.25 * o6 * o6) / l2;
}
}  // namespace

int64_t CollapseEngine::SmoothVertices() {
  const int64_t nv = mesh_.vertex_count();
  float* P = mesh_.positions.data();
  int64_t moved = 0;
  const double min6 = 6.0 * min_volume_;
  for (int64_t v = 0; v < nv; ++v) {
    if (mesh_.vertex_flags[v] & (kFeatureVertex | kExteriorBoundaryVertex)) continue;
    const int64_t b = adjacency_.offsets[v], e = adjacency_.offsets[v + 1];
    if (b == e) continue;
    double cx = 0, cy = 0, cz = 0, wsum = 0, old_q = 1;
    bool pure = true;
    for (int64_t i = b; i < e; ++i) {
      const int32_t* t = &mesh_.tets[4 * int64_t(adjacency_.tet_ids[i])];
      const double o6 = Orient6(P + 3 * t[0], P + 3 * t[1], P + 3 * t[2], P + 3 * t[3]);
      old_q = std::min(old_q, Quality(P + 3 * t[0], P + 3 * t[1], P + 3 * t[2], P + 3 * t[3], o6));
      for (int k = 0; k < 4; ++k) {
        cx += o6 * P[3 * t[k]], cy += o6 * P[3 * t[k] + 1], cz += o6 * P[3 * t[k] + 2];
        pure &= mesh_.labels[t[k]] == mesh_.labels[v];
      }
      wsum += 4 * o6;
    }
    if (!pure || !(wsum > 0)) continue;
    cx /= wsum, cy /= wsum, cz /= wsum;
    for (double alpha : {1.0, 0.5}) {
      float p[3] = {float(P[3 * v] + alpha * (cx - P[3 * v])),
                    float(P[3 * v + 1] + alpha * (cy - P[3 * v + 1])),
                    float(P[3 * v + 2] + alpha * (cz - P[3 * v + 2]))};
      double new_q = 1;
      bool ok = true;
      double value = 0, dist = 0;
      bool located = false;
      for (int64_t i = b; i < e && ok; ++i) {
        const int32_t* t = &mesh_.tets[4 * int64_t(adjacency_.tet_ids[i])];
        const float* q[4];
        for (int k = 0; k < 4; ++k) q[k] = t[k] == v ? p : P + 3 * t[k];
        const double o6 = Orient6(q[0], q[1], q[2], q[3]);
        ok = o6 >= min6;
        new_q = std::min(new_q, Quality(q[0], q[1], q[2], q[3], o6));
        if (!located) {
          // Barycentric coordinates of p in the old cell.
          const float* r[4] = {P + 3 * t[0], P + 3 * t[1], P + 3 * t[2], P + 3 * t[3]};
          const double all = Orient6(r[0], r[1], r[2], r[3]);
          double l[4];
          bool inside = true;
          for (int k = 0; k < 4 && inside; ++k) {
            const float* rr[4] = {r[0], r[1], r[2], r[3]};
            rr[k] = p;
            l[k] = Orient6(rr[0], rr[1], rr[2], rr[3]) / all;
            inside = l[k] >= -1e-9;
          }
          for (int k = 0; k < 4; ++k) inside &= mesh_.labels[t[k]] == mesh_.labels[v];
          if (inside) {
            located = true;
            for (int k = 0; k < 4; ++k) {
              value += l[k] * mesh_.scalars[t[k]];
              dist += l[k] * mesh_.interface_distance[t[k]];
            }
          }
        }
      }
      if (!ok || !located || !(new_q > old_q)) continue;
      std::copy_n(p, 3, P + 3 * v);
      ++clock_;
      for (int64_t i = b; i < e; ++i) {
        for (int k = 0; k < 4; ++k)
          touched_[mesh_.tets[4 * int64_t(adjacency_.tet_ids[i]) + k]] = clock_;
      }
      mesh_.scalars[v] = float(value);
      mesh_.interface_distance[v] = float(dist);
      ++moved;
      break;
    }
  }
  return moved;
}

float CollapseEngine::PlanError(const int32_t* tet, double volume, int slot) const {
  const ErrorWeights& w = options_.weights;
  const float* P = mesh_.positions.data();
  double s[4], px = 0, py = 0, pz = 0, s_new = 0;
  for (int k = 0; k < 4; ++k) {
    s[k] = mesh_.scalars[tet[k]];
    px += P[3 * tet[k]], py += P[3 * tet[k] + 1], pz += P[3 * tet[k] + 2];
    s_new += s[k];
  }
  if (slot < 0) {
    px *= 0.25, py *= 0.25, pz *= 0.25, s_new *= 0.25;
  } else {
    px = P[3 * tet[slot]], py = P[3 * tet[slot] + 1], pz = P[3 * tet[slot] + 2];
    s_new = s[slot];
  }
  const bool paper = options_.policy == SimplifyPolicy::kPaper;
  const uint8_t region = CellRegion(mesh_.labels[tet[0]], mesh_.labels[tet[1]],
                                    mesh_.labels[tet[2]], mesh_.labels[tet[3]]);
  double e_r = 0, e_g = 0, e_s = 0;
  for (int k = 0; k < 4; ++k) {
    const double d = s[k] - region_mean_[region];
    e_r += d * d;
    e_g += std::abs(s[k] - s_new);
    const double dx = P[3 * tet[k]] - px, dy = P[3 * tet[k] + 1] - py, dz = P[3 * tet[k] + 2] - pz;
    e_s += std::sqrt(dx * dx + dy * dy + dz * dz);
  }
  e_r = paper ? 0.25 * e_r / region_var_[region] : 0;              // Eq. (5): δ_c / δ_N
  e_g = 0.25 * e_g / (paper ? region_std_[region] : global_std_);  // Eq. (6)
  e_s = 0.25 * e_s / voxel_;                                       // Eq. (7), voxels
  const double e_v = std::abs(volume) / voxel_volume_;             // Eq. (7), voxels^3
  // Eq. (7) ε_n: neighbourhood volume from the vertex stars (a cell sharing k vertices with τ
  // counts k times; τ itself is excluded).
  double neighbourhood = -4.0 * volume;
  for (int k = 0; k < 4; ++k) neighbourhood += star_volume_[tet[k]];
  const double e_n = neighbourhood > 1e-12 * voxel_volume_ ? std::abs(volume) / neighbourhood : 1;
  return float(w.regional * e_r + w.gradient * e_g + w.shape * e_s + w.volume * e_v +
               w.neighbour * e_n);
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
  if (dead_[cell]) {
    plan.outcome = Outcome::kDead;
    return plan;
  }
  const double volume = cell_volume_.empty() ? CellVolume(tet) : cell_volume_[cell];
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
    plan.error = PlanError(tet, volume, -1);
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
    // Rule 4, estimated from the pass-start marks: TryCollapse decides exactly.
    unsigned touch = 0;
    for (int k = 0; k < 4; ++k)
      touch |= cross_touch_.empty() || !cross_touch_[tet[k]] ? 0u : 1u << k;
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
  plan.error = PlanError(tet, volume, slot);
  return plan;
}

bool CollapseEngine::GatherNeighbours(int32_t cell, int slot, const float* p) {
  static constexpr uint8_t kBits[16] = {0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4};
  a_set_.clear();
  d_set_.clear();
  const int32_t* tet = &mesh_.tets[4 * int64_t(cell)];
  const float* P = mesh_.positions.data();
  const double min6 = 6.0 * min_volume_;
  for (int k = 0; k < 4; ++k) {
    const int32_t v = tet[k];
    for (int64_t e = adjacency_.offsets[v]; e < adjacency_.offsets[v + 1]; ++e) {
      const int32_t n = adjacency_.tet_ids[e];
      if (n == cell || dead_[n]) continue;
      const int32_t* other = &mesh_.tets[4 * int64_t(n)];
      unsigned mask = 0;
      for (int q = 0; q < 4; ++q) {
        for (int j = 0; j < 4; ++j) mask |= other[q] == tet[j] ? 1u << j : 0u;
      }
      // A cell sharing several vertices is met once per shared vertex: keep the first.
      if (std::countr_zero(mask) != k) continue;
      if (kBits[mask] > 1) {
        d_set_.push_back({n, uint8_t(mask)});
        continue;
      }
      a_set_.push_back({n, uint8_t(mask)});
      // Rule 6 (when the collapse point is known): the moved vertex must stay on the same side
      // of the opposite face, with at least the guard volume.
      if (p != nullptr && k != slot) {
        const float* q[4];
        for (int j = 0; j < 4; ++j) q[j] = other[j] == v ? p : P + 3 * other[j];
        if (!(Orient6(q[0], q[1], q[2], q[3]) >= min6)) return false;
      }
    }
  }
  return true;
}

CollapseResult CollapseEngine::TryCollapse(int32_t cell) {
  CollapseResult result;
  if (dead_[cell]) {
    result.outcome = Outcome::kDead;
    return result;
  }
  if (locked_[cell]) {
    result.outcome = Outcome::kLocked;
    return result;
  }
  int32_t tet[4];
  std::copy_n(&mesh_.tets[4 * int64_t(cell)], 4, tet);
  // A cell rejected for its neighbourhood stays rejected until a collapse changes a cell
  // around one of its vertices (the decision depends on nothing else).
  if (rejected_at_[cell] != 0 && std::max({touched_[tet[0]], touched_[tet[1]], touched_[tet[2]],
                                           touched_[tet[3]]}) < rejected_at_[cell]) {
    result.outcome = Outcome::kUnchanged;
    return result;
  }
  const CellPlan plan = PlanCell(cell);
  result.error = plan.error;
  if (plan.outcome != Outcome::kCollapsed) {
    result.outcome = plan.outcome;
    return result;
  }

  int slot = plan.target_slot;
  const bool paper = options_.policy == SimplifyPolicy::kPaper;
  bool any_feature = false;
  int bslot = -1;
  for (int k = 0; k < 4; ++k) {
    any_feature |= IsFeature(tet[k]);
    if (IsBoundary(tet[k])) bslot = k;
  }
  // Rule 4 needs the whole neighbourhood first; cross-region cells are never created during a
  // pass, so only cells with a vertex marked at the pass start can have one around them.
  bool near_crossing = false;
  for (int k = 0; k < 4; ++k) near_crossing |= cross_touch_[tet[k]] != 0;
  const bool rule4 = paper && !any_feature && near_crossing;
  if (rule4) {
    GatherNeighbours(cell, -1, nullptr);
    // Rule 4 on the current neighbourhood. (a) Cross-region cells in A(τ) ∪ D(τ): collapse to
    // the vertex τ shares with them (with several, one common to all of them).
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
      if (common == 0) {
        result.outcome = Outcome::kCrossRegionNeighbours;
        rejected_at_[cell] = ++clock_;
        return result;
      }
      slot = BestSlot(tet, common);
    } else {
      slot = bslot;
    }
    // (b) More than one feature cell and more than one feature vertex in A(τ): keep τ. Cells of
    // D(τ) may hold any number of feature vertices.
    int feature_cells = 0;
    if (crossing > 0) {
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
      if (feature_cells > 1 && two_features) {
        result.outcome = Outcome::kFeatureNeighbourhood;
        rejected_at_[cell] = ++clock_;
        return result;
      }
    }
    if (slot != plan.target_slot) {
      result.error =
          PlanError(tet, cell_volume_.empty() ? CellVolume(tet) : cell_volume_[cell], slot);
    }
  }

  // The collapse point, rounded to the stored float precision before the flip check so the
  // check sees exactly the coordinates the mesh will hold.
  float p[3];
  const float* P = mesh_.positions.data();
  if (slot >= 0) {
    std::copy_n(P + 3 * tet[slot], 3, p);
  } else {
    for (int c = 0; c < 3; ++c) {
      p[c] = float(0.25 * (double(P[3 * tet[0] + c]) + P[3 * tet[1] + c] + P[3 * tet[2] + c] +
                           P[3 * tet[3] + c]));
    }
  }
  // Rule 6: every cell of A(τ) whose shared vertex moves must stay positive (and not a sliver).
  bool unflipped = true;
  if (rule4) {
    const double min6 = 6.0 * min_volume_;
    for (const Neighbour& n : a_set_) {
      const int k = std::countr_zero(unsigned(n.shared_mask));
      if (k == slot) continue;
      const int32_t* other = &mesh_.tets[4 * int64_t(n.cell)];
      const float* q[4];
      for (int j = 0; j < 4; ++j) q[j] = other[j] == tet[k] ? p : P + 3 * other[j];
      unflipped &= Orient6(q[0], q[1], q[2], q[3]) >= min6;
    }
  } else {
    unflipped = GatherNeighbours(cell, slot, p);
  }
  if (!unflipped) {
    result.outcome = Outcome::kFlip;
    rejected_at_[cell] = ++clock_;
    return result;
  }

  // Apply: the survivor takes the collapse point; the other vertices merge into it.
  int32_t survivor = slot >= 0 ? tet[slot] : *std::min_element(tet, tet + 4);
  if (slot < 0) {
    double s = 0, d = 0;
    for (int k = 0; k < 4; ++k) {
      s += mesh_.scalars[tet[k]];
      d += mesh_.interface_distance[tet[k]];
    }
    // The centroid's value: the mean of the four, which is also the linear interpolation of
    // the field at the centroid (§2.2.3.2's s'_n).
    mesh_.scalars[survivor] = float(0.25 * s);
    mesh_.interface_distance[survivor] = float(0.25 * d);
    mesh_.labels[survivor] = CellRegion(mesh_.labels[tet[0]], mesh_.labels[tet[1]],
                                        mesh_.labels[tet[2]], mesh_.labels[tet[3]]);
    mesh_.vertex_flags[survivor] = 0;  // no feature or boundary vertex goes to a centroid
    std::copy_n(p, 3, &mesh_.positions[3 * int64_t(survivor)]);
  }
  for (int k = 0; k < 4; ++k) {
    if (tet[k] != survivor) parent_[tet[k]] = survivor;
  }
  for (const Neighbour& n : a_set_) {
    const int k = std::countr_zero(unsigned(n.shared_mask));
    int32_t* other = &mesh_.tets[4 * int64_t(n.cell)];
    for (int j = 0; j < 4; ++j) {
      if (other[j] == tet[k]) other[j] = survivor;
    }
    locked_[n.cell] = 1;  // §2.2.4 step 2g
  }
  for (const Neighbour& n : d_set_) dead_[n.cell] = 1;  // step 2f: degenerate
  // Every vertex whose star changed: the vertices of the cells of A(τ) and D(τ).
  ++clock_;
  for (const auto* set : {&a_set_, &d_set_}) {
    for (const Neighbour& n : *set) {
      for (int j = 0; j < 4; ++j) touched_[mesh_.tets[4 * int64_t(n.cell) + j]] = clock_;
    }
  }
  touched_[survivor] = clock_;
  dead_[cell] = 1;
  result.cells_removed = int32_t(1 + d_set_.size());
  live_cells_ -= result.cells_removed;
  result.survivor = survivor;
  result.outcome = Outcome::kCollapsed;
  return result;
}

void CollapseEngine::SortedCandidates(int threads, std::vector<int32_t>* cells,
                                      std::vector<float>* errors) {
  const int64_t nt = mesh_.tet_count();
  keys_.resize(nt);
  ParallelFor(nt, threads, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) {
      const CellPlan plan = PlanCell(int32_t(t));
      keys_[t] = plan.outcome == Outcome::kCollapsed ? FloatKey(plan.error) : kNotCandidate;
    }
  });
  cells->clear();
  for (int64_t t = 0; t < nt; ++t) {
    if (keys_[t] != kNotCandidate) cells->push_back(int32_t(t));
  }
  // Stable LSD radix sort on the 32-bit error key, two 16-bit digits: ids enter in increasing
  // order, so ties stay ordered by cell id.
  const size_t n = cells->size();
  keys_tmp_.resize(n);
  ids_tmp_.resize(n);
  std::vector<uint32_t>& k0 = sort_keys_;
  k0.resize(n);
  for (size_t i = 0; i < n; ++i) k0[i] = keys_[(*cells)[i]];
  std::vector<uint32_t>& count = sort_count_;
  count.resize(65537);
  for (int shift = 0; shift < 32; shift += 16) {
    std::fill(count.begin(), count.end(), 0);
    for (size_t i = 0; i < n; ++i) ++count[((k0[i] >> shift) & 0xFFFF) + 1];
    for (int d = 0; d < 65536; ++d) count[d + 1] += count[d];
    for (size_t i = 0; i < n; ++i) {
      const uint32_t pos = count[(k0[i] >> shift) & 0xFFFF]++;
      keys_tmp_[pos] = k0[i];
      ids_tmp_[pos] = (*cells)[i];
    }
    k0.swap(keys_tmp_);
    cells->swap(ids_tmp_);
  }
  errors->resize(n);
  for (size_t i = 0; i < n; ++i) std::memcpy(&(*errors)[i], &k0[i], 4);
}

void CollapseEngine::Finish(TetMesh* out, std::vector<int32_t>* vertex_map) {
  const int64_t nv = mesh_.vertex_count(), nt = mesh_.tet_count();
  std::vector<int32_t> new_id(nv, -1);
  int64_t live = 0;
  for (int64_t t = 0; t < nt; ++t) {
    if (dead_[t]) continue;
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
    if (dead_[t]) continue;
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
