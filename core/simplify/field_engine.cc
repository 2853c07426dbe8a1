// Field-accurate simplification (SimplifyPolicy::kField).
//
// References: M. Garland, Y. Zhou, "Quadric-based simplification in any dimension", ACM TOG
// 2005 (quadrics of the graph of a field); P. Cignoni et al., "Simplification of tetrahedral
// meshes with accurate error evaluation", IEEE Vis 2000 (why the field, not the geometry, is
// what a volume mesh must keep). The design and the constraint rules are ours: README.md.
//
// Half-edge collapse u -> v: u disappears, every cell around u that does not hold v gets v in
// its place, the cells holding both are deleted. Positions and values of surviving vertices
// never change, so every kept vertex still carries its exact voxel sample and the grid points
// of kept vertices are reproduced exactly.
#include "core/simplify/field_engine.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cmath>
#include <limits>
#include <new>
#include <type_traits>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/bit_set.h"
#include "core/common/huge_pages.h"
#include "core/common/parallel.h"
#include "core/common/status.h"
#include "core/mesh/tetrahedralize.h"
#include "core/simplify/collapse_engine.h"

namespace decima::simplify_internal {
namespace {

// A symmetric 5x5 quadric over (x, y, z, s, 1), upper triangle row by row.
constexpr int kQuadricSize = 15;
constexpr int kWeightEntry = 12;  // (3, 3): the sum of the weights (a_s = -1 in every plane)
// Collapses of feature vertices (inside their interface layer) rank as if their field error were
// this many times larger, so free vertices go first and the interfaces keep their exact samples
// as long as the target allows (CT head at 50 %: interface RMSE 2.1 -> 0.9, PSNR unchanged).
constexpr double kFeatureCostFactor = 4;
// Parallel rounds: one slab per kMinSlabVoxels of the slab axis, cuts at least kMinCutVoxels
// apart, at most kMaxSlabs slabs and kMaxRounds rounds, and the last 1/kSerialShare of the
// target left to the serial loop. A cut freezes about two rings on each side for a round, so
// thin slabs freeze much of themselves and their order departs far from the serial loop's
// (README "Slab axis and slab width").
constexpr double kMinSlabVoxels = 12;
constexpr double kMinCutVoxels = 4;
constexpr int kMaxSlabs = 8;
constexpr int kMaxRounds = 16;
constexpr int64_t kSerialShare = 8;
// The frontier pass keeps, per block of 2^kRangeShift consecutive cell ids, an interval of the
// slab axis that holds every current vertex of the block's live cells, and skips the blocks
// whose interval no cut crosses.
constexpr int kRangeShift = 10;
// A vertex's state in a round (frontier_): on the frontier it stays where it is; near it (a cell
// of its star holds a frontier vertex) it is not queued, since it cannot collapse this round.
constexpr uint8_t kOnFrontier = 1, kNearFrontier = 2;
// Axes at least this share of the longest may carry the slabs (SlabAxis).
constexpr double kSlabAxisShare = 0.9;
// The label guard (InterfaceMode::kFree, README "Interfaces free inside their voxels"). The metric
// (core/metrics ResampleOnGrid) counts a point as inside a cell when every barycentric coordinate
// is >= -kMetricInside, takes the lowest such cell id and gives the point the cell's dominant
// label there (DominantLabelSlot, tet_mesh.h: the largest sum of coordinates of one label's
// vertices, ties to the lower slot). The guard computes the same coordinates from the same float
// positions (in mm instead of grid index units: equal up to rounding, ~1e-13), and makes the
// metric's answer independent of which cell it picks and of the tie rule: every cell within
// kMetricInside + kInsideSlack of a sample must give the sample's own label a weight ahead of
// every other label's by kLabelMargin, and at least one new cell must hold it within
// kMetricInside - kInsideSlack (coverage).
constexpr double kMetricInside = 1e-5;
constexpr double kInsideSlack = 1e-7;
// Also covers a sample that lies on a face the star shares with a cell outside it, whose
// coordinates in the two cells differ by the (float) distance to the face over the cells' heights.
constexpr double kLabelMargin = 1e-3;

// p^T q p at p = (a, b, c, d, 1): the diagonal term of each row, then twice the row's
// off-diagonal sum. Written out rather than as loops over an array: GCC vectorised those through
// the stack, and the loads then waited on failed store forwarding (perf: a third of SetCosts).
inline double EvaluateQuadric(const double* q, double a, double b, double c, double d) {
  double r = q[0] * a * a;
  r += 2 * a * (q[1] * b + q[2] * c + q[3] * d + q[4]);
  r += q[5] * b * b;
  r += 2 * b * (q[6] * c + q[7] * d + q[8]);
  r += q[9] * c * c;
  r += 2 * c * (q[10] * d + q[11]);
  r += q[12] * d * d;
  r += 2 * d * q[13];
  return r + q[14];
}

// q' = M^T q M with M the translation p -> p + d of the first four coordinates: the same
// quadric, expressed around an origin moved by -d (q was centred at o, q' is centred at o + d).
inline void TranslateQuadric(const float* q, const double d[4], double out[15]) {
  double full[5][5];
  for (int i = 0, k = 0; i < 5; ++i) {
    for (int j = i; j < 5; ++j, ++k) full[i][j] = full[j][i] = double(q[k]);
  }
  // (M^T Q M)_ij with M = I except M(i, 4) = d_i for i < 4.
  double qm[5][5];  // Q M
  for (int i = 0; i < 5; ++i) {
    for (int j = 0; j < 4; ++j) qm[i][j] = full[i][j];
    double last = full[i][4];
    for (int k = 0; k < 4; ++k) last += full[i][k] * d[k];
    qm[i][4] = last;
  }
  for (int i = 0, k = 0; i < 5; ++i) {
    for (int j = i; j < 5; ++j, ++k) {
      double v = qm[i][j];
      if (i == 4) {
        for (int m = 0; m < 4; ++m) v += d[m] * qm[m][j];
      }
      out[k] = v;
    }
  }
}

// q += a a^T (unit weight). Unrolled, so that q stays in registers over a vertex's cells: the
// set-up adds one plane per (vertex, cell), 140 M of them on the Colin27 MRI.
inline void AddPlane(double* q, const double a[5]) {
  int k = 0;
#pragma GCC unroll 5
  for (int i = 0; i < 5; ++i) {
#pragma GCC unroll 5
    for (int j = i; j < 5; ++j) q[k++] += a[i] * a[j];
  }
}

// How a vertex may move (README "Interfaces and hull kept as sets").
enum class Freedom : uint8_t {
  kFree,    // no feature or hull flag: may collapse onto any neighbour
  kPlanar,  // inside a planar patch of its constraint surface: onto a neighbour in the patch
  kCrease,  // on a straight crease: onto one of its two crease neighbours
  kPinned,  // a corner, a non-manifold spot, a curved patch: never moves
};

struct HeapEntry {
  float cost;
  int32_t vertex;
  uint32_t version;
  // The queue order: cost, then the lower vertex id.
  bool Before(const HeapEntry& o) const {
    return cost < o.cost || (cost == o.cost && vertex < o.vertex);
  }
};

// A 4-ary min-heap of queue entries. Why not std::priority_queue: the queue holds up to a
// million entries, far out of cache, and a binary heap's pop touches ~20 levels (perf: the
// sift's loads were a third of the serial loop's own time); four children per node halve the
// levels and sit on one or two cache lines. Any heap pops the same sequence of (cost, vertex)
// keys, and entries with equal keys are copies for one vertex of which one is current, so the
// collapses do not change.
class QueueHeap {
 public:
  bool empty() const { return h_.empty(); }
  size_t size() const { return h_.size(); }
  const HeapEntry& top() const { return h_[0]; }
  void Assign(std::vector<HeapEntry> entries) {
    h_ = std::move(entries);
    if (h_.size() < 2) return;
    for (size_t i = (h_.size() - 2) / 4 + 1; i-- > 0;) SiftDown(i, h_[i]);
  }
  void push(const HeapEntry& e) {
    size_t i = h_.size();
    h_.push_back(e);
    while (i > 0) {
      const size_t parent = (i - 1) / 4;
      if (!e.Before(h_[parent])) break;
      h_[i] = h_[parent];
      i = parent;
    }
    h_[i] = e;
  }
  void pop() {
    const HeapEntry last = h_.back();
    h_.pop_back();
    if (!h_.empty()) SiftDown(0, last);
  }

 private:
  // Places e at or below slot i.
  void SiftDown(size_t i, const HeapEntry e) {
    const size_t n = h_.size();
    for (;;) {
      const size_t first = 4 * i + 1;
      if (first >= n) break;
      const size_t end = std::min(first + 4, n);
      size_t best = first;
      for (size_t k = first + 1; k < end; ++k) {
        if (h_[k].Before(h_[best])) best = k;
      }
      if (!h_[best].Before(e)) break;
      h_[i] = h_[best];
      i = best;
    }
    h_[i] = e;
  }
  std::vector<HeapEntry> h_;
};

struct Candidate {
  double cost;
  int32_t target;
};

// The order of candidates everywhere: cost, then the lower target id (determinism).
inline bool Cheaper(const Candidate& a, const Candidate& b) {
  return a.cost < b.cost || (a.cost == b.cost && a.target < b.target);
}

// Whether a cell (four vertex ids) holds vertices of two labels: with a label per vertex, the
// interface is the set of such cells.
inline bool HoldsTwoLabels(const uint8_t* labels, const int32_t* c) {
  const uint8_t l = labels[c[0]];
  return labels[c[1]] != l || labels[c[2]] != l || labels[c[3]] != l;
}

// A face around a vertex u as its other two vertices a < b and whether its cell holds vertices of
// two labels, in one integer: (a, b, mixed) from the high bits down, so that sorting the integers
// (Classify sorts a few dozen per call) groups the faces by (a, b) with one comparison each.
using FaceKey = uint64_t;
inline FaceKey MakeFaceKey(int32_t a, int32_t b, bool mixed) {
  return (uint64_t(uint32_t(a)) << 33) | (uint64_t(uint32_t(b)) << 1) | uint64_t(mixed);
}
inline int32_t FaceA(FaceKey f) { return int32_t(f >> 33); }
inline int32_t FaceB(FaceKey f) { return int32_t((f >> 1) & 0xffffffffu); }
inline bool FaceMixed(FaceKey f) { return f & 1; }
inline bool SameFace(FaceKey f, FaceKey g) { return (f >> 1) == (g >> 1); }

// A cell of a vertex's star with its current vertices, resolved once per gather: the rules, the
// candidates and the collapse all read the star, and each resolution is four root_ loads.
struct StarCell {
  int32_t id;
  int32_t v[4];
};
using Star = std::vector<StarCell>;

// The vertices met so far in one call (Targets' candidates, Collapse's touched vertices): open
// addressing in a table at most half full, emptied by a new generation. Why not a flag per
// vertex of the mesh: that array (4 bytes per vertex and thread) missed the cache at nearly every
// insert (perf on phantom:256: the hottest instructions of Targets and Collapse).
class VertexSet {
 public:
  // Empties the set for at most `most` insertions.
  void Reset(size_t most) {
    if (slots_.empty() || 2 * most > slots_.size()) {
      slots_.assign(std::bit_ceil(std::max<size_t>(64, 2 * most)), Slot{0, 0});
      shift_ = 32 - std::countr_zero(slots_.size());
      generation_ = 0;
    }
    if (++generation_ == 0) {
      std::fill(slots_.begin(), slots_.end(), Slot{0, 0});
      generation_ = 1;
    }
  }
  // Adds x; false if it was there already.
  bool Insert(int32_t x) {
    const size_t mask = slots_.size() - 1;
    // Fibonacci hashing, the product's high bits: ids of neighbours differ by multiples of the
    // grid's row and slice, which the low bits would map to few slots.
    for (size_t i = (uint32_t(x) * 0x9E3779B1u) >> shift_;; i = (i + 1) & mask) {
      Slot& slot = slots_[i];
      if (slot.generation != generation_) {
        slot = {x, generation_};
        return true;
      }
      if (slot.vertex == x) return false;
    }
  }

 private:
  struct Slot {
    int32_t vertex;
    uint32_t generation;
  };
  std::vector<Slot> slots_;
  int shift_ = 32;
  uint32_t generation_ = 0;
};

// Per-thread working memory of the scoring functions (the initial scoring runs in parallel).
struct Scratch {
  Star star;
  std::vector<int32_t> patch;
  std::vector<FaceKey> faces;
  std::vector<Candidate> candidates;
  VertexSet seen;
};

// What the queue keeps per vertex, in one 32-byte record: the serial loop reads and writes these
// fields together for every vertex around a collapse, and they sit at scattered places of the
// mesh, so one cache line per vertex instead of one per field array. Trivial, so that the array
// is filled in parallel (Setup); Initial is the state of a vertex not scored yet.
struct QueueState {
  double cost;  // of the best collapse u -> best
  double second_cost;
  int32_t best;
  int32_t second;    // runner-up target (-1 unknown), to replace a lost best
  uint32_t version;  // of the vertex's current queue entry (older entries are stale)
  uint8_t blocked;   // no valid collapse at the last try; re-tried when touched
  uint8_t stale;     // constrained vertex whose star changed: re-score when popped
  uint8_t flags;     // the vertex's flags (a copy of flags_ next to the rest)
  static QueueState Initial(uint8_t flags) {
    const double inf = std::numeric_limits<double>::infinity();
    return {inf, inf, -1, -1, 0, 0, 0, flags};
  }
};
static_assert(sizeof(QueueState) == 32);
static_assert(std::is_trivially_default_constructible_v<QueueState>);

// The per-vertex arrays of the loop: filled in parallel by Setup, on huge pages, and cache-line
// aligned so that no 32-byte QueueState straddles two lines (FillLaterAllocator).
template <typename T>
using VertexArray = std::vector<T, FillLaterAllocator<T>>;

// PreparePlanes: per star cell, the plane of the face opposite u, scaled so that n . p >= min is
// "u moved to p leaves the cell at least min_volume".
struct Plane {
  double n[3];
  double min;
  // Whether u moved to p leaves the cell at least min_volume.
  bool Keeps(const double p[3]) const { return n[0] * p[0] + n[1] * p[1] + n[2] * p[2] >= min; }
};

// One collapse u -> v as the level record keeps it, with the cost that ordered it (to merge the
// slabs' records of a round).
struct LoggedCollapse {
  int32_t u, v;
  int64_t deleted;
  float cost;
};

// A cell a collapse would create, ready for barycentric coordinates: l_k = r_k . (p - a) / det for
// k = 1..3 and l_0 = 1 - l_1 - l_2 - l_3, as the metric computes them (T^-1 by its rows).
struct NewCell {
  // Left uninitialised: KeepsLabels sets every field it reads (a and r once `framed`), and
  // emplace_back() zeroing the 176 bytes was an eighth of its time (perf, CT head at 80 %).
  NewCell() {}
  int32_t id;
  int32_t v[4];
  double a[3];
  double r[3][3];       // rows of T^-1 (T's columns are the edges from v[0])
  double lo[3], hi[3];  // bounding box, widened by the inside tolerance
  uint8_t labels[4];
  bool mixed;
  bool framed;  // a and r are set (on the first sample inside the box: most cells get none)
};

// What one run of the greedy loop owns: its queue, its working memory and its counts. The serial
// loop has one; in a parallel round every block of the mesh gets one (README "Parallel rounds").
struct Worker {
  QueueHeap heap;
  Scratch scratch;
  std::vector<int32_t> touched, changed;
  std::vector<const StarCell*> guarded;  // Valid: the moved cells the shape guard checks last
  std::vector<Plane> planes;
  int32_t failed = -1;  // InKernel: the star cell that refused the last target
  // KeepsLabels: the new cells of the last try, and where each sample of the star goes if the last
  // valid try (relocated_for) is made.
  std::vector<NewCell> new_cells;
  std::vector<int32_t> samples;  // KeepsLabels: the samples listed in u's cells
  std::vector<int32_t> heads;    // KeepsLabels: the lists' current entries while they are walked
  std::vector<std::pair<int32_t, int32_t>> relocated;
  std::pair<int32_t, int32_t> relocated_for{-1, -1};
  // KeepsRegionTopology: one label's part of u's link.
  std::vector<int32_t> link_vertices, link_parent;
  std::vector<uint64_t> link_edges;
  int64_t removed = 0, collapses = 0, pops = 0, invalid_tries = 0, requeued = 0,
          constrained_moves = 0;
  double last_error = 0, max_error = 0;
  bool tolerance_hit = false;
  std::vector<LoggedCollapse>* log = nullptr;  // where the collapses go, if levels are recorded
  // Starts a new queue with fresh counts; the working memory is kept.
  void Reset(std::vector<HeapEntry> entries) {
    heap.Assign(std::move(entries));
    removed = collapses = pops = invalid_tries = requeued = constrained_moves = 0;
    last_error = max_error = 0;
    tolerance_hit = false;
  }
};

// A vertex with a queue entry and its cost, as the parallel rounds list them.
struct QueuedVertex {
  float cost;
  int32_t v;
};

// Why Drain returned.
enum class Drained { kLimit, kStopCost, kEmpty, kCancelled };

class FieldEngine {
 public:
  FieldEngine(const TetMesh& mesh, const SimplifyOptions& options, int threads,
              SimplifyLevels* levels, const FieldWindow* window = nullptr)
      : in_(mesh), options_(options), threads_(threads), levels_(levels), window_(window) {}

  absl::Status Run(int64_t target, double tolerance, const ProgressFn& progress,
                   const CancelToken* cancel, SimplifyResult* result);
  // The test hook (CheckFieldCollapse): the rules for one collapse u -> v on the input mesh.
  FieldCollapseCheck CheckOne(int32_t u, int32_t v);
  // The test hook PinnedFieldVertices.
  std::vector<uint8_t> Pinned();

 private:
  void Setup();
  template <typename Fn>
  void ForEachCell(int32_t v, Fn&& fn);
  void GatherStar(int32_t v, Star* star);
  Freedom Classify(int32_t u, Scratch& s, int32_t along[2]) const;
  void Targets(int32_t u, Scratch& s);
  void Candidates(int32_t u, Scratch& s);
  // Fills in the cost of every collapse u -> c.target.
  void SetCosts(int32_t u, std::vector<Candidate>* candidates) const;
  bool Score(int32_t u, Scratch& s, double* cost, int32_t* best);
  bool Rescore(int32_t u, Worker& w) {
    st_[u].stale = 0;
    return Score(u, w.scratch, &st_[u].cost, &st_[u].best);
  }
  void PreparePlanes(int32_t u, const Star& star, Worker& w);
  bool InKernel(int32_t v, const Star& star, Worker& w);
  bool Valid(int32_t u, int32_t v, const Star& star, Worker& w);
  bool KeepsLabels(int32_t u, int32_t v, const Star& star, Worker& w);
  bool KeepsRegionTopology(int32_t u, int32_t v, const Star& star, Worker& w) const;
  int64_t Collapse(int32_t u, int32_t v, const Star& star, Worker& w);
  void Push(int32_t u, Worker& w) {
    w.heap.push({static_cast<float>(st_[u].cost), u, ++st_[u].version});
  }
  bool Queued(int64_t v) const {
    return root_[v] == v && valence_[v] > 0 && st_[v].best >= 0 && !st_[v].blocked;
  }
  Drained Drain(Worker& w, int64_t limit, float stop_cost, bool in_block, double tolerance,
                const CancelToken* cancel);
  bool InTerritory(const Star& star) const;
  int64_t ParallelRounds(int64_t target, const ProgressFn& progress, const CancelToken* cancel,
                         Worker* totals, absl::Status* status);
  void ReleaseQueue();
  void Finish(SimplifyResult* result);
  // Appends collapses to the level record (levels_), which holds their deleted cells in 16 bits.
  absl::Status Record(const std::vector<LoggedCollapse>& collapses);

  // u's quadric in double with its point and cost factor: the candidates of u share it.
  struct Source {
    int32_t u;
    double q[kQuadricSize];
    double factor;
  };
  void LoadSource(int32_t u, Source* src) const {
    src->u = u;
    const float* qf = &quadric_[kQuadricSize * int64_t(u)];
    for (int k = 0; k < kQuadricSize; ++k) src->q[k] = qf[k];
    src->factor = (flags_[u] & kFeatureVertex) ? kFeatureCostFactor : 1.0;
  }
  // Cost of the collapse u -> x: u's quadric at x's point (x's position and value), plus the
  // shortest-edge tie break. Depends only on Q_u and x, both fixed until u or x collapses.
  double Cost(const Source& src, int32_t x) const {
    const int32_t u = src.u;
    // Quadrics are stored around their own vertex's point (x_u, s_u), so floats suffice.
    const double q = std::max(0.0, EvaluateQuadric(src.q, double(pos_[3 * x]) - pos_[3 * u],
                                                   double(pos_[3 * x + 1]) - pos_[3 * u + 1],
                                                   double(pos_[3 * x + 2]) - pos_[3 * u + 2],
                                                   double(in_.scalars[x]) - in_.scalars[u]));
    return src.factor * q + TieBreak(u, x);
  }
  double Cost(int32_t u, int32_t x) const {
    Source src;
    LoadSource(u, &src);
    return Cost(src, x);
  }
  double TieBreak(int32_t u, int32_t x) const {
    const double dx = double(pos_[3 * x]) - pos_[3 * u],
                 dy = double(pos_[3 * x + 1]) - pos_[3 * u + 1],
                 dz = double(pos_[3 * x + 2]) - pos_[3 * u + 2];
    return tie_break_ * (dx * dx + dy * dy + dz * dz);
  }
  // The inward normals N_k of the faces opposite each vertex of a positive cell, scaled by
  // twice their areas, and their squared lengths. For a positive cell
  // (p1 - p0) . ((p2 - p0) x (p3 - p0)) > 0, so N_1..N_3 point from their faces towards p1..p3;
  // the four sum to zero. The dihedral angle at the edge shared by faces i and j is
  // acos(-N_i . N_j / |N_i| |N_j|).
  void InwardNormals(const int32_t* c, double n[4][3], double sq[4]) const {
    const float* a = &pos_[3 * int64_t(c[0])];
    double e[3][3];
    for (int k = 0; k < 3; ++k) {
      const float* b = &pos_[3 * int64_t(c[k + 1])];
      for (int d = 0; d < 3; ++d) e[k][d] = double(b[d]) - a[d];
    }
    Cross(e[1], e[2], n[1]);
    Cross(e[2], e[0], n[2]);
    Cross(e[0], e[1], n[3]);
    for (int d = 0; d < 3; ++d) n[0][d] = -(n[1][d] + n[2][d] + n[3][d]);
    for (int k = 0; k < 4; ++k) sq[k] = n[k][0] * n[k][0] + n[k][1] * n[k][1] + n[k][2] * n[k][2];
  }
  static void Cross(const double* x, const double* y, double* out) {
    out[0] = x[1] * y[2] - x[2] * y[1];
    out[1] = x[2] * y[0] - x[0] * y[2];
    out[2] = x[0] * y[1] - x[1] * y[0];
  }
  static double Dot(const double* x, const double* y) {
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
  }
  // The cosine of the (positive) cell's smallest dihedral angle.
  double MaxDihedralCos(const int32_t* c) const {
    double n[4][3], sq[4];
    InwardNormals(c, n, sq);
    double worst = -1;
    for (int i = 0; i < 4; ++i) {
      for (int j = i + 1; j < 4; ++j) {
        worst = std::max(worst, -Dot(n[i], n[j]) / (std::sqrt(sq[i]) * std::sqrt(sq[j])));
      }
    }
    return worst;
  }
  // Whether every dihedral angle of the (positive) cell is at least the floor: the test of
  // MaxDihedralCos(c) <= max_cos_ without square roots (-N_i . N_j <= cos |N_i| |N_j|, squared
  // where the left side is positive). Valid runs it on every moved cell of every try that
  // passed the cheaper tests, so it is the guard's whole cost; the exact angles are computed
  // only for the few cells it fails.
  bool AboveFloor(const int32_t* c) const {
    double n[4][3], sq[4];
    InwardNormals(c, n, sq);
    const double cos2 = max_cos_ * max_cos_;
    for (int i = 0; i < 4; ++i) {
      for (int j = i + 1; j < 4; ++j) {
        const double dot = Dot(n[i], n[j]);
        if (dot < 0 && dot * dot > cos2 * sq[i] * sq[j]) return false;
      }
    }
    return true;
  }
  double SignedVolume(const int32_t* c) const {
    const float* a = &pos_[3 * c[0]];
    const float* b = &pos_[3 * c[1]];
    const float* d = &pos_[3 * c[2]];
    const float* e = &pos_[3 * c[3]];
    const double b0 = double(b[0]) - a[0], b1 = double(b[1]) - a[1], b2 = double(b[2]) - a[2];
    const double d0 = double(d[0]) - a[0], d1 = double(d[1]) - a[1], d2 = double(d[2]) - a[2];
    const double e0 = double(e[0]) - a[0], e1 = double(e[1]) - a[1], e2 = double(e[2]) - a[2];
    return (b0 * (d1 * e2 - d2 * e1) - b1 * (d0 * e2 - d2 * e0) + b2 * (d0 * e1 - d1 * e0)) / 6;
  }

  // Input cell c: loaded from the mesh's tets, or computed from its grid when they are dropped.
  void InputCell(int64_t c, int32_t t[4]) const { in_.Cell(c, t); }
  // Cell c as it is now: its input vertices, each replaced by the live vertex it became.
  void CellAt(int32_t c, int32_t t[4]) const {
    int32_t in[4];
    InputCell(c, in);
    for (int k = 0; k < 4; ++k) t[k] = root_[in[k]];
  }

  const TetMesh& in_;
  const SimplifyOptions& options_;
  const int threads_;
  SimplifyLevels* const levels_;     // null: no level record
  const FieldWindow* const window_;  // null: the whole mesh (field_engine.h)
  // With a window: per input cell, the output cell Finish gives it (-1: deleted), and per input
  // vertex the input cell whose bucket lists it when the loop ended (-1: none).
  std::vector<int32_t> sample_home_;

  int64_t nv_ = 0, nt_ = 0;
  const float* pos_ = nullptr;  // the input positions, mm (they never change)
  std::vector<uint8_t> flags_;
  BitSet dead_;
  // InterfaceMode::kFree: the label guard's samples. Every removed input vertex is a voxel centre
  // whose label must stay; it is listed in one live cell that holds it (bucket_head_ per cell,
  // sample_next_ per input vertex). A vertex still alive is its own sample, exactly at a vertex
  // of its own label, and needs no list.
  bool free_interfaces_ = false;
  std::vector<int32_t> bucket_head_, sample_next_;
  // Adjacency: the input CSR rows, linked per merge class (survivor first).
  VertexArray<int32_t> row_start_;  // int32: 4 * cells fits (Simplify checks)
  VertexArray<int32_t> row_len_, class_next_, class_tail_;
  std::vector<int32_t, FillLaterAllocator<int32_t>> cell_ids_;
  VertexArray<int32_t> valence_;  // live cells around a live vertex
  // The live vertex each input vertex is now: itself while alive, else the survivor of its merge
  // class. A cell is its input vertices through root_, so the engine keeps no copy of the cells
  // (16 bytes per cell: 1.3 GB on phantom:256) and a collapse rewrites no cell.
  VertexArray<int32_t> root_;
  // Per vertex, centred at its own point (position, value) so that float keeps the precision.
  VertexArray<float> quadric_;
  VertexArray<QueueState> st_;
  double voxel_volume_ = 1, min_volume_ = 0, tie_break_ = 0;
  double max_cos_ = 1;  // cos of the dihedral floor (1: no shape guard)
  // Parallel rounds: per vertex, whether a neighbour lies in another block (kOnFrontier: it
  // waits for a round with other cuts, or the serial loop) or it has a frontier neighbour
  // (kNearFrontier). Per block of cell ids, an interval of the slab axis holding the current
  // vertices of its live cells (kRangeShift); a collapse in a round widens its cells' intervals
  // to the survivor (slab_axis_ >= 0 while the rounds run).
  std::vector<uint8_t> frontier_;
  std::vector<float> range_lo_, range_hi_;
  int slab_axis_ = -1;
  // Widens cell c's block interval to hold z. Slabs of one round may share a block, so atomic;
  // nearly always z is inside already and this is two loads.
  void WidenRange(int32_t c, float z) {
    const int64_t b = c >> kRangeShift;
    std::atomic_ref<float> lo(range_lo_[b]), hi(range_hi_[b]);
    for (float l = lo.load(std::memory_order_relaxed);
         z < l && !lo.compare_exchange_weak(l, z, std::memory_order_relaxed);) {
    }
    for (float h = hi.load(std::memory_order_relaxed);
         z > h && !hi.compare_exchange_weak(h, z, std::memory_order_relaxed);) {
    }
  }
};

template <typename Fn>
void FieldEngine::ForEachCell(int32_t v, Fn&& fn) {
  // The merge class in batches: its links first, asking for each member's row on the way, so
  // that the rows' loads overlap the walk instead of each waiting for the link before it.
  constexpr int kBatch = 16;
  int32_t batch[kBatch];
  int32_t prev = -1;  // the last member kept in the class
  for (int32_t next = v; next >= 0;) {
    int members = 0;
    for (; next >= 0 && members < kBatch; next = class_next_[next]) {
      batch[members++] = next;
      __builtin_prefetch(cell_ids_.data() + row_start_[next]);
    }
    for (int m = 0; m < members; ++m) {
      const int32_t r = batch[m];
      int32_t* ids = cell_ids_.data() + row_start_[r];
      int32_t n = row_len_[r];
      for (int32_t i = 0; i < n;) {
        if (dead_.TestShared(ids[i])) {
          ids[i] = ids[--n];  // drop dead cells as the walk meets them
          continue;
        }
        fn(ids[i]);
        ++i;
      }
      if (n != row_len_[r]) row_len_[r] = n;
      if (n == 0 && r != v) {
        // A row never gains a cell: the member leaves the class for good (CT head 50 %: almost
        // half of the members the walks met had none left). Its root_ stays at the class's
        // root of now, which Finish follows on.
        class_next_[prev] = class_next_[r];
        if (class_tail_[v] == r) class_tail_[v] = prev;
      } else {
        prev = r;
      }
    }
  }
}

void FieldEngine::GatherStar(int32_t v, Star* star) {
  // In phases, because each step waits on memory the previous one names: the cell ids (the
  // adjacency rows), their input vertices (asked for all at once), then what those vertices
  // became.
  star->clear();
  // With the cells dropped, a cell is computed from its id (no load to wait on).
  ForEachCell(v, [&](int32_t c) {
    star->emplace_back().id = c;
    if (!in_.cells_dropped) __builtin_prefetch(&in_.tets[4 * int64_t(c)]);
  });
  for (StarCell& sc : *star) {
    InputCell(sc.id, sc.v);
    for (int k = 0; k < 4; ++k) __builtin_prefetch(&root_[sc.v[k]]);
  }
  for (StarCell& sc : *star) {
    for (int k = 0; k < 4; ++k) sc.v[k] = root_[sc.v[k]];
  }
}

void FieldEngine::Setup() {
  nv_ = in_.vertex_count();
  nt_ = in_.tet_count();
  pos_ = in_.positions.data();
  // A window's flags come from the input grid's cells (its carried cells are simplified ones).
  if (window_ != nullptr && window_->flags_complete) {
    flags_ = in_.vertex_flags;
  } else {
    FieldVertexFlags(in_, options_, threads_, &flags_);
  }
  dead_ = BitSet(nt_);
  free_interfaces_ = options_.interfaces == InterfaceMode::kFree;
  if (free_interfaces_) {
    bucket_head_.assign(nt_, -1);
    sample_next_.assign(nv_, -1);
    if (window_ != nullptr && window_->sample_cell != nullptr) {
      // Samples of removed voxel centres carried in from the window before: each goes back into
      // the bucket of the cell that listed it there. Backwards, so a bucket lists its samples by
      // increasing vertex id.
      for (int64_t s = nv_ - 1; s >= 0; --s) {
        const int32_t c = window_->sample_cell[s];
        if (c < 0) continue;
        sample_next_[s] = bucket_head_[c];
        bucket_head_[c] = int32_t(s);
      }
    }
  }

  VertexTetAdjacency adjacency = BuildVertexTetAdjacency(in_, threads_);
  cell_ids_ = std::move(adjacency.tet_ids);  // the rows are consumed in place
  for (auto* a : {&row_start_, &row_len_, &valence_, &class_next_, &class_tail_, &root_}) {
    a->resize(nv_);  // uninitialised: filled below
  }
  st_.resize(nv_);
  ParallelFor(nv_, threads_, 65536, [&](int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      row_start_[v] = int32_t(adjacency.offsets[v]);
      row_len_[v] = valence_[v] = int32_t(adjacency.offsets[v + 1] - adjacency.offsets[v]);
      class_next_[v] = -1;
      class_tail_[v] = root_[v] = int32_t(v);
      st_[v] = QueueState::Initial(flags_[v]);
    }
  });

  // The mesh's volume in fixed blocks of cells: the same sum on any thread count.
  // (Blocks of 65536 cells, each summed in order, then the blocks in order.)
  constexpr int64_t kVolumeBlock = 65536;
  const double total_volume =
      BlockSum((nt_ + kVolumeBlock - 1) / kVolumeBlock, threads_, 1, [&](int64_t b) {
        double sum = 0;
        in_.ForEachCell(b * kVolumeBlock, std::min(nt_, (b + 1) * kVolumeBlock),
                        [&](int64_t, const int32_t* c) { sum += SignedVolume(c); });
        return sum;
      });
  if (options_.voxel_size_mm > 0) {
    voxel_volume_ = std::pow(options_.voxel_size_mm, 3);
  } else {
    voxel_volume_ = nt_ > 0 ? 5 * total_volume / double(nt_) : 1;
  }
  min_volume_ = options_.min_volume_fraction * voxel_volume_;
  max_cos_ = options_.min_dihedral_degrees > 0
                 ? std::cos(options_.min_dihedral_degrees * M_PI / 180.0)
                 : 1.0;
  float lo_s = std::numeric_limits<float>::infinity(), hi_s = -lo_s;
  for (float s : in_.scalars) {
    lo_s = std::min(lo_s, s);
    hi_s = std::max(hi_s, s);
  }
  if (window_ != nullptr) {  // the whole volume's range, so that windows break ties alike
    lo_s = window_->scalar_lo;
    hi_s = window_->scalar_hi;
  }
  const double range = nv_ > 0 ? std::max(1e-6, double(hi_s) - double(lo_s)) : 1;
  const double voxel = std::cbrt(voxel_volume_);
  // Orders collapses of equal field error (flat regions) shortest edge first, which keeps the
  // cells well shaped; far below any field error that matters (1e-9 of the range squared).
  tie_break_ = 1e-9 * range * range / (voxel * voxel);

  // Quadric of every vertex: the planes of its cells' linear interpolants, one unit weight per
  // cell (volume weights, and volume squared, were measured worse on the CT head at 80 %).
  // A cell's gradient is the same for its four vertices, and computing it (a 3x3 solve) was most
  // of this loop, four times per cell. So each thread computes the gradients of a window of
  // consecutive cell ids once, and the vertices of a block read them there: with the grid's
  // numbering a block's cells are a window not much longer than the block's rows, and a mesh
  // numbered otherwise computes them per row as before.
  constexpr int64_t kBlockVertices = 65536;
  // The gradient of cell t's linear interpolant, in its own frame (edge vectors from its first
  // vertex: differences of float positions, exact in double); NaN if the cell is not positive.
  auto gradient = [&](const int32_t* t) {
    auto at = [&](int k) {
      return Eigen::Vector3d(pos_[3 * t[k]], pos_[3 * t[k] + 1], pos_[3 * t[k] + 2]);
    };
    auto ds = [&](int k) { return double(in_.scalars[t[k]]) - double(in_.scalars[t[0]]); };
    const Eigen::Vector3d p0 = at(0), e0 = at(1) - p0, e1 = at(2) - p0, e2 = at(3) - p0;
    // g solves e g = ds, e's rows being e0, e1, e2: the columns of e's inverse are these cross
    // products over its determinant (less than half the work of Eigen's determinant() and
    // inverse(), which bound this loop).
    const Eigen::Vector3d r0 = e1.cross(e2), r1 = e2.cross(e0), r2 = e0.cross(e1);
    const double det = e0.dot(r0);
    if (!(det > 0)) return Eigen::Vector3d::Constant(std::nan("")).eval();
    return ((ds(1) * r0 + ds(2) * r1 + ds(3) * r2) / det).eval();
  };
  // A window entry: the cell's gradient and its first vertex, the origin of its plane.
  struct CellPlane {
    Eigen::Vector3d gradient;
    int32_t first;
  };
  auto plane = [&](const int32_t* t) { return CellPlane{gradient(t), t[0]}; };
  quadric_.resize(kQuadricSize * nv_);  // uninitialised: every entry is written below
  ParallelFor(nv_, threads_, 4096, [&](int64_t v0, int64_t v1) {
    Scratch scratch;
    std::vector<CellPlane> window;
    int64_t window_lo = 0, window_hi = -1;  // the cells whose planes window holds
    for (int64_t b0 = v0; b0 < v1; b0 += kBlockVertices) {
      const int64_t b1 = std::min(v1, b0 + kBlockVertices);
      // Rows are sorted by cell id: the block's cells lie in [lo, hi].
      int64_t lo = nt_, hi = -1;
      for (int64_t v = b0; v < b1; ++v) {
        if (adjacency.offsets[v + 1] == adjacency.offsets[v]) continue;
        lo = std::min<int64_t>(lo, cell_ids_[adjacency.offsets[v]]);
        hi = std::max<int64_t>(hi, cell_ids_[adjacency.offsets[v + 1] - 1]);
      }
      const int64_t pairs = adjacency.offsets[b1] - adjacency.offsets[b0];
      const bool windowed = hi >= lo && hi - lo + 1 <= 2 * pairs;
      if (windowed) {
        // Consecutive blocks' windows overlap (with the grid's numbering by a slice of cubes,
        // half of each window): the gradients already there move to the front.
        int64_t from = lo;
        if (lo >= window_lo && lo <= window_hi && hi >= window_hi) {
          if (lo > window_lo) {
            std::copy(window.begin() + (lo - window_lo),
                      window.begin() + (window_hi - window_lo + 1), window.begin());
          }
          from = window_hi + 1;
        }
        window.resize(hi - lo + 1);
        in_.ForEachCell(from, hi + 1,
                        [&](int64_t c, const int32_t* t) { window[c - lo] = plane(t); });
        window_lo = lo;
        window_hi = hi;
      }
      for (int64_t v = b0; v < b1; ++v) {
        double q[kQuadricSize] = {};
        const Eigen::Vector3d origin(pos_[3 * v], pos_[3 * v + 1], pos_[3 * v + 2]);
        for (int64_t i = adjacency.offsets[v]; i < adjacency.offsets[v + 1]; ++i) {
          const int64_t c = cell_ids_[i];
          CellPlane p;
          if (windowed) {
            p = window[c - lo];
          } else {
            int32_t cell[4];
            InputCell(c, cell);
            p = plane(cell);
          }
          const Eigen::Vector3d& g = p.gradient;
          if (std::isnan(g.x())) continue;
          const int32_t t0 = p.first;
          const Eigen::Vector3d p0 =
              Eigen::Vector3d(pos_[3 * t0], pos_[3 * t0 + 1], pos_[3 * t0 + 2]) - origin;
          const double a[5] = {g.x(), g.y(), g.z(), -1.0,
                               double(in_.scalars[t0]) - double(in_.scalars[v]) - g.dot(p0)};
          AddPlane(q, a);
        }
        for (int k = 0; k < kQuadricSize; ++k) quadric_[kQuadricSize * v + k] = float(q[k]);
        // v's collapses are scored now, while its cells are in cache: a cost reads only v's
        // quadric and its neighbours' points, and no cell is dead yet.
        Score(int32_t(v), scratch, &st_[v].cost, &st_[v].best);
      }
    }
  });
}

Freedom FieldEngine::Classify(int32_t u, Scratch& s, int32_t along[2]) const {
  const Star& star = s.star;
  std::vector<FaceKey>& faces_ = s.faces;
  std::vector<int32_t>& patch_ = s.patch;
  const uint8_t fu = flags_[u];
  if (fu == 0) return Freedom::kFree;
  const uint8_t label = in_.labels[u];
  // Faces around u, as the pair of their other two vertices; a face met once is on the hull.
  // Only faces whose other two vertices are both flagged can be constraint faces (hull vertices
  // carry kExteriorBoundaryVertex, which the engine relies on anyway: an unflagged vertex is
  // free; layer vertices kFeatureVertex), so only those are listed. The sort below was most of
  // this function's time, and near an interface about half of u's neighbours are unflagged.
  faces_.clear();
  bool touches_mixed = false;
  for (const StarCell& sc : star) {
    const int32_t* t = sc.v;
    const bool mixed = HoldsTwoLabels(in_.labels.data(), t);
    touches_mixed |= mixed;
    int32_t o[3], n = 0;
    for (int k = 0; k < 4; ++k) {
      if (t[k] != u && flags_[t[k]] != 0) o[n++] = t[k];
    }
    for (int i = 0; i < n; ++i) {
      for (int j = i + 1; j < n; ++j) {
        faces_.push_back(MakeFaceKey(std::min(o[i], o[j]), std::max(o[i], o[j]), mixed));
      }
    }
  }
  // A feature vertex is on an interface only if a cell around it holds two labels. The feature
  // band is a distance threshold and can be more than one vertex deep; a vertex whose cells
  // all hold its own label lies inside its region, and collapsing it changes no interface.
  bool feature = (fu & kFeatureVertex) && touches_mixed;
  bool junction = false;
  if (feature && free_interfaces_) {
    // Free interfaces: the label guard (KeepsLabels) decides where an interface vertex of two
    // labels may go, and its voxel layer is no constraint. Where three or more labels meet (a
    // junction curve of the label regions) the vertex keeps the voxel-faces rules below on top of
    // the guard: it slides along a straight run of its layers' crease (the curve) or within a
    // plane, and a corner of its layers (a junction corner) stays.
    uint8_t seen[2] = {label, label};
    int nlabels = 1;
    for (const StarCell& sc : star) {
      for (int k = 0; k < 4 && nlabels < 3; ++k) {
        const uint8_t l = in_.labels[sc.v[k]];
        if (l == seen[0] || (nlabels > 1 && l == seen[1])) continue;
        if (nlabels < 2) seen[1] = l;
        ++nlabels;
      }
    }
    junction = nlabels >= 3;
    if (!junction) feature = false;  // only the hull constrains it now
  }
  // At a junction a layer face also records the label across it (key 1 + that label): where the
  // label across changes, the curve bends even if u's layer goes on straight, and the change
  // makes a crease edge.
  auto across = [&](int32_t a, int32_t b) {
    for (const StarCell& sc : star) {
      int hits = 0;
      uint8_t other = label;
      for (int k = 0; k < 4; ++k) {
        const int32_t x = sc.v[k];
        if (x == u || x == a || x == b) {
          ++hits;
        } else {
          other = in_.labels[x];
        }
      }
      if (hits == 3 && other != label) return int(other);
    }
    return int(label);
  };
  std::sort(faces_.begin(), faces_.end());
  // Constraint faces: hull faces (key 0), and faces of three feature vertices of u's label that
  // border a two-label cell (key 1): the voxel-interface layer u belongs to. A face of the band
  // between two cells of one label is inside the region: counted, it made every vertex of a
  // band two vertices deep look like a corner.
  struct CFace {
    int32_t a, b;
    uint8_t key;
    Eigen::Vector3d normal;
  };
  std::array<CFace, 64> cf;
  int ncf = 0;
  patch_.clear();
  const Eigen::Vector3d pu(pos_[3 * u], pos_[3 * u + 1], pos_[3 * u + 2]);
  for (size_t i = 0; i < faces_.size();) {
    size_t j = i + 1;
    while (j < faces_.size() && SameFace(faces_[j], faces_[i])) ++j;
    const int32_t a = FaceA(faces_[i]), b = FaceB(faces_[i]);
    int key = -1;
    if (j - i == 1) {
      key = 0;
    } else if (j - i > 2) {
      return Freedom::kPinned;  // non-manifold around u: leave it alone
    } else if (feature && (FaceMixed(faces_[i]) || FaceMixed(faces_[i + 1])) &&
               (flags_[a] & kFeatureVertex) && (flags_[b] & kFeatureVertex) &&
               in_.labels[a] == label && in_.labels[b] == label) {
      key = junction ? 1 + across(a, b) : 1;
    }
    if (key >= 0) {
      if (ncf == int(cf.size())) return Freedom::kPinned;
      const Eigen::Vector3d pa(pos_[3 * a], pos_[3 * a + 1], pos_[3 * a + 2]);
      const Eigen::Vector3d pb(pos_[3 * b], pos_[3 * b + 1], pos_[3 * b + 2]);
      cf[ncf++] = {a, b, uint8_t(key), (pa - pu).cross(pb - pu).normalized()};
      patch_.push_back(a);
      patch_.push_back(b);
    }
    i = j;
  }
  if (ncf == 0) {
    // Off every layer: a thin line or a dot of its label (pinned), or inside its region.
    return feature ? Freedom::kPinned : Freedom::kFree;
  }
  if (feature) {
    // A feature vertex moves only within (or along the rim of) its own interface layer.
    bool on_layer = false;
    for (int f = 0; f < ncf; ++f) on_layer |= cf[f].key >= 1;
    if (!on_layer) return Freedom::kPinned;
  }
  auto parallel = [](const Eigen::Vector3d& m, const Eigen::Vector3d& n) {
    return m.cross(n).squaredNorm() < 1e-8;
  };
  // Edges (u, x) of the constraint faces: smooth if exactly two faces of one key in one plane.
  std::array<std::pair<int32_t, int16_t>, 128> edges;
  int ne = 0;
  for (int f = 0; f < ncf; ++f) {
    edges[ne++] = {cf[f].a, int16_t(f)};
    edges[ne++] = {cf[f].b, int16_t(f)};
  }
  std::sort(edges.begin(), edges.begin() + ne);
  int32_t crease[2];
  int ncrease = 0;
  for (int i = 0; i < ne;) {
    int j = i + 1;
    while (j < ne && edges[j].first == edges[i].first) ++j;
    const bool smooth = j - i == 2 && cf[edges[i].second].key == cf[edges[i + 1].second].key &&
                        parallel(cf[edges[i].second].normal, cf[edges[i + 1].second].normal);
    if (!smooth) {
      if (ncrease == 2) return Freedom::kPinned;
      crease[ncrease++] = edges[i].first;
    }
    i = j;
  }
  if (ncrease == 0) {
    for (int f = 1; f < ncf; ++f) {
      if (cf[f].key != cf[0].key || !parallel(cf[f].normal, cf[0].normal)) return Freedom::kPinned;
    }
    return Freedom::kPlanar;
  }
  if (ncrease != 2) return Freedom::kPinned;
  const Eigen::Vector3d d0 =
      Eigen::Vector3d(pos_[3 * crease[0]], pos_[3 * crease[0] + 1], pos_[3 * crease[0] + 2]) - pu;
  const Eigen::Vector3d d1 =
      Eigen::Vector3d(pos_[3 * crease[1]], pos_[3 * crease[1] + 1], pos_[3 * crease[1] + 2]) - pu;
  if (d0.dot(d1) >= 0 || !parallel(d0.normalized(), d1.normalized())) return Freedom::kPinned;
  along[0] = crease[0];
  along[1] = crease[1];
  return Freedom::kCrease;
}

// Every target x of a collapse u -> x the constraint rules allow, once each, in s.candidates
// (unsorted, costs not set). s.star must hold u's cells.
void FieldEngine::Targets(int32_t u, Scratch& s) {
  s.candidates.clear();
  if (window_ != nullptr && window_->frozen != nullptr && window_->frozen[u]) return;
  int32_t along[2];
  const Freedom freedom = Classify(u, s, along);
  if (freedom == Freedom::kPinned) return;
  if (freedom == Freedom::kCrease) {
    for (int32_t x : along) s.candidates.push_back({0, x});
    return;
  }
  s.seen.Reset(3 * s.star.size() + s.patch.size());
  auto add = [&](int32_t x) {
    if (!s.seen.Insert(x)) return;
    s.candidates.push_back({0, x});
    // The cost reads x's position and value next (SetCosts): ask for both now.
    __builtin_prefetch(&pos_[3 * int64_t(x)]);
    __builtin_prefetch(&in_.scalars[x]);
  };
  if (freedom == Freedom::kPlanar) {
    for (int32_t x : s.patch) add(x);  // neighbours joined to u by a face of its patch
  } else {
    for (const StarCell& sc : s.star) {
      const int32_t* t = sc.v;
      for (int k = 0; k < 4; ++k) {
        if (t[k] != u) add(t[k]);
      }
    }
  }
}

// Every collapse u -> x the constraint rules allow, with its cost (not yet checked for flips),
// in s.candidates (unsorted). s.star must hold u's cells.
void FieldEngine::Candidates(int32_t u, Scratch& s) {
  Targets(u, s);
  SetCosts(u, &s.candidates);
}

void FieldEngine::SetCosts(int32_t u, std::vector<Candidate>* candidates) const {
  Source src;
  LoadSource(u, &src);
  for (Candidate& c : *candidates) c.cost = Cost(src, c.target);
}

bool FieldEngine::Score(int32_t u, Scratch& s, double* cost, int32_t* best) {
  GatherStar(u, &s.star);
  Candidates(u, s);
  Candidate first{std::numeric_limits<double>::infinity(), -1}, second = first;
  for (const Candidate& c : s.candidates) {
    if (first.target < 0 || Cheaper(c, first)) {
      second = first;
      first = c;
    } else if (second.target < 0 || Cheaper(c, second)) {
      second = c;
    }
  }
  *cost = first.cost;
  *best = first.target;
  st_[u].second = second.target;
  st_[u].second_cost = second.cost;
  return *best >= 0;
}

void FieldEngine::PreparePlanes(int32_t u, const Star& star, Worker& w) {
  // With u in slot k of a positive cell, the other three in this order span a positively
  // oriented face: V(p) = n . (p - a) / 6 with n = (b - a) x (c - a) (even permutations of the
  // slots keep the sign).
  static constexpr int kOthers[4][3] = {{2, 1, 3}, {0, 2, 3}, {0, 3, 1}, {0, 1, 2}};
  w.planes.resize(star.size());
  w.failed = -1;
  for (size_t i = 0; i < star.size(); ++i) {
    const int32_t* t = star[i].v;
    int k = 0;
    while (k < 3 && t[k] != u) ++k;
    const float* a = &pos_[3 * int64_t(t[kOthers[k][0]])];
    const float* b = &pos_[3 * int64_t(t[kOthers[k][1]])];
    const float* c = &pos_[3 * int64_t(t[kOthers[k][2]])];
    const double e0[3] = {double(b[0]) - a[0], double(b[1]) - a[1], double(b[2]) - a[2]};
    const double e1[3] = {double(c[0]) - a[0], double(c[1]) - a[1], double(c[2]) - a[2]};
    Plane& pl = w.planes[i];
    pl.n[0] = e0[1] * e1[2] - e0[2] * e1[1];
    pl.n[1] = e0[2] * e1[0] - e0[0] * e1[2];
    pl.n[2] = e0[0] * e1[1] - e0[1] * e1[0];
    pl.min = pl.n[0] * a[0] + pl.n[1] * a[1] + pl.n[2] * a[2] + 6 * min_volume_;
  }
}

// The volume part of rule 6 alone: every cell that keeps u (now at v's place) keeps at least
// min_volume. PreparePlanes(u, star) must have run.
bool FieldEngine::InKernel(int32_t v, const Star& star, Worker& w) {
  const double pv[3] = {pos_[3 * int64_t(v)], pos_[3 * int64_t(v) + 1], pos_[3 * int64_t(v) + 2]};
  auto keeps = [&](size_t i) {
    const int32_t* t = star[i].v;
    if (t[0] == v || t[1] == v || t[2] == v || t[3] == v) return true;  // deleted
    return w.planes[i].Keeps(pv);
  };
  // The cell that failed the last try first: the targets of one vertex tend to fail on the same
  // cell.
  if (w.failed >= 0 && !keeps(size_t(w.failed))) return false;
  for (size_t i = 0; i < star.size(); ++i) {
    if (!keeps(i)) {
      w.failed = int32_t(i);
      return false;
    }
  }
  return true;
}

// Rule 6 of the paper for a half-edge collapse: every cell that keeps u (now at v's place) stays
// positive with at least min_volume; no vertex loses its last cell. PreparePlanes(u, star) must
// have run: a refused best target is followed by tries of every other candidate on the same
// star, and each try is then one dot product per cell instead of a determinant.
bool FieldEngine::Valid(int32_t u, int32_t v, const Star& star, Worker& w) {
  int32_t lost[64][2];
  int nlost = 0;
  w.guarded.clear();
  const double pv[3] = {pos_[3 * int64_t(v)], pos_[3 * int64_t(v) + 1], pos_[3 * int64_t(v) + 2]};
  for (size_t i = 0; i < star.size(); ++i) {
    const int32_t* t = star[i].v;
    if (t[0] == v || t[1] == v || t[2] == v || t[3] == v) {
      for (int k = 0; k < 4; ++k) {
        if (t[k] == u || t[k] == v) continue;
        int j = 0;
        while (j < nlost && lost[j][0] != t[k]) ++j;
        if (j == nlost) {
          if (nlost == 64) return false;
          lost[nlost][0] = t[k];
          lost[nlost++][1] = 0;
        }
        ++lost[j][1];
      }
      continue;
    }
    if (!w.planes[i].Keeps(pv)) return false;
    if (max_cos_ < 1) w.guarded.push_back(&star[i]);
  }
  for (int i = 0; i < nlost; ++i) {
    if (valence_[lost[i][0]] <= lost[i][1]) return false;
  }
  // The shape guard, once every cheaper test passed (most tries fail on volume): a moved cell
  // may not get a dihedral angle below the floor unless it had an even smaller one before
  // (cells of the input are never blocked by their own shape).
  for (const StarCell* sc : w.guarded) {
    const int32_t* t = sc->v;
    int32_t moved[4] = {t[0], t[1], t[2], t[3]};
    for (int k = 0; k < 4; ++k) {
      if (moved[k] == u) moved[k] = v;
    }
    if (!AboveFloor(moved)) {
      const double after = MaxDihedralCos(moved);
      if (after > max_cos_ && after > MaxDihedralCos(t)) return false;
    }
  }
  // Last, the label guard: it is the dearest test and the cheap ones refuse most tries.
  if (free_interfaces_ && !KeepsLabels(u, v, star, w)) return false;
  // The regions' topology after the labels, although it is cheaper: of the collapses it refuses,
  // the label guard refuses nearly all too (README "Region topology"), and in this order it only
  // runs on the collapses across an interface that the label guard lets through.
  if (free_interfaces_ && !KeepsRegionTopology(u, v, star, w)) {
    w.relocated_for = {-1, -1};  // KeepsLabels' relocation is for a collapse that is not made
    return false;
  }
  return true;
}

// The link conditions for the label regions (InterfaceMode::kFree; README "Region topology").
// Under the label rule of tet_mesh.h (DominantLabelSlot) the region of a label L deformation-
// retracts onto K_L, the full subcomplex of the vertices labelled L: in every cell the points
// where L's weight is largest slide straight onto the cell's L face. So a collapse keeps each
// region's topology if it keeps each K_L's homotopy type.
// - u -> v of one label: the mesh's own link condition, which rule 6 guarantees (v sees every
//   face of u's link from inside), holds in every full subcomplex too. Nothing to check.
// - u of label A -> v of label B: K_A loses u, glued to the rest along u's link in K_A; K_B gains
//   the cone from v over T, the B part of u's link, glued along T itself (v and its B neighbours
//   in the link are in T already). Other labels gain and lose nothing. Both keep their homotopy
//   type if those two parts of u's link are contractible.
// u's link is a triangulated sphere (a disk on the hull), so a part of it other than the whole
// has no 2-cycle: contractible iff non-empty, connected and of Euler characteristic 1. The A part
// never holds v; the B part is the whole sphere when u has no neighbour of label A, and its
// Euler characteristic 2 refuses the collapse, rightly (K_B would gain a cone over a sphere).
bool FieldEngine::KeepsRegionTopology(int32_t u, int32_t v, const Star& star, Worker& w) const {
  const uint8_t* labels = in_.labels.data();
  if (labels[u] == labels[v]) return true;
  auto contractible = [&](uint8_t label) {
    std::vector<int32_t>& vs = w.link_vertices;
    std::vector<uint64_t>& es = w.link_edges;
    vs.clear();
    es.clear();
    int64_t triangles = 0;
    for (const StarCell& sc : star) {
      int32_t o[3], n = 0;
      for (int k = 0; k < 4; ++k) {
        if (sc.v[k] != u && labels[sc.v[k]] == label) o[n++] = sc.v[k];
      }
      triangles += n == 3;
      for (int i = 0; i < n; ++i) {
        vs.push_back(o[i]);
        for (int j = i + 1; j < n; ++j) {
          es.push_back(uint64_t(uint32_t(std::min(o[i], o[j]))) << 32 |
                       uint32_t(std::max(o[i], o[j])));
        }
      }
    }
    std::sort(vs.begin(), vs.end());
    vs.erase(std::unique(vs.begin(), vs.end()), vs.end());
    std::sort(es.begin(), es.end());
    es.erase(std::unique(es.begin(), es.end()), es.end());
    if (vs.empty() || int64_t(vs.size()) - int64_t(es.size()) + triangles != 1) return false;
    // Connected: union-find over the part's vertices, by their rank in vs.
    std::vector<int32_t>& parent = w.link_parent;
    parent.resize(vs.size());
    for (size_t i = 0; i < vs.size(); ++i) parent[i] = int32_t(i);
    auto find = [&](int32_t x) {
      while (parent[x] != x) x = parent[x] = parent[parent[x]];
      return x;
    };
    auto rank = [&](int32_t x) {
      return int32_t(std::lower_bound(vs.begin(), vs.end(), x) - vs.begin());
    };
    size_t components = vs.size();
    for (uint64_t e : es) {
      const int32_t a = find(rank(int32_t(e >> 32))), b = find(rank(int32_t(e & 0xffffffffu)));
      if (a != b) {
        parent[a] = b;
        --components;
      }
    }
    return components == 1;
  };
  return contractible(labels[u]) && contractible(labels[v]);
}

// The label guard (InterfaceMode::kFree): whether every sample the collapse u -> v moves into new
// cells (u's own, and those listed in u's cells) lies in a new cell and gets its own label in
// every new cell that holds it (README "Interfaces free inside their voxels"). On success
// w.relocated says which new cell each sample goes to (Collapse lists them there). Valid's
// other tests must have passed: every new cell is positive.
bool FieldEngine::KeepsLabels(int32_t u, int32_t v, const Star& star, Worker& w) {
  w.relocated.clear();
  w.relocated_for = {-1, -1};
  std::vector<NewCell>& cells = w.new_cells;
  cells.clear();
  const uint8_t* labels = in_.labels.data();
  // The sample lists' heads are scattered loads: asked for now, read after the new cells are set.
  for (const StarCell& sc : star) __builtin_prefetch(&bucket_head_[sc.id]);
  bool one_label = true;  // every vertex of u's star has u's label
  for (const StarCell& sc : star) {
    const int32_t* t = sc.v;
    for (int k = 0; k < 4; ++k) one_label &= labels[t[k]] == labels[u];
    if (t[0] == v || t[1] == v || t[2] == v || t[3] == v) continue;  // deleted
    NewCell& c = cells.emplace_back();
    c.id = sc.id;
    for (int k = 0; k < 4; ++k) c.v[k] = t[k] == u ? v : t[k];
    double p[4][3];
    for (int k = 0; k < 4; ++k) {
      for (int d = 0; d < 3; ++d) p[k][d] = pos_[3 * int64_t(c.v[k]) + d];
    }
    c.framed = false;
    for (int d = 0; d < 3; ++d) {
      c.lo[d] = std::min({p[0][d], p[1][d], p[2][d], p[3][d]});
      c.hi[d] = std::max({p[0][d], p[1][d], p[2][d], p[3][d]});
    }
    // A point within the inside tolerance of the cell is within that share of its largest
    // height, itself at most its longest box side times sqrt(3).
    const double widen = 2 * (kMetricInside + kInsideSlack) *
                         std::max({c.hi[0] - c.lo[0], c.hi[1] - c.lo[1], c.hi[2] - c.lo[2]});
    for (int d = 0; d < 3; ++d) {
      c.lo[d] -= widen;
      c.hi[d] += widen;
    }
    c.mixed = false;
    for (int k = 0; k < 4; ++k) {
      c.labels[k] = labels[c.v[k]];
      c.mixed |= c.labels[k] != c.labels[0];
    }
  }
  // The barycentric frame of a new cell: a = its first vertex, r = the rows of T^-1.
  auto frame = [&](NewCell& c) {
    double p[4][3];
    for (int k = 0; k < 4; ++k) {
      for (int d = 0; d < 3; ++d) p[k][d] = pos_[3 * int64_t(c.v[k]) + d];
    }
    double e[3][3];
    for (int k = 0; k < 3; ++k) {
      for (int d = 0; d < 3; ++d) e[k][d] = p[k + 1][d] - p[0][d];
    }
    Cross(e[1], e[2], c.r[0]);
    Cross(e[2], e[0], c.r[1]);
    Cross(e[0], e[1], c.r[2]);
    const double det = Dot(e[0], c.r[0]);
    for (int k = 0; k < 3; ++k) {
      for (int d = 0; d < 3; ++d) c.r[k][d] /= det;
    }
    for (int d = 0; d < 3; ++d) c.a[d] = p[0][d];
    c.framed = true;
  };
  // One sample: false if it would leave the new cells or get another label in one of them.
  auto place = [&](int32_t s) {
    const double q[3] = {pos_[3 * int64_t(s)], pos_[3 * int64_t(s) + 1], pos_[3 * int64_t(s) + 2]};
    const uint8_t own = labels[s];
    int32_t home = -1;
    for (NewCell& c : cells) {
      if (q[0] < c.lo[0] || q[0] > c.hi[0] || q[1] < c.lo[1] || q[1] > c.hi[1] || q[2] < c.lo[2] ||
          q[2] > c.hi[2]) {
        continue;
      }
      if (!c.framed) frame(c);
      const double d[3] = {q[0] - c.a[0], q[1] - c.a[1], q[2] - c.a[2]};
      double l[4];
      l[1] = Dot(c.r[0], d);
      l[2] = Dot(c.r[1], d);
      l[3] = Dot(c.r[2], d);
      l[0] = 1.0 - l[1] - l[2] - l[3];
      const double lowest = std::min({l[0], l[1], l[2], l[3]});
      if (lowest < -(kMetricInside + kInsideSlack)) continue;
      if (home < 0 && lowest >= -(kMetricInside - kInsideSlack)) home = c.id;
      // Every new cell has the samples' label (they had it before): the first home is the answer.
      if (one_label) {
        if (home >= 0) break;
        continue;
      }
      if (!c.mixed) {
        if (c.labels[0] != own) return false;
        continue;
      }
      const double mine = LabelWeight(c.labels, l, own);
      double other = 0;
      for (int k = 0; k < 4; ++k) {
        if (c.labels[k] != own) other = std::max(other, LabelWeight(c.labels, l, c.labels[k]));
      }
      if (!(mine > other + kLabelMargin)) return false;
    }
    if (home < 0) return false;
    w.relocated.emplace_back(s, home);
    return true;
  };
  // The samples first, asking for their positions and labels on the way (each is a removed
  // vertex, somewhere in the arrays): then u's own sample is placed while those loads are under
  // way. The lists are walked side by side, one step of each in turn, so that their next-links
  // (a load that misses the cache at nearly every step) are fetched several at a time. The order
  // of the samples changes nothing: each must pass, and where each goes does not depend on the
  // others.
  std::vector<int32_t>& samples = w.samples;
  std::vector<int32_t>& heads = w.heads;
  samples.clear();
  heads.clear();
  for (const StarCell& sc : star) {
    const int32_t s = bucket_head_[sc.id];
    if (s >= 0) {
      heads.push_back(s);
      __builtin_prefetch(&sample_next_[s]);
    }
  }
  while (!heads.empty()) {
    size_t n = 0;
    for (int32_t s : heads) {
      samples.push_back(s);
      __builtin_prefetch(&pos_[3 * int64_t(s)]);
      __builtin_prefetch(&labels[s]);
      const int32_t next = sample_next_[s];
      if (next >= 0) {
        heads[n++] = next;
        __builtin_prefetch(&sample_next_[next]);
      }
    }
    heads.resize(n);
  }
  if (!place(u)) return false;
  for (int32_t s : samples) {
    if (!place(s)) return false;
  }
  w.relocated_for = {u, v};
  return true;
}

int64_t FieldEngine::Collapse(int32_t u, int32_t v, const Star& star, Worker& w) {
  int64_t removed = 0;
  std::vector<int32_t>& touched = w.touched;
  touched.clear();
  if (free_interfaces_) {
    // The samples of u's cells (and u's own) go to the new cells KeepsLabels found for them.
    // Valid's last try was this one in every caller; should another try come between, redo it.
    if (w.relocated_for != std::make_pair(u, v)) KeepsLabels(u, v, star, w);
    for (const StarCell& sc : star) bucket_head_[sc.id] = -1;
    for (const auto& [sample, cell] : w.relocated) {
      sample_next_[sample] = bucket_head_[cell];
      bucket_head_[cell] = sample;
    }
    w.relocated_for = {-1, -1};
  }
  for (const StarCell& sc : star) {
    const int32_t c = sc.id;
    int32_t t[4] = {sc.v[0], sc.v[1], sc.v[2], sc.v[3]};
    if (t[0] == v || t[1] == v || t[2] == v || t[3] == v) {
      dead_.SetShared(c);
      ++removed;
      for (int k = 0; k < 4; ++k) --valence_[t[k]];
    } else {
      for (int k = 0; k < 4; ++k) {
        if (t[k] == u) t[k] = v;
      }
      ++valence_[v];
      if (slab_axis_ >= 0) WidenRange(c, pos_[3 * int64_t(v) + slab_axis_]);
    }
    for (int k = 0; k < 4; ++k) {
      if (t[k] != u) touched.push_back(t[k]);
    }
  }
  // Every vertex merged into u so far (u's class) is v now; this is what moves u's cells to v.
  for (int32_t r = u; r >= 0; r = class_next_[r]) root_[r] = v;
  class_next_[class_tail_[v]] = u;
  class_tail_[v] = class_tail_[u];
  // Q_v += Q_u, moved from u's origin to v's.
  const double d[4] = {double(pos_[3 * v]) - pos_[3 * u], double(pos_[3 * v + 1]) - pos_[3 * u + 1],
                       double(pos_[3 * v + 2]) - pos_[3 * u + 2],
                       double(in_.scalars[v]) - in_.scalars[u]};
  double moved[kQuadricSize];
  TranslateQuadric(&quadric_[kQuadricSize * int64_t(u)], d, moved);
  float* qv = &quadric_[kQuadricSize * int64_t(v)];
  for (int k = 0; k < kQuadricSize; ++k) qv[k] = float(double(qv[k]) + moved[k]);
  valence_[u] = 0;
  st_[u].cost = std::numeric_limits<double>::infinity();
  ++st_[u].version;  // its queue entries are stale
  w.scratch.seen.Reset(touched.size());
  size_t n = 0;
  for (int32_t x : touched) {
    if (w.scratch.seen.Insert(x)) touched[n++] = x;
  }
  touched.resize(n);
  return removed;
}

bool FieldEngine::InTerritory(const Star& star) const {
  for (const StarCell& sc : star) {
    for (int k = 0; k < 4; ++k) {
      if (frontier_[sc.v[k]] == kOnFrontier) return false;
    }
  }
  return true;
}

// The greedy loop on w's queue, until w has removed `limit` cells, the queue is empty or its
// cheapest entry costs more than `stop_cost`. With in_block, u collapses only if no vertex of its
// star is a frontier vertex; then every vertex it reads or writes is its block's own.
Drained FieldEngine::Drain(Worker& w, int64_t limit, float stop_cost, bool in_block,
                           double tolerance, const CancelToken* cancel) {
  while (w.removed < limit) {
    if (w.heap.empty()) return Drained::kEmpty;
    const HeapEntry e = w.heap.top();
    if (e.cost > stop_cost) return Drained::kStopCost;
    w.heap.pop();
    const int32_t u = e.vertex;
    if (e.version != st_[u].version || root_[u] != u) continue;
    if (st_[u].stale) {
      const double old_cost = st_[u].cost;
      const int32_t old_best = st_[u].best;
      if (!Rescore(u, w)) continue;
      if (st_[u].cost != old_cost || st_[u].best != old_best) {
        Push(u, w);
        continue;
      }
    }
    if ((++w.pops & 0xffff) == 0 && cancel != nullptr && cancel->cancelled()) {
      return Drained::kCancelled;
    }
    if (tolerance > 0) {
      const double wt = quadric_[kQuadricSize * int64_t(u) + kWeightEntry];
      if (wt > 0 && std::sqrt(st_[u].cost / wt) > tolerance) {
        w.tolerance_hit = true;
        st_[u].blocked = 1;
        continue;
      }
    }
    // u's cells, once: the validity checks, the fallback's candidates and the collapse share it.
    const Star& star = w.scratch.star;
    GatherStar(u, &w.scratch.star);
    // Outside its block's territory u waits (still queued) for a round with other cuts.
    if (in_block && !InTerritory(star)) continue;
    PreparePlanes(u, star, w);
    int32_t v = st_[u].best;
    double cost = st_[u].cost;
    if (!Valid(u, v, star, w)) {
      ++w.invalid_tries;
      // The cheapest valid one of the other targets. The volume test first: most tries fail it
      // (a blocked vertex fails them all: 2.7 M times on Colin27 at 50 %), and only the targets
      // that pass need a cost and the rest of the checks.
      Targets(u, w.scratch);
      std::vector<Candidate>& candidates = w.scratch.candidates;
      size_t n = 0;
      for (const Candidate& c : candidates) {
        if (c.target != v && InKernel(c.target, star, w)) candidates[n++] = c;
      }
      candidates.resize(n);
      SetCosts(u, &candidates);
      std::sort(candidates.begin(), candidates.end(), Cheaper);
      v = -1;
      for (const Candidate& c : candidates) {
        if (Valid(u, c.target, star, w)) {
          v = c.target;
          cost = c.cost;
          break;
        }
      }
      if (v < 0) {
        st_[u].blocked = 1;
        continue;
      }
      if (!w.heap.empty() && float(cost) > w.heap.top().cost) {
        // The best valid target costs more than the next vertex in the queue: wait for it.
        st_[u].cost = cost;
        st_[u].best = v;
        Push(u, w);
        ++w.requeued;
        continue;
      }
    }
    const bool u_free = st_[u].flags == 0;
    if (!u_free) ++w.constrained_moves;
    const int64_t deleted = Collapse(u, v, star, w);
    w.removed += deleted;
    ++w.collapses;
    if (w.log != nullptr) w.log->push_back({u, v, deleted, float(cost)});
    const double wt = quadric_[kQuadricSize * int64_t(u) + kWeightEntry];
    w.last_error = wt > 0 ? std::sqrt(std::max(0.0, cost) / wt) : 0;
    w.max_error = std::max(w.max_error, w.last_error);
    // Every vertex whose neighbourhood changed is re-scored now, so the queue order is exact.
    // For a free vertex x only two of its candidates can have changed: u is gone and v may be
    // new (Q_x and every position are unchanged), so unless u was its best one comparison
    // does. v (its quadric grew) and constrained vertices (their patch changed) are re-scored.
    w.changed.swap(w.touched);
    // The loop below is bound by cache misses on these scattered records: ask for them first.
    for (int32_t x : w.changed) {
      __builtin_prefetch(&quadric_[kQuadricSize * int64_t(x)]);
      __builtin_prefetch(&st_[x]);
    }
    for (const int32_t x : w.changed) {
      QueueState& xs = st_[x];
      if (xs.second == u) xs.second = -1;  // u is gone
      const bool was_blocked = xs.blocked;
      xs.blocked = 0;  // its star changed: worth another try
      if (u_free && x != v && xs.flags != 0 && !was_blocked && xs.best >= 0) {
        // A free vertex's collapse changes no constraint face, so x's patch, candidates and
        // their costs are unchanged; only its validity may differ: re-checked when popped.
        xs.stale = 1;
        continue;
      }
      if (x != v && xs.flags == 0 && xs.best == u && xs.second >= 0 && xs.second != v) {
        // Its best target is gone; the runner-up and v are the only contenders (every other
        // candidate's cost is unchanged and was not below the runner-up's).
        const double c = Cost(x, v);
        if (c < xs.second_cost || (c == xs.second_cost && v < xs.second)) {
          xs.cost = c;
          xs.best = v;
        } else {
          xs.cost = xs.second_cost;
          xs.best = xs.second;
        }
        xs.second = -1;  // unknown now: the next loss of the best re-scores fully
        Push(x, w);
        continue;
      }
      if (x != v && xs.flags == 0 && xs.best != u && xs.best >= 0) {
        const double c = Cost(x, v);
        if (c < xs.cost || (c == xs.cost && v < xs.best)) {
          xs.second = xs.best;
          xs.second_cost = xs.cost;
          xs.cost = c;
          xs.best = v;
          Push(x, w);
        } else {
          if (xs.second >= 0 && (c < xs.second_cost || (c == xs.second_cost && v < xs.second))) {
            xs.second = v;
            xs.second_cost = c;
          }
          if (was_blocked) Push(x, w);  // a blocked vertex has no queue entry
        }
        continue;
      }
      const double old_cost = xs.cost;
      const int32_t old_best = xs.best;
      if (Rescore(x, w)) {
        // An unchanged score keeps its queue entry (unless it was blocked: it has none).
        if (was_blocked || xs.cost != old_cost || xs.best != old_best) Push(x, w);
      } else {
        ++xs.version;
      }
    }
  }
  return Drained::kLimit;
}

namespace {
// Adds w's counts to *to.
void AddCounts(const Worker& w, Worker* to) {
  to->removed += w.removed;
  to->collapses += w.collapses;
  to->pops += w.pops;
  to->invalid_tries += w.invalid_tries;
  to->requeued += w.requeued;
  to->constrained_moves += w.constrained_moves;
  to->max_error = std::max(to->max_error, w.max_error);
  to->tolerance_hit |= w.tolerance_hit;
}
}  // namespace

// Parallel rounds (README "Parallel rounds"): the mesh is cut into slabs along the axis SlabAxis
// picks; in each round every slab runs the greedy loop on its own queue up to a common cost,
// touching only its own vertices and cells, so the slabs run on any number of threads with the
// same result. Every other round the cuts sit halfway between the last ones. Returns the cells
// removed.
int64_t FieldEngine::ParallelRounds(int64_t target, const ProgressFn& progress,
                                    const CancelToken* cancel, Worker* totals,
                                    absl::Status* status) {
  if (nv_ == 0) return 0;
  float lo[3], hi[3];
  for (int k = 0; k < 3; ++k) lo[k] = hi[k] = pos_[k];
  for (int64_t v = 1; v < nv_; ++v) {
    for (int k = 0; k < 3; ++k) {
      lo[k] = std::min(lo[k], pos_[3 * v + k]);
      hi[k] = std::max(hi[k], pos_[3 * v + k]);
    }
  }
  const double voxel = std::cbrt(voxel_volume_);
  const double slab_width = kMinSlabVoxels * voxel;  // the thinnest slab
  const int axis = SlabAxis(pos_, nv_, lo, hi, slab_width, threads_);
  const int slabs =
      int(std::clamp((double(hi[axis]) - lo[axis]) / slab_width, 1.0, double(kMaxSlabs)));
  if (slabs < 2) return 0;
  frontier_.resize(nv_);
  // No interval known yet: the first round scans every block.
  const int64_t range_blocks = ((nt_ - 1) >> kRangeShift) + 1;
  range_lo_.assign(range_blocks, -std::numeric_limits<float>::infinity());
  range_hi_.assign(range_blocks, std::numeric_limits<float>::infinity());
  slab_axis_ = axis;
  std::vector<Worker> workers(std::max(1, threads_));
  int64_t removed = 0;
  float last_stop_cost = 0;
  bool stuck = false;  // the last round removed less than 1/200 of the target
  for (int round = 0; round < kMaxRounds; ++round) {
    if (cancel != nullptr && cancel->cancelled()) {
      *status = CheckCancelled(cancel, "simplify");
      return removed;
    }
    const int64_t remaining = target - removed;
    if (remaining <= target / kSerialShare) break;
    // The queued vertices in id order, found in parallel (one list per range, joined in order).
    std::vector<QueuedVertex> queued_list;
    {
      const int64_t ranges = std::max(1, threads_);
      std::vector<std::vector<QueuedVertex>> parts(ranges);
      ParallelFor(ranges, threads_, [&](int64_t r0, int64_t r1) {
        for (int64_t r = r0; r < r1; ++r) {
          for (int64_t v = nv_ * r / ranges; v < nv_ * (r + 1) / ranges; ++v) {
            if (Queued(v)) parts[r].push_back({float(st_[v].cost), int32_t(v)});
          }
        }
      });
      for (const auto& part : parts)
        queued_list.insert(queued_list.end(), part.begin(), part.end());
    }
    if (queued_list.empty()) break;
    std::vector<float> costs(queued_list.size());
    for (size_t i = 0; i < queued_list.size(); ++i) costs[i] = queued_list[i].cost;
    // The common cost: as many queued vertices below it as a quarter of the collapses still
    // needed (at the cells per collapse seen so far). A round does every collapse below it,
    // the ones it makes cheap as well; a cost near the target's own (half the collapses, or
    // all) let the slabs spend the target on collapses the serial order would never make:
    // CT head 80 % 39.9 instead of 48.3 dB.
    const double per_collapse =
        totals->collapses > 0 ? double(removed) / double(totals->collapses) : 4.0;
    // After a round that removed little, only the vertices it did not reach count: the ones at
    // or below its cost could not collapse (waiting at a cut, or refused) and, counted, kept the
    // next cost at a double of the last (Colin27 50 %: seven more rounds of 0.1 M cells each).
    size_t reachable = costs.size();
    if (stuck) {
      reachable = size_t(
          std::partition(costs.begin(), costs.end(), [&](float c) { return c > last_stop_cost; }) -
          costs.begin());
      if (reachable == 0) break;
    }
    const size_t k =
        std::min(reachable - 1, size_t(std::max(1.0, double(remaining) / per_collapse / 4)));
    std::nth_element(costs.begin(), costs.begin() + k, costs.begin() + reachable);
    // At least twice the last round's cost: rounds that barely raise it do little work each.
    const float stop_cost = std::max(costs[k], 2 * last_stop_cost);
    last_stop_cost = stop_cost;
    // This round's cuts: at quantiles of the vertices that may collapse, so that the slabs get
    // about equal work; every other round halfway between (slabs + 1 slabs, the outer two half
    // as big), so that what waited at a cut is inside a slab next time. Cuts closer than
    // kMinCutVoxels to the previous one are dropped.
    std::vector<float> coords;
    for (const QueuedVertex& q : queued_list) {
      if (q.cost <= stop_cost) coords.push_back(pos_[3 * int64_t(q.v) + axis]);
    }
    const double shift = round % 2 == 0 ? 0.0 : 0.5;
    std::vector<float> cuts;
    size_t placed = 0;  // coords[0, placed) hold no value above coords[placed] (earlier cuts)
    for (int i = 1; i <= slabs; ++i) {
      const double q = (i - shift) / slabs;
      if (q >= 1) break;
      const size_t at = std::min(coords.size() - 1, size_t(q * double(coords.size())));
      std::nth_element(coords.begin() + placed, coords.begin() + at, coords.end());
      placed = at;
      const float cut = coords[at];
      if (cuts.empty() ? cut - lo[axis] >= kMinCutVoxels * voxel
                       : cut - cuts.back() >= kMinCutVoxels * voxel) {
        cuts.push_back(cut);
      }
    }
    const int blocks = int(cuts.size()) + 1;
    // The slab a coordinate of the slab axis falls in.
    auto owner = [&](float z) {
      return int(std::upper_bound(cuts.begin(), cuts.end(), z) - cuts.begin());
    };
    // The frontier: every vertex of a cell whose vertices lie in two slabs. Only blocks whose
    // interval a cut crosses can hold such a cell; their intervals are made tight again.
    std::fill(frontier_.begin(), frontier_.end(), 0);
    // Calls fn(t) with the current vertices t of every live cell of block b.
    auto for_live_cells = [&](int64_t b, auto&& fn) {
      for (int64_t c = b << kRangeShift; c < std::min(nt_, (b + 1) << kRangeShift); ++c) {
        if (dead_.TestShared(c)) continue;
        int32_t t[4];
        CellAt(int32_t(c), t);
        fn(t);
      }
    };
    std::vector<uint8_t> crossed(range_blocks, 0);
    ParallelFor(range_blocks, threads_, 16, [&](int64_t b0, int64_t b1) {
      for (int64_t b = b0; b < b1; ++b) {
        if (!(range_lo_[b] <= range_hi_[b]) || owner(range_lo_[b]) == owner(range_hi_[b])) {
          continue;
        }
        crossed[b] = 1;
        float lo_b = std::numeric_limits<float>::infinity(), hi_b = -lo_b;
        for_live_cells(b, [&](const int32_t* t) {
          float z[4];
          for (int j = 0; j < 4; ++j) {
            z[j] = pos_[3 * int64_t(t[j]) + axis];
            lo_b = std::min(lo_b, z[j]);
            hi_b = std::max(hi_b, z[j]);
          }
          const int o = owner(z[0]);
          if (owner(z[1]) == o && owner(z[2]) == o && owner(z[3]) == o) return;
          for (int j = 0; j < 4; ++j) {
            std::atomic_ref<uint8_t>(frontier_[t[j]]).store(kOnFrontier, std::memory_order_relaxed);
          }
        });
        range_lo_[b] = lo_b;
        range_hi_[b] = hi_b;
      }
    });
    // The vertices near the frontier: InTerritory refuses them all round (a collapse in a slab
    // neither adds a frontier vertex to a star nor removes a cell that holds one), so they are
    // not queued. Before, a quarter of the rounds' pops (CT head 50 %: 240,403 of 966,202)
    // gathered such a star only to put it aside. Only the cells of blocks with a frontier are
    // looked at; a near vertex missed elsewhere is still refused when popped.
    ParallelFor(range_blocks, threads_, 16, [&](int64_t b0, int64_t b1) {
      auto state = [&](int32_t x) {
        return std::atomic_ref<uint8_t>(frontier_[x]).load(std::memory_order_relaxed);
      };
      for (int64_t b = b0; b < b1; ++b) {
        if (!crossed[b]) continue;
        for_live_cells(b, [&](const int32_t* t) {
          if (state(t[0]) != kOnFrontier && state(t[1]) != kOnFrontier &&
              state(t[2]) != kOnFrontier && state(t[3]) != kOnFrontier) {
            return;
          }
          for (int j = 0; j < 4; ++j) {
            if (state(t[j]) == 0) {
              std::atomic_ref<uint8_t>(frontier_[t[j]])
                  .store(kNearFrontier, std::memory_order_relaxed);
            }
          }
        });
      }
    });
    // Each slab's queue: its vertices at or below the cost, neither on nor near the frontier, in
    // id order (listed per range of the list in parallel, joined in range order).
    std::vector<std::vector<HeapEntry>> entries(blocks);
    int64_t queued = 0;
    {
      const int64_t ranges = std::max(1, threads_);
      std::vector<std::vector<std::vector<HeapEntry>>> parts(
          ranges, std::vector<std::vector<HeapEntry>>(blocks));
      const int64_t listed = int64_t(queued_list.size());
      ParallelFor(ranges, threads_, [&](int64_t r0, int64_t r1) {
        for (int64_t r = r0; r < r1; ++r) {
          for (int64_t i = listed * r / ranges; i < listed * (r + 1) / ranges; ++i) {
            const QueuedVertex& q = queued_list[i];
            if (frontier_[q.v] || q.cost > stop_cost) continue;
            parts[r][owner(pos_[3 * int64_t(q.v) + axis])].push_back(
                {q.cost, q.v, ++st_[q.v].version});
          }
        }
      });
      for (int b = 0; b < blocks; ++b) {
        for (const auto& part : parts) {
          entries[b].insert(entries[b].end(), part[b].begin(), part[b].end());
        }
        queued += int64_t(entries[b].size());
      }
    }
    if (queued == 0) break;
    // Each slab may remove its share of what is left, by its share of the queued vertices.
    std::vector<int64_t> limit(blocks);
    for (int b = 0; b < blocks; ++b) {
      limit[b] = int64_t(double(remaining) * double(entries[b].size()) / double(queued));
    }
    // The biggest slabs first, so that the last one to finish is a small one.
    std::vector<int> order(blocks);
    for (int b = 0; b < blocks; ++b) order[b] = b;
    std::stable_sort(order.begin(), order.end(),
                     [&](int x, int y) { return entries[x].size() > entries[y].size(); });
    std::vector<Worker> done(blocks);
    std::vector<std::vector<LoggedCollapse>> slab_log(levels_ != nullptr ? blocks : 0);
    std::atomic<bool> cancelled{false};
    ParallelTasks(blocks, threads_, [&](int thread, int64_t task) {
      const int b = order[task];
      Worker& w = workers[thread];
      w.Reset(std::move(entries[b]));
      w.log = levels_ != nullptr ? &slab_log[b] : nullptr;
      if (Drain(w, limit[b], stop_cost, true, 0, cancel) == Drained::kCancelled) cancelled = true;
      AddCounts(w, &done[b]);
    });
    if (cancelled) {
      *status = CheckCancelled(cancel, "simplify");
      return removed;
    }
    if (levels_ != nullptr) {
      // The slabs' collapses touch disjoint vertices and cells, so any interleaving that keeps
      // each slab's order is a valid sequence with the same end. Merged by cost (ties to the
      // lower slab), a level cut inside this round takes the cheapest collapses of every slab
      // instead of all of the first slabs': the nearest to the serial order this round allows.
      std::vector<LoggedCollapse> merged;
      std::vector<size_t> next(blocks, 0);
      for (;;) {
        int best = -1;
        for (int b = 0; b < blocks; ++b) {
          if (next[b] == slab_log[b].size()) continue;
          if (best < 0 || slab_log[b][next[b]].cost < slab_log[best][next[best]].cost) best = b;
        }
        if (best < 0) break;
        merged.push_back(slab_log[best][next[best]++]);
      }
      *status = Record(merged);
      if (!status->ok()) return removed;
    }
    int64_t round_removed = 0, round_collapses = 0;
    for (const Worker& d : done) {
      round_removed += d.removed;
      round_collapses += d.collapses;
      AddCounts(d, totals);
    }
    removed += round_removed;
    Report(progress, {"simplify",
                      std::min(1.0, double(removed) / double(std::max<int64_t>(1, target))),
                      absl::StrFormat("round %d: %d collapses in %d slabs removed %d cells (%.1f%% "
                                      "of the input)",
                                      round + 1, round_collapses, blocks, round_removed,
                                      100.0 * double(removed) / double(std::max<int64_t>(1, nt_))),
                      {{"pass", 1.0}, {"cells_removed", double(removed)}, {"error", 0.0}}});
    // A round that removed little is followed by one at the cost of the vertices it did not
    // reach; if that one too removes little, the cuts leave too little for the slabs and the
    // serial loop does the rest.
    if (round_removed < target / 200) {
      if (stuck) break;
      stuck = true;
    } else {
      stuck = false;
    }
  }
  return removed;
}

absl::Status FieldEngine::Run(int64_t target, double tolerance, const ProgressFn& progress,
                              const CancelToken* cancel, SimplifyResult* result) {
  Setup();
  // The set-up takes seconds on large meshes: say what is happening before the first collapse.
  Report(progress,
         {"simplify",
          0.0,
          absl::StrFormat("field quadrics of %d vertices built and their collapses scored", nv_),
          {{"pass", 1.0}, {"cells_removed", 0.0}, {"error", 0.0}}});
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "simplify"));
  SimplifyPassStats stats;
  for (int64_t v = 0; v < nv_; ++v) stats.candidates += Queued(v);

  // The rounds need a target to pace them; with an error tolerance the serial loop does it all.
  Worker rounds;
  int64_t removed = 0;
  // A paced window (FieldWindow::stop_cost): the serial loop alone, up to the threshold.
  const bool paced = window_ != nullptr && window_->stop_cost >= 0;
  if (tolerance == 0 && !paced && target < nt_) {
    absl::Status status;
    removed = ParallelRounds(target, progress, cancel, &rounds, &status);
    slab_axis_ = -1;  // the serial loop keeps no intervals
    DECIMA_RETURN_IF_ERROR(status);
  }
  Worker w;
  std::vector<LoggedCollapse> serial_log;
  const bool log_costs = levels_ == nullptr && window_ != nullptr && window_->cost_log != nullptr;
  if (levels_ != nullptr || log_costs) w.log = &serial_log;
  if (log_costs) window_->cost_log->clear();
  {
    std::vector<HeapEntry> entries;
    for (int64_t v = 0; v < nv_; ++v) {
      if (Queued(v)) entries.push_back({float(st_[v].cost), int32_t(v), ++st_[v].version});
    }
    w.Reset(std::move(entries));
  }
  const int64_t step = std::max<int64_t>(1, target / 50);
  const float stop_cost =
      paced ? float(std::min<double>(window_->stop_cost, std::numeric_limits<float>::max()))
            : std::numeric_limits<float>::infinity();
  for (;;) {
    const int64_t limit = std::min(target - removed, w.removed + step);
    const Drained drained = Drain(w, limit, stop_cost, false, tolerance, cancel);
    if (drained == Drained::kCancelled) return CheckCancelled(cancel, "simplify");
    const int64_t total = removed + w.removed;
    Report(progress, {"simplify",
                      std::min(1.0, double(total) / double(std::max<int64_t>(1, target))),
                      absl::StrFormat("%d collapses removed %d cells (%.1f%% of the input)",
                                      rounds.collapses + w.collapses, total,
                                      100.0 * double(total) / double(std::max<int64_t>(1, nt_))),
                      {{"pass", 1.0}, {"cells_removed", double(total)}, {"error", w.last_error}}});
    // The log is handed on as it comes, so the window never holds it twice.
    if (levels_ != nullptr) DECIMA_RETURN_IF_ERROR(Record(serial_log));
    if (log_costs) {
      for (const LoggedCollapse& c : serial_log) {
        window_->cost_log->emplace_back(c.cost, int32_t(c.deleted));
      }
    }
    serial_log.clear();
    if (drained != Drained::kLimit || total >= target) break;
  }
  removed += w.removed;
  AddCounts(w, &rounds);
  stats.collapses = rounds.collapses;
  stats.cells_removed = removed;
  stats.rejected_flip = rounds.invalid_tries;
  stats.requeued = rounds.requeued;
  stats.other_point = rounds.constrained_moves;
  // With no serial collapse, the rounds' largest error stands for the last one (the slabs' last
  // collapses have no order among each other).
  stats.last_error = w.collapses > 0 ? w.last_error : rounds.max_error;
  result->pass_stats.push_back(stats);
  result->passes = 1;
  result->collapses = rounds.collapses;
  result->max_error = rounds.max_error;
  if (removed >= target) {
    result->stop_reason = StopReason::kTargetReached;
  } else {
    result->stop_reason =
        rounds.tolerance_hit ? StopReason::kErrorTolerance : StopReason::kNoValidCollapse;
  }
  if (levels_ != nullptr) {
    levels_->base_vertices = nv_;
    levels_->base_cells = nt_;
    levels_->exhausted = removed < target;
  }
  if (window_ != nullptr && window_->queued_costs != nullptr) {
    window_->queued_costs->clear();
    for (int64_t v = 0; v < nv_; ++v) {
      if (Queued(v)) window_->queued_costs->push_back(float(st_[v].cost));
    }
  }
  if (window_ != nullptr && free_interfaces_) {
    sample_home_.assign(nv_, -1);
    for (int64_t c = 0; c < nt_; ++c) {
      for (int32_t s = bucket_head_[c]; s >= 0; s = sample_next_[s]) sample_home_[s] = int32_t(c);
    }
  }
  ReleaseQueue();
  Finish(result);
  return absl::OkStatus();
}

absl::Status FieldEngine::Record(const std::vector<LoggedCollapse>& collapses) {
  for (const LoggedCollapse& c : collapses) {
    if (c.deleted > std::numeric_limits<uint16_t>::max()) {
      return absl::InternalError(absl::StrCat(
          "simplify: collapse ", c.u, " -> ", c.v, " deleted ", c.deleted,
          " cells, more than the level record holds (65535); run without record_levels_to"));
    }
    levels_->removed_vertex.push_back(c.u);
    levels_->survivor.push_back(c.v);
    levels_->cells_deleted.push_back(uint16_t(c.deleted));
  }
  return absl::OkStatus();
}

// Frees what only the collapse loop needs before Finish builds the output mesh: with both
// alive, the output was the peak of the whole simplification (about 1 GB of queue, quadrics
// and adjacency per 10 M input cells on top of the output).
void FieldEngine::ReleaseQueue() {
  auto release = [](auto& v) { std::decay_t<decltype(v)>().swap(v); };
  release(quadric_);
  release(st_);
  release(row_start_);
  release(row_len_);
  release(class_next_);
  release(class_tail_);
  release(cell_ids_);
  release(flags_);
  release(bucket_head_);
  release(sample_next_);
  release(frontier_);
  release(range_lo_);
  release(range_hi_);
}

void FieldEngine::Finish(SimplifyResult* result) {
  // On all threads, each over a fixed range of vertices or cells: per range a count, the counts
  // summed in range order into each range's first output slot, then every range fills its own
  // slots. The output is the same on any thread count (the serial version took 0.5 s on Colin27).
  const int64_t ranges = std::max(1, threads_);
  auto range_of = [&](int64_t n, int64_t r) {
    return std::pair<int64_t, int64_t>{n * r / ranges, n * (r + 1) / ranges};
  };
  // For the items i in [0, n) that `keep`: first[r] is the first output slot of range r's, and
  // first[ranges] their number.
  auto first_slots = [&](int64_t n, auto&& keep) {
    std::vector<int64_t> first(ranges + 1, 0);
    ParallelFor(ranges, threads_, [&](int64_t r0, int64_t r1) {
      for (int64_t r = r0; r < r1; ++r) {
        const auto [i0, i1] = range_of(n, r);
        for (int64_t i = i0; i < i1; ++i) first[r + 1] += keep(i);
      }
    });
    for (int64_t r = 0; r < ranges; ++r) first[r + 1] += first[r];
    return first;
  };
  auto live_vertex = [&](int64_t v) { return root_[v] == v && valence_[v] > 0; };
  auto live_cell = [&](int64_t t) { return !dead_.Test(t); };
  const std::vector<int64_t> first_vertex = first_slots(nv_, live_vertex);
  const int64_t n = first_vertex[ranges];
  std::vector<int32_t> index(nv_);
  TetMesh& out = result->mesh;
  out.positions.resize(3 * n);
  out.scalars.resize(n);
  out.labels.resize(n);
  out.interface_distance.resize(n);
  out.vertex_flags.resize(n);
  ParallelFor(ranges, threads_, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      const auto [v0, v1] = range_of(nv_, r);
      int64_t i = first_vertex[r];
      for (int64_t v = v0; v < v1; ++v) {
        if (!live_vertex(v)) {
          index[v] = -1;
          continue;
        }
        index[v] = int32_t(i);
        for (int k = 0; k < 3; ++k) out.positions[3 * i + k] = in_.positions[3 * v + k];
        out.scalars[i] = in_.scalars[v];
        out.labels[i] = in_.labels[v];
        out.interface_distance[i] = in_.interface_distance[v];
        out.vertex_flags[i] = in_.vertex_flags[v];
        ++i;
      }
    }
  });
  const std::vector<int64_t> first_cell = first_slots(nt_, live_cell);
  if (window_ != nullptr && window_->sample_home != nullptr) {
    // Input cell -> output cell, for the samples' buckets.
    std::vector<int32_t> cell_index(nt_, -1);
    for (int64_t t = 0, i = 0; t < nt_; ++t) {
      if (live_cell(t)) cell_index[t] = int32_t(i++);
    }
    std::vector<int32_t>& home = *window_->sample_home;
    home.assign(nv_, -1);
    for (int64_t v = 0; v < int64_t(sample_home_.size()); ++v) {
      if (sample_home_[v] >= 0) home[v] = cell_index[sample_home_[v]];
    }
    std::vector<int32_t>().swap(sample_home_);
  }
  out.tets.resize(4 * first_cell[ranges]);
  out.cell_regions.resize(first_cell[ranges]);
  ParallelFor(ranges, threads_, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      const auto [t0, t1] = range_of(nt_, r);
      int64_t i = first_cell[r];
      for (int64_t t = t0; t < t1; ++t) {
        if (!live_cell(t)) continue;
        int32_t c[4];
        CellAt(int32_t(t), c);
        for (int k = 0; k < 4; ++k) out.tets[4 * i + k] = index[c[k]];
        out.cell_regions[i] =
            CellRegion(in_.labels[c[0]], in_.labels[c[1]], in_.labels[c[2]], in_.labels[c[3]]);
        ++i;
      }
    }
  });
  result->vertex_map.resize(nv_);
  ParallelFor(nv_, threads_, 65536, [&](int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      // A vertex that left its class (ForEachCell) still points at the root it had then.
      int32_t r = int32_t(v);
      while (root_[r] != r) r = root_[r];
      result->vertex_map[v] = index[r];
    }
  });
}

std::vector<uint8_t> FieldEngine::Pinned() {
  Setup();
  Scratch s;
  std::vector<uint8_t> pinned(nv_);
  for (int64_t u = 0; u < nv_; ++u) {
    GatherStar(int32_t(u), &s.star);
    int32_t along[2];
    pinned[u] = Classify(int32_t(u), s, along) == Freedom::kPinned;
  }
  return pinned;
}

FieldCollapseCheck FieldEngine::CheckOne(int32_t u, int32_t v) {
  Setup();
  Worker w;
  GatherStar(u, &w.scratch.star);
  const Star& star = w.scratch.star;
  Targets(u, w.scratch);
  bool target = false;
  for (const Candidate& c : w.scratch.candidates) target |= c.target == v;
  if (!target) return FieldCollapseCheck::kNotATarget;
  PreparePlanes(u, star, w);
  const bool guard = free_interfaces_;
  free_interfaces_ = false;
  const bool valid = Valid(u, v, star, w);
  free_interfaces_ = guard;
  if (!valid) return FieldCollapseCheck::kInvalid;
  if (guard && !KeepsLabels(u, v, star, w)) return FieldCollapseCheck::kLabelChanged;
  if (guard && !KeepsRegionTopology(u, v, star, w)) return FieldCollapseCheck::kTopologyChanged;
  return FieldCollapseCheck::kAllowed;
}

}  // namespace

FieldCollapseCheck CheckFieldCollapse(const TetMesh& mesh, const SimplifyOptions& options,
                                      int32_t u, int32_t v) {
  FieldEngine engine(mesh, options, 1, nullptr);
  return engine.CheckOne(u, v);
}

std::vector<uint8_t> PinnedFieldVertices(const TetMesh& mesh, const SimplifyOptions& options) {
  FieldEngine engine(mesh, options, 1, nullptr);
  return engine.Pinned();
}

int SlabAxis(const float* positions, int64_t n, const float lo[3], const float hi[3], double width,
             int threads) {
  int longest = 0;
  for (int k = 1; k < 3; ++k) {
    if (hi[k] - lo[k] > hi[longest] - lo[longest]) longest = k;
  }
  int axis = longest;
  int64_t fewest = -1;
  for (int k = 0; k < 3; ++k) {
    if (double(hi[k]) - lo[k] < kSlabAxisShare * (double(hi[longest]) - lo[longest])) continue;
    // Runs of consecutive ids in one slab, with slabs of equal width (the cuts come later).
    auto slab = [&](int64_t v) { return int64_t((double(positions[3 * v + k]) - lo[k]) / width); };
    const auto runs = int64_t(BlockSum(
        n, threads, 65536, [&](int64_t v) { return v > 0 && slab(v) != slab(v - 1) ? 1.0 : 0.0; }));
    if (fewest < 0 || runs < fewest) {
      fewest = runs;
      axis = k;
    }
  }
  return axis;
}

absl::Status RunFieldSimplify(const TetMesh& mesh, const SimplifyOptions& options, int threads,
                              int64_t target, double tolerance, const ProgressFn& progress,
                              const CancelToken* cancel, SimplifyResult* result,
                              SimplifyLevels* levels) {
  FieldEngine engine(mesh, options, threads, levels);
  return engine.Run(target, tolerance, progress, cancel, result);
}

void FieldVertexFlags(const TetMesh& mesh, const SimplifyOptions& options, int threads,
                      std::vector<uint8_t>* flags) {
  *flags = mesh.vertex_flags;
  ApplyFeatureThreshold(options, mesh.interface_distance, flags);
  // With a label per vertex, the interface is the set of cells that hold two labels, and every
  // vertex of such a cell is on it. The distance threshold misses some: a 5-tet cell's diagonal
  // reaches a vertex 1.12 voxels from the level set (20,680 of the CT head's 141,494). Left
  // free, they moved and took the label boundary with them (mean Dice 0.998 at 90 %).
  // (In parallel: a flag is set, never cleared, so the order of the writes does not matter.)
  uint8_t* f = flags->data();
  ParallelFor(mesh.tet_count(), threads, 65536, [&](int64_t t0, int64_t t1) {
    mesh.ForEachCell(t0, t1, [&](int64_t, const int32_t* c) {
      if (!HoldsTwoLabels(mesh.labels.data(), c)) return;
      for (int k = 0; k < 4; ++k) {
        std::atomic_ref<uint8_t>(f[c[k]]).fetch_or(kFeatureVertex, std::memory_order_relaxed);
      }
    });
  });
}

absl::Status RunFieldSimplifyWindow(const TetMesh& mesh, const SimplifyOptions& options,
                                    int threads, int64_t target, const FieldWindow& window,
                                    const ProgressFn& progress, const CancelToken* cancel,
                                    SimplifyResult* result) {
  FieldEngine engine(mesh, options, threads, nullptr, &window);
  return engine.Run(target, 0, progress, cancel, result);
}

}  // namespace decima::simplify_internal
