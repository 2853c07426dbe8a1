#include "core/metrics/fidelity.h"
#include "core/common/parallel.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <map>
#include <optional>
#include <thread>

#include "absl/strings/str_cat.h"
#include "core/common/status.h"

namespace decima {
namespace {

// Cell loops run in ranges of at least this many cells (thread start-up is not free).
constexpr int64_t kCellChunk = 4096;

absl::Status CheckMesh(const TetMesh& m, const char* what) {
  const int64_t nv = m.vertex_count();
  if (int64_t(m.positions.size()) != 3 * nv || int64_t(m.labels.size()) != nv ||
      m.tets.size() % 4 != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("metrics: ", what, " mesh has inconsistent arrays (", m.scalars.size(),
                     " scalars, ", m.positions.size(), " position floats, ", m.labels.size(),
                     " labels, ", m.tets.size(), " tet indices)"));
  }
  for (int32_t v : m.tets) {
    if (v < 0 || v >= nv) {
      return absl::InvalidArgumentError(
          absl::StrCat("metrics: ", what, " mesh has vertex index ", v, " outside [0, ", nv, ")"));
    }
  }
  return absl::OkStatus();
}

// Barycentric frame of a cell in grid index space: x = v0 + T * (l1, l2, l3).
struct Frame {
  Eigen::Vector3d v0;
  Eigen::Matrix3d inverse;  // T^-1
  bool ok = false;
};

Frame MakeFrame(const Eigen::Vector3d q[4]) {
  Frame f;
  f.v0 = q[0];
  Eigen::Matrix3d t;
  t.col(0) = q[1] - q[0];
  t.col(1) = q[2] - q[0];
  t.col(2) = q[3] - q[0];
  const double det = t.determinant();
  const double scale = t.col(0).norm() * t.col(1).norm() * t.col(2).norm();
  if (!(std::abs(det) > 1e-12 * scale)) return f;
  f.inverse = t.inverse();
  f.ok = true;
  return f;
}

inline void Barycentric(const Frame& f, const Eigen::Vector3d& x, double l[4]) {
  const Eigen::Vector3d b = f.inverse * (x - f.v0);
  l[1] = b[0], l[2] = b[1], l[3] = b[2];
  l[0] = 1.0 - b[0] - b[1] - b[2];
}

}  // namespace

absl::StatusOr<GridResample> ResampleOnGrid(const Volume& grid, const TetMesh& mesh, int threads,
                                            double tolerance, const CancelToken* cancel) {
  DECIMA_RETURN_IF_ERROR(CheckMesh(mesh, "simplified"));
  const int64_t nx = grid.dims[0], ny = grid.dims[1], nz = grid.dims[2];
  if (nx < 1 || ny < 1 || nz < 1 || grid.voxel_count() > kMaxVoxels ||
      !(grid.spacing.minCoeff() > 0)) {
    return absl::InvalidArgumentError("metrics: the grid has invalid dims or spacing");
  }
  const int64_t np = grid.voxel_count(), nt = mesh.tet_count();
  threads = ResolveThreads(threads);
  // Physical -> continuous index coordinates.
  const Eigen::Matrix3d to_index = (grid.direction * grid.spacing.asDiagonal()).inverse();
  std::vector<std::atomic<int32_t>> owner(np);
  for (auto& o : owner) o.store(std::numeric_limits<int32_t>::max(), std::memory_order_relaxed);

  auto index_point = [&](int32_t v) {
    return Eigen::Vector3d(to_index * (mesh.Position(v) - grid.origin));
  };
  std::atomic<bool> cancelled{false};
  ParallelFor(nt, threads, kCellChunk, [&](int64_t b, int64_t e) {
    for (int64_t t = b; t < e; ++t) {
      if ((t & 0x3FFF) == 0 && cancel != nullptr && cancel->cancelled()) {
        cancelled = true;
        return;
      }
      Eigen::Vector3d q[4];
      for (int k = 0; k < 4; ++k) q[k] = index_point(mesh.tets[4 * t + k]);
      const Frame f = MakeFrame(q);
      if (!f.ok) continue;
      Eigen::Vector3d lo = q[0], hi = q[0];
      for (int k = 1; k < 4; ++k) lo = lo.cwiseMin(q[k]), hi = hi.cwiseMax(q[k]);
      int64_t r0[3], r1[3];
      for (int c = 0; c < 3; ++c) {
        r0[c] = std::max<int64_t>(0, int64_t(std::ceil(lo[c] - 1e-6)));
        r1[c] = std::min<int64_t>(grid.dims[c] - 1, int64_t(std::floor(hi[c] + 1e-6)));
      }
      for (int64_t k = r0[2]; k <= r1[2]; ++k) {
        for (int64_t j = r0[1]; j <= r1[1]; ++j) {
          for (int64_t i = r0[0]; i <= r1[0]; ++i) {
            double l[4];
            Barycentric(f, Eigen::Vector3d(double(i), double(j), double(k)), l);
            if (l[0] < -tolerance || l[1] < -tolerance || l[2] < -tolerance || l[3] < -tolerance)
              continue;
            std::atomic<int32_t>& o = owner[i + nx * (j + ny * k)];
            int32_t cur = o.load(std::memory_order_relaxed);
            while (int32_t(t) < cur &&
                   !o.compare_exchange_weak(cur, int32_t(t), std::memory_order_relaxed)) {
            }
          }
        }
      }
    }
  });
  if (cancelled) return absl::CancelledError("metrics: cancelled while resampling");

  GridResample out;
  out.values.assign(np, 0.f);
  out.labels.assign(np, 0);
  out.cell.assign(np, -1);
  ParallelFor(nz, threads, [&](int64_t k0, int64_t k1) {
    for (int64_t p = k0 * nx * ny; p < k1 * nx * ny; ++p) {
      const int32_t t = owner[p].load(std::memory_order_relaxed);
      if (t == std::numeric_limits<int32_t>::max()) continue;
      const int64_t i = p % nx, j = (p / nx) % ny, k = p / (nx * ny);
      Eigen::Vector3d q[4];
      for (int c = 0; c < 4; ++c) q[c] = index_point(mesh.tets[4 * int64_t(t) + c]);
      double l[4];
      Barycentric(MakeFrame(q), Eigen::Vector3d(double(i), double(j), double(k)), l);
      double value = 0;
      uint8_t label[4];
      for (int c = 0; c < 4; ++c) {
        value += l[c] * mesh.scalars[mesh.tets[4 * int64_t(t) + c]];
        label[c] = mesh.labels[mesh.tets[4 * int64_t(t) + c]];
      }
      out.values[p] = float(value);
      out.labels[p] = label[DominantLabelSlot(label, l)];
      out.cell[p] = t;
    }
  });
  (void)nz;
  return out;
}

MeshQuality MeasureQuality(const TetMesh& mesh, double degenerate_volume_mm3) {
  MeshQuality q;
  double min_angle = 180;
  for (int64_t t = 0; t < mesh.tet_count(); ++t) {
    const double vol = TetVolume(mesh, t);
    if (vol < 0) {
      ++q.inverted_cells;
    } else if (vol < degenerate_volume_mm3) {
      ++q.degenerate_cells;
    }
    Eigen::Vector3d p[4];
    for (int k = 0; k < 4; ++k) p[k] = mesh.Position(mesh.tets[4 * t + k]);
    const Frame f = MakeFrame(p);
    if (!f.ok) {
      min_angle = 0;
      continue;
    }
    // Gradients of the barycentric coordinates are inward face normals; the dihedral angle at
    // the edge opposite faces i and j is acos(-g_i . g_j / |g_i||g_j|).
    Eigen::Vector3d g[4];
    for (int k = 0; k < 3; ++k) g[k + 1] = f.inverse.row(k).transpose();
    g[0] = -(g[1] + g[2] + g[3]);
    for (int i = 0; i < 4; ++i) {
      for (int j = i + 1; j < 4; ++j) {
        const double c = -g[i].dot(g[j]) / (g[i].norm() * g[j].norm());
        min_angle = std::min(min_angle, std::acos(std::clamp(c, -1.0, 1.0)) * 180.0 / M_PI);
      }
    }
  }
  q.min_dihedral_deg = mesh.tet_count() > 0 ? min_angle : 0;
  return q;
}

FaceCounts CountFaces(const TetMesh& mesh, int threads) {
  // The faces of a positively oriented tet (v0, v1, v2, v3), each wound so its normal points out
  // of the cell. Two cells on opposite sides of a shared face wind it in opposite directions.
  static constexpr int kFaces[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(mesh);
  const int64_t nv = mesh.vertex_count();
  threads = ResolveThreads(threads);
  // One slot per range, summed in range order so the area is the same on every run.
  std::vector<std::pair<int64_t, FaceCounts>> partial(threads);
  std::atomic<int> next_slot{0};
  ParallelFor(nv, threads, kCellChunk, [&](int64_t begin, int64_t end) {
    auto& [range_begin, c] = partial[next_slot++];
    range_begin = begin;
    // The faces whose smallest vertex is v: the other two vertices (ascending) and whether the
    // outward winding is an even permutation of (v, a, b).
    struct Face {
      int32_t a, b;
      bool even;
      bool operator<(const Face& o) const { return a != o.a ? a < o.a : b < o.b; }
    };
    std::vector<Face> faces;
    for (int64_t v = begin; v < end; ++v) {
      faces.clear();
      for (int64_t i = adj.offsets[v]; i < adj.offsets[v + 1]; ++i) {
        const int32_t* t = &mesh.tets[4 * int64_t(adj.tet_ids[i])];
        for (const auto& f : kFaces) {
          int32_t w[3] = {t[f[0]], t[f[1]], t[f[2]]};
          // Rotate (an even permutation) so v comes first; skip faces without v or with a
          // smaller vertex (they are counted at that vertex).
          int at = -1;
          for (int k = 0; k < 3; ++k)
            if (w[k] == v) at = k;
          if (at < 0) continue;
          std::rotate(w, w + at, w + 3);
          if (w[1] < v || w[2] < v) continue;
          faces.push_back(w[1] < w[2] ? Face{w[1], w[2], true} : Face{w[2], w[1], false});
        }
      }
      std::sort(faces.begin(), faces.end());
      for (size_t i = 0; i < faces.size();) {
        size_t j = i + 1;
        while (j < faces.size() && faces[j].a == faces[i].a && faces[j].b == faces[i].b) ++j;
        if (j - i == 1) {
          ++c.boundary_faces;
          const Eigen::Vector3d p = mesh.Position(v);
          c.boundary_area_mm2 +=
              0.5 * (mesh.Position(faces[i].a) - p).cross(mesh.Position(faces[i].b) - p).norm();
        } else if (j - i == 2) {
          ++c.interior_faces;
          if (faces[i].even == faces[i + 1].even) ++c.folded_faces;
        } else {
          ++c.nonmanifold_faces;
        }
        i = j;
      }
    }
  });
  partial.resize(next_slot);
  std::sort(partial.begin(), partial.end(),
            [](const auto& x, const auto& y) { return x.first < y.first; });
  FaceCounts total;
  for (const auto& [range_begin, c] : partial) {
    total.boundary_faces += c.boundary_faces;
    total.interior_faces += c.interior_faces;
    total.nonmanifold_faces += c.nonmanifold_faces;
    total.folded_faces += c.folded_faces;
    total.boundary_area_mm2 += c.boundary_area_mm2;
  }
  return total;
}

absl::StatusOr<FieldError> MeasureFieldError(const Volume& image, const TetMesh& mesh, int threads,
                                             double inside_tolerance, const CancelToken* cancel,
                                             GridResample* resample) {
  DECIMA_ASSIGN_OR_RETURN(GridResample r,
                          ResampleOnGrid(image, mesh, threads, inside_tolerance, cancel));
  FieldError f;
  const int64_t np = image.voxel_count();
  const auto [lo, hi] = image.ValueRange();
  f.value_range = hi - lo;
  f.grid_points = np;
  double sq = 0;
  for (int64_t p = 0; p < np; ++p) {
    if (r.cell[p] < 0) continue;
    ++f.covered_points;
    const double e = double(r.values[p]) - image.ValueAt(p);
    sq += e * e;
    f.max_abs_error = std::max(f.max_abs_error, std::abs(e));
  }
  f.coverage = np > 0 ? double(f.covered_points) / double(np) : 0;
  f.rmse = f.covered_points > 0 ? std::sqrt(sq / double(f.covered_points)) : 0;
  f.psnr_db = f.rmse > 0 ? 20.0 * std::log10(f.value_range / f.rmse)
                         : std::numeric_limits<double>::infinity();
  if (resample != nullptr) *resample = std::move(r);
  return f;
}

absl::StatusOr<FeatureVertexCounts> CountFeatureVertices(const TetMesh& o,
                                                         const std::vector<int32_t>& vertex_map,
                                                         const TetMesh& simplified) {
  if (int64_t(vertex_map.size()) != o.vertex_count() ||
      int64_t(o.vertex_flags.size()) != o.vertex_count() ||
      int64_t(o.positions.size()) != 3 * o.vertex_count()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "metrics: vertex_map has ", vertex_map.size(), " entries and the original ",
        o.vertex_flags.size(), " vertex flags and ", o.positions.size(),
        " position floats, expected one (three) per original vertex (", o.vertex_count(), ")"));
  }
  FeatureVertexCounts m;
  // An output vertex that sits exactly where one of the feature vertices mapped to it was is
  // that vertex, unmoved; the others mapped to it were merged into it (removed). Only an
  // output vertex at none of their places counts one of them as moved. (Deciding by the
  // first vertex in index order instead called a vertex merged into a later one "moved".)
  const int64_t nout = simplified.vertex_count();
  auto same_place = [&](int64_t v, int32_t n) {
    return simplified.positions[3 * int64_t(n)] == o.positions[3 * v] &&
           simplified.positions[3 * int64_t(n) + 1] == o.positions[3 * v + 1] &&
           simplified.positions[3 * int64_t(n) + 2] == o.positions[3 * v + 2];
  };
  std::vector<uint8_t> kept(nout, 0);  // 1: a feature vertex stayed there; 2: one moved there
  for (int64_t v = 0; v < o.vertex_count(); ++v) {
    if (!(o.vertex_flags[v] & kFeatureVertex)) continue;
    const int32_t n = vertex_map[v];
    if (n >= 0 && n < nout && same_place(v, n)) kept[n] = 1;
  }
  for (int64_t v = 0; v < o.vertex_count(); ++v) {
    if (!(o.vertex_flags[v] & kFeatureVertex)) continue;
    ++m.vertices;
    const int32_t n = vertex_map[v];
    if (n < 0 || n >= nout) {
      ++m.removed;
    } else if (kept[n] == 1) {
      m.removed += !same_place(v, n);
    } else if (kept[n] == 0) {
      kept[n] = 2;
      ++m.moved;
    } else {
      ++m.removed;
    }
  }
  return m;
}

absl::StatusOr<FidelityMetrics> MeasureFidelity(const Volume& image, const TetMesh& simplified,
                                                const FidelityOptions& options,
                                                const CancelToken* cancel) {
  DECIMA_RETURN_IF_ERROR(Validate(image, "metrics: image"));
  DECIMA_RETURN_IF_ERROR(CheckMesh(simplified, "simplified"));
  if (options.labels != nullptr &&
      (!SameGrid(image, *options.labels) || options.labels->type != VoxelType::kUInt8)) {
    return absl::InvalidArgumentError(
        "metrics: the label volume must be uint8 on the same grid as the image");
  }
  if ((options.original == nullptr) != (options.vertex_map == nullptr)) {
    return absl::InvalidArgumentError(
        "metrics: the feature-vertex counts need both the original mesh and the vertex map");
  }
  if (options.feature_counts != nullptr && options.original != nullptr) {
    return absl::InvalidArgumentError(
        "metrics: the feature-vertex counts come from feature_counts or from the original mesh "
        "and the vertex map, not both");
  }
  if (options.original != nullptr) {
    DECIMA_RETURN_IF_ERROR(CheckMesh(*options.original, "original"));
    if (int64_t(options.vertex_map->size()) != options.original->vertex_count() ||
        int64_t(options.original->vertex_flags.size()) != options.original->vertex_count()) {
      return absl::InvalidArgumentError(absl::StrCat("metrics: vertex_map has ",
                                                     options.vertex_map->size(),
                                                     " entries, expected one per "
                                                     "original vertex (",
                                                     options.original->vertex_count(), ")"));
    }
  }
  if (!(options.degenerate_volume_fraction >= 0) || !(options.inside_tolerance >= 0)) {
    return absl::InvalidArgumentError(
        "metrics: degenerate_volume_fraction and inside_tolerance must be >= 0");
  }

  FidelityMetrics m;
  m.vertices = simplified.vertex_count();
  m.cells = simplified.tet_count();
  GridResample r;
  DECIMA_ASSIGN_OR_RETURN(
      const FieldError field,
      MeasureFieldError(image, simplified, options.threads, options.inside_tolerance, cancel, &r));
  const int64_t np = image.voxel_count();
  m.grid_points = field.grid_points;
  m.covered_points = field.covered_points;
  m.coverage = field.coverage;
  m.rmse = field.rmse;
  m.max_abs_error = field.max_abs_error;
  m.value_range = field.value_range;
  m.psnr_db = field.psnr_db;

  if (options.labels != nullptr) {
    const uint8_t* truth = options.labels->data<uint8_t>();
    int64_t truth_count[256] = {}, mesh_count[256] = {}, both[256] = {}, mismatch = 0;
    const int64_t nx = image.dims[0], ny = image.dims[1], nz = image.dims[2];
    double interface_sq = 0;
    for (int64_t p = 0; p < np; ++p) {
      ++truth_count[truth[p]];
      const bool covered = r.cell[p] >= 0;
      if (covered) ++mesh_count[r.labels[p]];
      if (covered && r.labels[p] == truth[p]) {
        ++both[truth[p]];
      } else {
        ++mismatch;
      }
      const int64_t i = p % nx, j = (p / nx) % ny, k = p / (nx * ny);
      const bool at_interface =
          (i > 0 && truth[p - 1] != truth[p]) || (i + 1 < nx && truth[p + 1] != truth[p]) ||
          (j > 0 && truth[p - nx] != truth[p]) || (j + 1 < ny && truth[p + nx] != truth[p]) ||
          (k > 0 && truth[p - nx * ny] != truth[p]) ||
          (k + 1 < nz && truth[p + nx * ny] != truth[p]);
      if (at_interface && covered) {
        const double e = double(r.values[p]) - image.ValueAt(p);
        interface_sq += e * e;
        ++m.interface_points;
      }
    }
    int truth_labels = 0;
    double dice_sum = 0;
    for (int l = 0; l < 256; ++l) {
      if (truth_count[l] == 0 && mesh_count[l] == 0) continue;
      RegionDice d{l, truth_count[l], mesh_count[l], both[l], 1.0};
      d.dice = 2.0 * double(both[l]) / double(truth_count[l] + mesh_count[l]);
      if (truth_count[l] > 0) ++truth_labels, dice_sum += d.dice;
      m.dice.push_back(d);
    }
    m.mean_dice = truth_labels > 0 ? dice_sum / truth_labels : 0;
    m.label_mismatch = np > 0 ? double(mismatch) / double(np) : 0;
    m.interface_rmse =
        m.interface_points > 0 ? std::sqrt(interface_sq / double(m.interface_points)) : 0;
  }

  // The resampling (9 bytes per grid point) is not read below: freed before the face adjacency
  // (CountFaces) is built, so the two are never resident together (issue 30).
  r = GridResample();

  std::optional<FeatureVertexCounts> counted;
  if (options.feature_counts == nullptr && options.original != nullptr) {
    DECIMA_ASSIGN_OR_RETURN(
        counted, CountFeatureVertices(*options.original, *options.vertex_map, simplified));
  }
  if (const FeatureVertexCounts* c = counted ? &*counted : options.feature_counts) {
    m.feature_vertices = c->vertices;
    m.feature_vertices_moved = c->moved;
    m.feature_vertices_removed = c->removed;
  }

  if (int64_t(simplified.interface_distance.size()) == simplified.vertex_count()) {
    // Each vertex of a two-label cell once, in vertex order (the sum does not depend on threads).
    std::vector<uint8_t> on_interface(simplified.vertex_count(), 0);
    for (int64_t c = 0; c < simplified.tet_count(); ++c) {
      const int32_t* t = &simplified.tets[4 * c];
      const uint8_t l = simplified.labels[t[0]];
      if (simplified.labels[t[1]] == l && simplified.labels[t[2]] == l &&
          simplified.labels[t[3]] == l) {
        continue;
      }
      for (int k = 0; k < 4; ++k) on_interface[t[k]] = 1;
    }
    double sum = 0;
    for (int64_t v = 0; v < simplified.vertex_count(); ++v) {
      const double d = std::abs(double(simplified.interface_distance[v]));
      if (!on_interface[v] || !std::isfinite(d)) continue;
      ++m.interface_vertices;
      sum += d;
      m.interface_distance_max_voxels = std::max(m.interface_distance_max_voxels, d);
    }
    m.interface_distance_mean_voxels =
        m.interface_vertices > 0 ? sum / double(m.interface_vertices) : 0;
  }

  const double voxel_volume = image.spacing.prod();
  const MeshQuality q =
      MeasureQuality(simplified, options.degenerate_volume_fraction * voxel_volume);
  m.inverted_cells = q.inverted_cells;
  m.degenerate_cells = q.degenerate_cells;
  m.min_dihedral_deg = q.min_dihedral_deg;
  const FaceCounts faces = CountFaces(simplified, options.threads);
  m.boundary_faces = faces.boundary_faces;
  m.interior_faces = faces.interior_faces;
  m.nonmanifold_faces = faces.nonmanifold_faces;
  m.folded_faces = faces.folded_faces;
  m.boundary_area_mm2 = faces.boundary_area_mm2;
  m.manifold = faces.nonmanifold_faces == 0 && faces.folded_faces == 0;

  m.mesh_bytes = options.mesh_bytes;
  m.voxel_bytes = int64_t(image.bytes.size());
  m.bytes_ratio = m.voxel_bytes > 0 ? double(m.mesh_bytes) / double(m.voxel_bytes) : 0;
  return m;
}

}  // namespace decima
