#include "core/mesh/tetrahedralize.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/common/huge_pages.h"
#include "core/common/parallel.h"
#include "core/common/status.h"
#include "core/mesh/grid_tets.h"

namespace decima {
namespace {

// Writes mesh->tets and mesh->cell_regions from mesh->grid and the vertex labels, a slice of
// cubes per task.
void FillGridCells(TetMesh* mesh, int threads) {
  const GridTets& grid = *mesh->grid;
  const int64_t nx = grid.nx(), ny = grid.ny(), nz = grid.nz();
  const int64_t cubes = (nx - 1) * (ny - 1) * (nz - 1);
  AssignOnHugePages(&mesh->tets, cubes * 5 * 4, 0);
  mesh->cell_regions.resize(cubes * 5);
  const uint8_t* labels = mesh->labels.data();
  const int64_t slice_cells = 5 * (nx - 1) * (ny - 1);
  ParallelFor(nz - 1, threads, [&](int64_t k0, int64_t k1) {
    grid.ForEachCell(k0 * slice_cells, k1 * slice_cells, [&](int64_t t, const int32_t* v) {
      std::copy(v, v + 4, &mesh->tets[4 * t]);
      mesh->cell_regions[t] = CellRegion(labels[v[0]], labels[v[1]], labels[v[2]], labels[v[3]]);
    });
  });
}

}  // namespace

void GridVertexPositions(const Volume& image, float* out, int threads) {
  const int64_t nx = image.dims[0], ny = image.dims[1], nz = image.dims[2];
  const Eigen::Matrix3d linear = image.direction * image.spacing.asDiagonal();
  ParallelFor(nz, ResolveThreads(threads), [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) {
      for (int64_t j = 0; j < ny; ++j) {
        const Eigen::Vector3d row =
            image.origin + linear * Eigen::Vector3d(0, double(j), double(k));
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * (j + ny * k);
          const Eigen::Vector3d p = row + linear.col(0) * double(i);
          out[3 * v] = static_cast<float>(p.x());
          out[3 * v + 1] = static_cast<float>(p.y());
          out[3 * v + 2] = static_cast<float>(p.z());
        }
      }
    }
  });
}

void RestoreGridCells(TetMesh* mesh, int threads) {
  if (!mesh->cells_dropped) return;
  FillGridCells(mesh, ResolveThreads(threads));
  mesh->cells_dropped = false;
}

absl::StatusOr<TetMesh> Tetrahedralize(const Volume& image, const TetrahedralizeOptions& options,
                                       const ProgressFn& progress, const CancelToken* cancel) {
  const int64_t nx = image.dims[0], ny = image.dims[1], nz = image.dims[2];
  if (nx < 2 || ny < 2 || nz < 2) {
    return absl::InvalidArgumentError(absl::StrCat("tetrahedralize: volume ", Describe(image),
                                                   " needs at least 2 voxels along every axis"));
  }
  if (options.labels != nullptr &&
      (!SameGrid(image, *options.labels) || options.labels->type != VoxelType::kUInt8)) {
    return absl::InvalidArgumentError(
        "tetrahedralize: the label volume must be uint8 on the same grid as the image");
  }
  const int64_t cubes = (nx - 1) * (ny - 1) * (nz - 1);
  if (cubes * 5 * 4 > std::numeric_limits<int32_t>::max() ||
      image.voxel_count() > std::numeric_limits<int32_t>::max()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "tetrahedralize: ", Describe(image), " gives more cells than 32-bit indices address"));
  }
  const int64_t nv = image.voxel_count();
  const int threads = ResolveThreads(options.threads);

  TetMesh mesh;
  AssignOnHugePages(&mesh.positions, 3 * nv, 0.f);
  mesh.scalars = image.ToFloat();
  mesh.labels.assign(nv, 0);
  if (options.labels != nullptr) {
    std::copy_n(options.labels->data<uint8_t>(), nv, mesh.labels.begin());
  }
  mesh.interface_distance.resize(nv);
  mesh.vertex_flags.resize(nv);
  Report(progress, {"tetra", 0.0, "allocated", {}});

  // Vertices: one per voxel centre.
  GridVertexPositions(image, mesh.positions.data(), threads);
  const Eigen::Matrix3d linear = image.direction * image.spacing.asDiagonal();
  const float inf = std::numeric_limits<float>::infinity();
  ParallelFor(nz, threads, [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) {
      for (int64_t j = 0; j < ny; ++j) {
        const bool jk_edge = j == 0 || j == ny - 1 || k == 0 || k == nz - 1;
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * (j + ny * k);
          const float d = options.interface_distance ? options.interface_distance[v] : inf;
          mesh.interface_distance[v] = d;
          uint8_t flags = std::abs(d) <= options.feature_threshold_voxels ? kFeatureVertex : 0;
          if (jk_edge || i == 0 || i == nx - 1) flags |= kExteriorBoundaryVertex;
          mesh.vertex_flags[v] = flags;
        }
      }
    }
  });
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "tetrahedralize"));
  Report(progress, {"tetra", 0.3, "vertices placed", {}});

  // Cells: 5 per cube, cube c = i + (nx-1) * (j + (ny-1) * k) owns tets 5c .. 5c+4 (GridTets).
  mesh.grid = GridTets(nx, ny, nz, linear.determinant() < 0);
  if (options.cells) {
    FillGridCells(&mesh, threads);
  } else {
    mesh.cells_dropped = true;
  }
  DECIMA_RETURN_IF_ERROR(CheckCancelled(cancel, "tetrahedralize"));
  Report(progress, {"tetra",
                    1.0,
                    absl::StrCat(mesh.tet_count(), " tets"),
                    {{"vertices", double(nv)}, {"tets", double(mesh.tet_count())}}});
  return mesh;
}

}  // namespace decima
